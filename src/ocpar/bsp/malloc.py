"""glibc malloc tuning for worker processes that run many small IPOPT solves.

Dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``. Any fixed trim threshold
switches off glibc's adaptive mmap threshold, so IPOPT/MUMPS get their 0.3–1.6 MB workspaces
from fresh ``mmap`` calls and give them back after every solve: ~13 mmap/munmap pairs and ~16
page faults per solve instead of ~1, and each small DMOC solve runs ~1.3x slower (measured on
this project's 2-core machine, in a Dask worker and in a plain process given the same
variable alike). Raising both thresholds above those sizes keeps the workspaces on the heap.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from functools import lru_cache

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 2**20
TRIM_THRESHOLD_BYTES = 64 * 2**20


@lru_cache(maxsize=1)
def keep_solver_workspaces_on_heap() -> bool:
    """Set glibc's mmap threshold to 32 MiB and trim threshold to 64 MiB in this process
    (once). Returns False where there is no glibc ``mallopt`` (other platforms)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok_mmap = mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    ok_trim = mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    return bool(ok_mmap and ok_trim)
