"""Kernels: plain importable functions of one task, named ``module:function``, run in chunks.

A *batched* kernel (attribute ``batched = True``, e.g. :func:`ocpar.ocp.solve_tasks`) is a
function of a list of tasks returning their results in order: a worker calls it once for its
whole chunk, and each task's time in the trace is the chunk's time shared equally. A batched
kernel that is also *columnar* (``columnar = True``) is given a chunk that arrives as
:class:`~ocpar.bsp.columns.Columns` as it is, and may return its results as ``Columns``: no
object per task on either side.

Extension hook: if the environment variable :data:`WRAPPER_VARIABLE` names a function
``module:function`` (importable in every process that solves), each kernel is resolved as
``wrapper(name, kernel)``, a callable of one task that replaces the kernel in this process
(for instance to inject faults, trace or count tasks). The coordinator's environment reaches
MPI ranks and the embedded Dask workers; on a Dask cluster, set it where the workers start.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import resource
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from ocpar.bsp.columns import Columns, from_columns, to_columns

KernelRef = str | Callable[[Any], Any]
#: Environment variable naming a kernel wrapper ``module:function`` (module docstring).
WRAPPER_VARIABLE = "OCPAR_KERNEL_WRAPPER"


def kernel_name(kernel: KernelRef) -> str:
    """``module:function`` name of a kernel given as a name or as a module-level function."""
    if isinstance(kernel, str):
        if ":" not in kernel:
            raise ValueError(f"kernel name must look like 'module:function', got {kernel!r}")
        return kernel
    module, qualname = getattr(kernel, "__module__", None), getattr(kernel, "__qualname__", "")
    if not module or "<" in qualname or "." in qualname:
        raise ValueError(
            f"kernel {kernel!r} is not a module-level function; workers cannot import it"
        )
    return f"{module}:{qualname}"


def _import(name: str) -> Callable[..., Any]:
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)


@lru_cache(maxsize=64)
def resolve_kernel(name: str) -> Callable[[Any], Any]:
    """Import the kernel ``module:function`` (once per process), wrapped by the function that
    :data:`WRAPPER_VARIABLE` names, if it names one."""
    kernel = _import(name)
    wrapper = os.environ.get(WRAPPER_VARIABLE, "").strip()
    if not wrapper:
        return kernel
    if ":" not in wrapper:
        raise ValueError(f"{WRAPPER_VARIABLE} must look like 'module:function', got {wrapper!r}")
    return _import(wrapper)(name, kernel)


@dataclass
class ChunkResult:
    """What one worker returns for its chunk of a superstep.

    ``results`` is a list, or :class:`~ocpar.bsp.columns.Columns` where a backend packed
    them; ``task_wall_s``/``task_cpu_s`` are per task (s, float arrays); ``busy_s``/``cpu_s``
    cover the
    whole chunk (with its unpacking and packing, where there is any);
    ``peak_rss_mb`` is the worker process's peak resident memory so far (MiB);
    ``sent_bytes``/``received_bytes`` the length of the coordinator's message with the chunk
    and of the reply, as the backend's transport counted them (0 where the chunk ran in the
    coordinator's process, or the transport does not count: Dask's ``tasks`` dispatch).
    """

    results: list[Any] | Columns
    task_wall_s: np.ndarray
    task_cpu_s: np.ndarray
    busy_s: float
    cpu_s: float
    peak_rss_mb: float
    sent_bytes: int = 0
    received_bytes: int = 0


def run_chunk(name: str, tasks: Sequence[Any] | Columns) -> ChunkResult:
    """Run kernel ``name`` on each task in order, timing each one (wall and CPU); a batched
    kernel on all tasks at once, a columnar one on the ``Columns`` as they are (module
    docstring)."""
    kernel = resolve_kernel(name)
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    if getattr(kernel, "batched", False):
        if isinstance(tasks, Columns) and len(tasks) and getattr(kernel, "columnar", False):
            results: Any = kernel(tasks)
        else:
            results = list(kernel(from_columns(tasks))) if len(tasks) else []
        busy, cpu = time.perf_counter() - start_wall, time.process_time() - start_cpu
        share = max(len(tasks), 1)
        return ChunkResult(results=results, task_wall_s=np.full(len(tasks), busy / share),
                           task_cpu_s=np.full(len(tasks), cpu / share), busy_s=busy,
                           cpu_s=cpu, peak_rss_mb=peak_rss_mb())
    results, walls, cpus = [], [], []
    for task in from_columns(tasks):
        t_wall, t_cpu = time.perf_counter(), time.process_time()
        results.append(kernel(task))
        walls.append(time.perf_counter() - t_wall)
        cpus.append(time.process_time() - t_cpu)
    return ChunkResult(
        results=results,
        task_wall_s=np.array(walls),
        task_cpu_s=np.array(cpus),
        busy_s=time.perf_counter() - start_wall,
        cpu_s=time.process_time() - start_cpu,
        peak_rss_mb=peak_rss_mb(),
    )


def run_packed_chunk(name: str, tasks: Columns | list[Any]) -> ChunkResult:
    """:func:`run_chunk` for backends that pickle chunks: the tasks arrive as
    :func:`~ocpar.bsp.columns.to_columns` made them, and the results leave the same way (as
    :class:`~ocpar.bsp.columns.Columns` where they are instances of one dataclass)."""
    resolve_kernel(name)  # importing it on first use is not the chunk's work
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    chunk = run_chunk(name, tasks)
    results = to_columns(chunk.results)
    return dataclasses.replace(chunk, results=results,
                               busy_s=time.perf_counter() - start_wall,
                               cpu_s=time.process_time() - start_cpu)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (ru_maxrss: KiB on Linux)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2**20 if sys.platform == "darwin" else 2**10)
