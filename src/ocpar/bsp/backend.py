"""The engine's contract: one superstep = kernel applied to tasks, results in task order."""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

from ocpar.bsp.kernel import ChunkResult, KernelRef, kernel_name
from ocpar.bsp.partition import contiguous_blocks, longest_first
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

    def superstep(
        self, kernel: KernelRef, tasks: Sequence[Any], costs: Sequence[float] | None = None
    ) -> list[Any]:
        """Run ``kernel`` on every task, one chunk per worker; wait for all (the barrier) and
        return the results in task order. Chunks are contiguous blocks of equal size, or,
        given estimated ``costs`` (one per task, any unit), assigned longest-first to balance
        the workers. The superstep's timings are appended to :attr:`traces` (per-task times
        in task order)."""
        name = kernel_name(kernel)
        tasks = list(tasks)
        if costs is None:
            groups = [list(b) for b in contiguous_blocks(len(tasks), self.workers)]
        else:
            if len(costs) != len(tasks):
                raise ValueError(f"{len(costs)} costs for {len(tasks)} tasks")
            groups = longest_first(list(costs), self.workers)
        start = time.perf_counter()
        chunks = self._run_chunks(name, [[tasks[i] for i in group] for group in groups])
        wall = time.perf_counter() - start
        order = [i for group in groups for i in group]
        position = {task: k for k, task in enumerate(order)}
        flat = [r for chunk in chunks for r in chunk.results]
        walls = [t for chunk in chunks for t in chunk.task_wall_s]
        cpus = [t for chunk in chunks for t in chunk.task_cpu_s]
        results = [flat[position[i]] for i in range(len(tasks))]
        self.traces.append(
            SuperstepTrace(
                index=len(self.traces),
                tasks=len(tasks),
                wall_s=wall,
                worker_busy_s=[c.busy_s for c in chunks],
                worker_cpu_s=[c.cpu_s for c in chunks],
                worker_tasks=[len(c.results) for c in chunks],
                worker_peak_rss_mb=[c.peak_rss_mb for c in chunks],
                task_wall_s=[walls[position[i]] for i in range(len(tasks))],
                task_cpu_s=[cpus[position[i]] for i in range(len(tasks))],
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
