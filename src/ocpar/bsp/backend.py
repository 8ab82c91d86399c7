"""The engine's contract: one superstep = kernel applied to tasks, results in task order."""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

from ocpar.bsp.kernel import ChunkResult, KernelRef, kernel_name
from ocpar.bsp.partition import contiguous_blocks, longest_first, sticky_longest_first
from ocpar.bsp.trace import SuperstepTrace

#: How a superstep's tasks are assigned to workers when no cost estimates are given:
#: ``blocks`` (contiguous blocks of equal size) or ``lpt`` (longest-processing-time-first on
#: the previous superstep's measured task times, keeping each task on its previous worker
#: where that costs at most :data:`AFFINITY_TOLERANCE` of the makespan).
BALANCE_POLICIES = ("blocks", "lpt")
AFFINITY_TOLERANCE = 0.05



class BackendError(RuntimeError):
    """A backend could not be started (bad address, unreachable scheduler, too few workers)."""


def check_balance(balance: str) -> None:
    """Raise :class:`BackendError` unless ``balance`` is one of :data:`BALANCE_POLICIES`."""
    if balance not in BALANCE_POLICIES:
        raise BackendError(
            f"unknown balance policy {balance!r}; choose one of {', '.join(BALANCE_POLICIES)}")


class Backend(ABC):
    """A pool of ``workers`` that runs supersteps for a coordinator.

    Subclasses only say how chunks reach workers (:meth:`_run_chunks`); partitioning, ordering
    and timing are common. Use as a context manager, or call :meth:`close`.
    """

    name: str = "backend"

    def __init__(self, workers: int, balance: str = "blocks") -> None:
        check_balance(balance)
        self.workers = workers
        self.balance = balance
        self.traces: list[SuperstepTrace] = []
        self._last_kernel: str | None = None

    @property
    def is_coordinator(self) -> bool:
        """True in the process that runs the outer problem (always, except MPI ranks > 0)."""
        return True

    def superstep(
        self, kernel: KernelRef, tasks: Sequence[Any], costs: Sequence[float] | None = None
    ) -> list[Any]:
        """Run ``kernel`` on every task, one chunk per worker; wait for all (the barrier) and
        return the results in task order. Given estimated ``costs`` (one per task, any unit)
        tasks are assigned longest-first; otherwise by the backend's :attr:`balance` policy
        (see :data:`BALANCE_POLICIES`; ``lpt`` needs a previous superstep of the same kernel
        with the same number of tasks, task i being the same piece of work, and uses
        contiguous blocks until then). The assignment never changes the results. The
        superstep's timings are appended to :attr:`traces` (per-task times and workers in
        task order)."""
        name = kernel_name(kernel)
        tasks = list(tasks)
        if costs is not None:
            if len(costs) != len(tasks):
                raise ValueError(f"{len(costs)} costs for {len(tasks)} tasks")
            groups = longest_first(list(costs), self.workers)
        elif self.balance == "lpt" and self._repeats_last_superstep(name, len(tasks)):
            last = self.traces[-1]
            groups = sticky_longest_first(last.task_wall_s, self.workers, last.task_worker,
                                          AFFINITY_TOLERANCE)
        else:
            groups = [list(b) for b in contiguous_blocks(len(tasks), self.workers)]
        start = time.perf_counter()
        chunks = self._run_chunks(name, [[tasks[i] for i in group] for group in groups])
        wall = time.perf_counter() - start
        order = [i for group in groups for i in group]
        position = {task: k for k, task in enumerate(order)}
        worker_of = {i: w for w, group in enumerate(groups) for i in group}
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
                task_worker=[worker_of[i] for i in range(len(tasks))],
            )
        )
        self._last_kernel = name
        return results

    def _repeats_last_superstep(self, name: str, n_tasks: int) -> bool:
        return (self._last_kernel == name and bool(self.traces)
                and self.traces[-1].tasks == n_tasks and self.traces[-1].workers == self.workers)

    @abstractmethod
    def _run_chunks(self, name: str, chunks: list[list[Any]]) -> list[ChunkResult]:
        """Run chunk w on worker w; return the chunk results in worker order."""

    def close(self) -> None:  # noqa: B027 - backends without resources need no cleanup
        """Release workers (idempotent)."""

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
