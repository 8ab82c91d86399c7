"""Synthetic kernels for exercising the engine: tasks of known, unequal duration, and real
inner solves made slow enough to interrupt (fault tests).

>>> spin(0.001)
0.001
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any


def spin(seconds: float) -> float:
    """Keep the CPU busy for ``seconds`` of wall time (a stand-in for an inner solve of known
    length); returns ``seconds``."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass
    return seconds


@dataclass(frozen=True)
class Delayed:
    """Run kernel ``kernel`` (``module:function``) on ``task`` after spinning ``seconds``."""

    seconds: float
    kernel: str
    task: Any


def delayed(task: Delayed) -> Any:
    """Kernel: :func:`spin`, then the wrapped kernel's result (identical to running it
    directly)."""
    from ocpar.bsp.kernel import resolve_kernel

    spin(task.seconds)
    return resolve_kernel(task.kernel)(task.task)
