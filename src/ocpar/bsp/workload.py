"""A synthetic kernel for exercising the engine: tasks of known, unequal duration.

>>> spin(0.001)
0.001
"""

from __future__ import annotations

import time


def spin(seconds: float) -> float:
    """Keep the CPU busy for ``seconds`` of wall time (a stand-in for an inner solve of known
    length); returns ``seconds``."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass
    return seconds
