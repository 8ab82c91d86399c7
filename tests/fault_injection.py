"""Test-only fault injection through the engine's kernel hook (``OCPAR_KERNEL_WRAPPER``, see
:mod:`ocpar.bsp.kernel`): the first attempt of a deterministic fraction of inner solves fails,
as a solver failing from a bad start would; the schemes' failure policies then retry.

:func:`enable` sets, for one test, ``OCPAR_KERNEL_WRAPPER=fault_injection:wrap``, the rate
``OCPAR_INJECT_FAILURES=RATE[:SEED]`` (RATE in [0, 1]) and puts this directory on
``PYTHONPATH``, so that MPI ranks and Dask worker processes started afterwards import the same
wrapper. Which solves fail depends only on the seed and the task's data, so runs on any backend
and worker count fail the same solves:

- :func:`ocpar.ocp.solve_task` and the batched :func:`ocpar.ocp.solve_tasks`: the task's first
  guess is replaced by a non-finite one, which the failure policy counts as a failed attempt
  (status ``Invalid_Guess``) before it retries from the task's fallback and the
  transcription's fallbacks;
- :func:`ocpar.macs.local_search.run_search`: the search fails at once (one evaluation).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Callable
from functools import lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np

ENVIRONMENT_VARIABLE = "OCPAR_INJECT_FAILURES"
WRAPPER = "fault_injection:wrap"
STATUS = "Injected_Failure"
TESTS = Path(__file__).resolve().parent


@lru_cache(maxsize=1)
def setting() -> tuple[float, int]:
    """(rate, seed) from the environment; (0, 0) when unset."""
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
    rate, seed = setting()
    if rate == 0.0:
        return False
    h = hashlib.blake2b(data, digest_size=8, key=str(seed).encode())
    return int.from_bytes(h.digest(), "little") / 2**64 < rate


def _inject(task: Any) -> Any:
    if injected(np.asarray(task.params, float).tobytes()):
        return dataclasses.replace(task, warm_start=np.full(1, np.nan), multipliers=None)
    return task


def _ocp_task(kernel: Callable[[Any], Any], task: Any) -> Any:
    return kernel(_inject(task))


def _ocp_tasks(kernel: Callable[[Any], Any], tasks: list[Any]) -> Any:
    return kernel([_inject(task) for task in tasks])


def _search_task(kernel: Callable[[Any], Any], task: Any) -> Any:
    from ocpar.macs.local_search import SearchResult

    key = b"".join(np.asarray(v, float).tobytes() for v in
                   (task.z0, task.p0, task.weights, task.utopia) if v is not None)
    if not injected(task.kind.encode() + key):
        return kernel(task)
    start = task.z0 if task.z0 is not None else np.full(0, np.nan)
    return SearchResult(z=start, objectives=np.full(task.problem.n_objectives, np.nan),
                        feasible=False, evaluations=1, status=STATUS, iterations=0,
                        solve_time_s=0.0)


def wrap(_name: str, kernel: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """The kernel hook: the inner-solve kernels with faults injected, others unchanged."""
    ref = f"{getattr(kernel, '__module__', '')}:{getattr(kernel, '__qualname__', '')}"
    if ref == "ocpar.ocp.contract:solve_task":
        return partial(_ocp_task, kernel)
    if ref == "ocpar.ocp.contract:solve_tasks":
        batched = partial(_ocp_tasks, kernel)
        batched.batched = True  # type: ignore[attr-defined]
        return batched
    if ref == "ocpar.macs.local_search:run_search":
        return partial(_search_task, kernel)
    return kernel


def enable(monkeypatch: Any, rate: str | None) -> None:
    """Switch injection on (``rate`` "RATE[:SEED]") or off (None) in this process and in the
    processes it starts from now on, through ``monkeypatch``."""
    from ocpar.bsp.kernel import WRAPPER_VARIABLE, resolve_kernel

    if rate is None:
        monkeypatch.delenv(ENVIRONMENT_VARIABLE, raising=False)
        monkeypatch.delenv(WRAPPER_VARIABLE, raising=False)
    else:
        monkeypatch.setenv(ENVIRONMENT_VARIABLE, rate)
        monkeypatch.setenv(WRAPPER_VARIABLE, WRAPPER)
        path = os.environ.get("PYTHONPATH", "")
        monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    setting.cache_clear()
    resolve_kernel.cache_clear()
