"""A test-only fault hook: make the first attempt of a deterministic fraction of inner solves
fail, as a solver failing from a bad start would; the schemes' failure policies then retry.

Off unless the environment variable ``OCPAR_INJECT_FAILURES`` is set (to ``RATE`` or
``RATE:SEED``, RATE in [0, 1]) in the processes that solve (the coordinator's environment
reaches MPI ranks and embedded Dask workers). Which solves fail depends only on the seed and
the task's data, so runs on any backend and worker count fail the same solves.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache

ENVIRONMENT_VARIABLE = "OCPAR_INJECT_FAILURES"
STATUS = "Injected_Failure"


@lru_cache(maxsize=1)
def _setting() -> tuple[float, int]:
    text = os.environ.get(ENVIRONMENT_VARIABLE, "").strip()
    if not text:
        return 0.0, 0
    rate_text, _, seed_text = text.partition(":")
    try:
        rate, seed = float(rate_text), int(seed_text or 0)
    except ValueError:
        raise ValueError(f"{ENVIRONMENT_VARIABLE} must be RATE or RATE:SEED, got {text!r}") \
            from None
    if not 0.0 <= rate <= 1.0:
        raise ValueError(f"{ENVIRONMENT_VARIABLE} rate must be in [0, 1], got {rate}")
    return rate, seed


def injected(data: bytes) -> bool:
    """True if the first attempt of the solve with input ``data`` is to fail."""
    rate, seed = _setting()
    if rate == 0.0:
        return False
    h = hashlib.blake2b(data, digest_size=8, key=str(seed).encode())
    return int.from_bytes(h.digest(), "little") / 2**64 < rate
