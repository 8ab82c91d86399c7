"""The engine's contract: one superstep = kernel applied to tasks, results in task order."""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

from ocpar.bsp.kernel import ChunkResult, KernelRef, kernel_name
from ocpar.bsp.partition import contiguous_blocks
from ocpar.bsp.trace import SuperstepTrace


class BackendError(RuntimeError):
    """A backend could not be started (bad address, unreachable scheduler, too few workers)."""


class Backend(ABC):
    """A pool of ``workers`` that runs supersteps for a coordinator.

    Subclasses only say how chunks reach workers (:meth:`_run_chunks`); partitioning, ordering
    and timing are common. Use as a context manager, or call :meth:`close`.
    """

    name: str = "backend"

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self.traces: list[SuperstepTrace] = []

    @property
    def is_coordinator(self) -> bool:
        """True in the process that runs the outer problem (always, except MPI ranks > 0)."""
        return True

    def superstep(self, kernel: KernelRef, tasks: Sequence[Any]) -> list[Any]:
        """Run ``kernel`` on every task, one contiguous chunk per worker; wait for all (the
        barrier) and return the results in task order. The superstep's timings are appended
        to :attr:`traces`."""
        name = kernel_name(kernel)
        tasks = list(tasks)
        blocks = contiguous_blocks(len(tasks), self.workers)
        start = time.perf_counter()
        chunks = self._run_chunks(name, [[tasks[i] for i in block] for block in blocks])
        wall = time.perf_counter() - start
        results = [r for chunk in chunks for r in chunk.results]
        self.traces.append(
            SuperstepTrace(
                index=len(self.traces),
                tasks=len(tasks),
                wall_s=wall,
                worker_busy_s=[c.busy_s for c in chunks],
                worker_cpu_s=[c.cpu_s for c in chunks],
                worker_tasks=[len(c.results) for c in chunks],
                worker_peak_rss_mb=[c.peak_rss_mb for c in chunks],
                task_wall_s=[t for c in chunks for t in c.task_wall_s],
                task_cpu_s=[t for c in chunks for t in c.task_cpu_s],
            )
        )
        return results

    @abstractmethod
    def _run_chunks(self, name: str, chunks: list[list[Any]]) -> list[ChunkResult]:
        """Run chunk w on worker w; return the chunk results in worker order."""

    def close(self) -> None:  # noqa: B027 - backends without resources need no cleanup
        """Release workers (idempotent)."""

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
