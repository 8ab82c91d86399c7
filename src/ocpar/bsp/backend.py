"""The engine's contract: one superstep = kernel applied to tasks, results in task order."""

from __future__ import annotations

import itertools
import time
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ocpar.bsp.columns import Columns, from_columns, to_columns
from ocpar.bsp.journal import Journal, digest
from ocpar.bsp.kernel import ChunkResult, KernelRef, kernel_name
from ocpar.bsp.partition import (
    AFFINITY_TOLERANCE,
    contiguous_blocks,
    longest_first,
    sticky_longest_first,
)
from ocpar.bsp.resident import STEP, ResidentSet
from ocpar.bsp.trace import SuperstepTrace

#: How a superstep's tasks are assigned to workers when no cost estimates are given:
#: ``blocks`` (contiguous blocks of equal size) or ``lpt`` (longest-processing-time-first on
#: the previous superstep's measured task times, keeping each task on its previous worker
#: where that costs at most :data:`~ocpar.bsp.partition.AFFINITY_TOLERANCE` of the makespan).
BALANCE_POLICIES = ("blocks", "lpt")


class RunCancelled(RuntimeError):
    """The run was asked to stop (its stop file appeared) at a superstep boundary."""


class BackendError(RuntimeError):
    """A backend could not be started (bad address, unreachable scheduler, too few workers)."""


class UnreadableRequest(RuntimeError):
    """A worker could not unpickle a request: a module or class the run's tasks need is
    missing there (the message names it, and the worker's host; :mod:`ocpar.bsp.channel`)."""


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
        #: Where supersteps are checkpointed and replayed from (:mod:`ocpar.bsp.journal`).
        self.journal: Journal | None = None
        #: If this file exists when a superstep is to start, the run stops there
        #: (:class:`RunCancelled`): how a detached job is cancelled, its checkpoint intact.
        self.stop_file: Path | None = None
        self._resident_sets: weakref.WeakSet[ResidentSet] = weakref.WeakSet()
        #: Resident sets' blocks move between supersteps when their estimated imbalance
        #: (max/mean load) exceeds 1 + this and the move pays (:mod:`ocpar.bsp.resident`);
        #: None: they stay the equal blocks of :func:`~ocpar.bsp.partition.contiguous_blocks`.
        self.resident_tolerance: float | None = AFFINITY_TOLERANCE

    @property
    def is_coordinator(self) -> bool:
        """True in the process that runs the outer problem (always, except MPI ranks > 0)."""
        return True

    @property
    def shares_files(self) -> bool:
        """Whether every worker sees the coordinator's file system, so that a worker may
        write its share of a run's output itself: here (one process, and MPI ranks, which
        run where ``mpirun`` put them: a job's output directory is one every rank sees),
        Dask's where its workers are on this host."""
        return True

    def superstep(
        self, kernel: KernelRef, tasks: Sequence[Any], costs: Sequence[float] | None = None,
        record: bool = True,
    ) -> list[Any]:
        """Run ``kernel`` on every task, one chunk per worker; wait for all (the barrier) and
        return the results in task order. Given estimated ``costs`` (one per task, any unit)
        tasks go out longest-first: where the backend has a shared queue (MPI, a kernel that
        is not batched) each worker takes the next task when it is free, elsewhere they are
        assigned in advance (:func:`~ocpar.bsp.partition.longest_first`); otherwise by the
        backend's :attr:`balance` policy
        (see :data:`BALANCE_POLICIES`; ``lpt`` needs a previous superstep of the same kernel
        with the same number of tasks, task i being the same piece of work, and uses
        contiguous blocks until then). The assignment never changes the results. The
        superstep's timings are appended to :attr:`traces` (per-task times and workers in
        task order), and the :attr:`journal` records it; with ``record`` False neither: work
        that is no step of the run (e.g. checking its answer), which a resumed run does
        again."""
        tasks = list(tasks)
        return self._superstep(kernel, len(tasks), lambda group: [tasks[i] for i in group],
                               costs, columns=False, record=record)

    def superstep_columns(
        self, kernel: KernelRef, tasks: Columns, costs: Sequence[float] | None = None
    ) -> Columns:
        """:meth:`superstep` with the tasks and the results in columnar form
        (:class:`~ocpar.bsp.columns.Columns`), for many small tasks: the coordinator then
        selects, joins and reorders whole columns instead of handling each task (~µs per
        superstep instead of ~5 µs per task). The kernel's results must be instances of one
        dataclass; at least one task."""
        if not isinstance(tasks, Columns) or len(tasks) == 0:
            raise ValueError("superstep_columns needs a non-empty Columns of tasks")
        return self._superstep(kernel, len(tasks), tasks.take, costs, columns=True)

    def resident(self, kernel: KernelRef, agents: int) -> ResidentSet:
        """A :class:`~ocpar.bsp.resident.ResidentSet` of ``agents`` agents whose states stay
        on this backend's workers, driven by the resident kernel ``kernel`` (see
        :mod:`ocpar.bsp.resident`); closed when the backend closes, if not before."""
        resident = ResidentSet(self, kernel, agents)
        self._resident_sets.add(resident)
        return resident

    def _resident_superstep(self, resident: ResidentSet, what: str, tasks: Columns | None,
                            reduce: str | None = None) -> Columns:
        """One superstep of ``resident`` (:meth:`ResidentSet.step` with its n ``tasks`` and
        optional ``reduce``r, or :meth:`ResidentSet.collect` with None): the agents on the
        workers of their slots' blocks (:attr:`ResidentSet.blocks`, whatever the
        :attr:`balance` policy), results in agent order (a reduced step's: in unit order),
        timed and journaled like any superstep. The results must be instances of one
        dataclass (as for :meth:`superstep_columns`)."""
        n = resident.agents
        if what == STEP:
            assert tasks is not None
            name = resident.kernel if reduce is None else f"{resident.kernel}>{reduce}"
            return self._superstep(name, n, tasks.take, None, columns=True,
                                   run=lambda: resident.run(STEP, tasks, reduce))
        return self._superstep(f"{resident.kernel}#{what}", n,
                               lambda _: (what, resident.version, n), None, columns=True,
                               run=lambda: resident.run(what, None))

    def _superstep(self, kernel: KernelRef, n: int, select: Callable[[list[int]], Any],
                   costs: Sequence[float] | None, columns: bool,
                   run: Callable[[], tuple[list[range], list[ChunkResult]]] | None = None,
                   record: bool = True) -> Any:
        """The superstep of ``kernel`` on ``n`` tasks, ``select(indices)`` giving those tasks
        (and, for all indices, what the journal's digest is of). ``run``: how a resident
        superstep runs its contiguous blocks (:meth:`_resident_superstep`) instead: the
        blocks and their chunk results. ``record`` False: neither traced nor journaled."""
        name = kernel_name(kernel)
        if record and self.stop_file is not None and self.stop_file.exists():
            raise RunCancelled(f"cancelled before superstep {len(self.traces)}")
        tasks_digest = None
        if record and self.journal is not None:
            tasks_digest = digest(select(list(range(n))))
            if (recorded := self.journal.replay(len(self.traces), name, tasks_digest)) is not None:
                self.traces.append(recorded.trace)
                self._last_kernel = name
                return recorded.results if columns else from_columns(recorded.results)
        if costs is not None and len(costs) != n:
            raise ValueError(f"{len(costs)} costs for {n} tasks")
        start = time.perf_counter()
        if run is not None:
            groups, chunks = run()
        elif costs is not None and self._queues(name):
            queue = sorted(range(n), key=lambda i: (-costs[i], i))
            taken, chunks = self._run_queue(name, select(queue))
            groups: list[list[int]] | list[range] = [[queue[k] for k in ks] for ks in taken]
        else:
            groups = self._assign(name, n, costs)
            chunks = self._run_chunks(name, [select(group) for group in groups])
        position = _positions(groups, n)  # position[i]: where task i's result is among the
        in_order = position is None        # chunks'; None for contiguous blocks (in order)
        if columns:
            packed = [to_columns(c.results) for c in chunks if len(c.results)]
            if not all(isinstance(p, Columns) for p in packed):
                raise TypeError(f"superstep_columns: the results of {name} are not instances "
                                "of one dataclass")
            results: Any = Columns.concat(packed)
            if not in_order:
                results = results.take(position)
        else:
            flat = [r for c in chunks for r in from_columns(c.results)]
            results = flat if in_order else [flat[i] for i in position.tolist()]

        def per_task(per_chunk: list[np.ndarray]) -> np.ndarray:
            values = np.concatenate([np.zeros(0), *per_chunk])
            return values if in_order else values[position]

        walls = per_task([c.task_wall_s for c in chunks])
        cpus = per_task([c.task_cpu_s for c in chunks])
        workers = np.repeat(np.arange(len(groups)), [len(g) for g in groups])
        if not in_order:
            workers = workers[position]
        wall = time.perf_counter() - start
        if not record:
            return results
        self.traces.append(
            SuperstepTrace(
                index=len(self.traces),
                tasks=n,
                wall_s=wall,
                worker_busy_s=[c.busy_s for c in chunks],
                worker_cpu_s=[c.cpu_s for c in chunks],
                worker_tasks=[len(g) for g in groups],
                worker_peak_rss_mb=[c.peak_rss_mb for c in chunks],
                task_wall_s=walls,
                task_cpu_s=cpus,
                task_worker=workers,
                worker_sent_bytes=[c.sent_bytes for c in chunks],
                worker_received_bytes=[c.received_bytes for c in chunks],
            )
        )
        self._last_kernel = name
        if self.journal is not None:
            self.journal.record(len(self.traces) - 1, name, tasks_digest, results,
                                self.traces[-1])
        return results

    def _assign(self, name: str, n: int, costs: Sequence[float] | None
                ) -> list[list[int]] | list[range]:
        """Task indices per worker, by the estimated ``costs`` or the :attr:`balance` policy."""
        if costs is not None:
            return longest_first(list(costs), self.workers)
        if self.balance == "lpt" and self._repeats_last_superstep(name, n):
            last = self.traces[-1]
            return sticky_longest_first(last.task_wall_s, self.workers, last.task_worker,
                                        AFFINITY_TOLERANCE)
        return contiguous_blocks(n, self.workers)

    def _repeats_last_superstep(self, name: str, n_tasks: int) -> bool:
        return (self._last_kernel == name and bool(self.traces)
                and self.traces[-1].tasks == n_tasks and self.traces[-1].workers == self.workers)

    def _queues(self, name: str) -> bool:
        """True if this backend runs a superstep of kernel ``name`` from a shared queue
        (:meth:`_run_queue`) when given costs."""
        return False

    def _run_queue(self, name: str, tasks: list[Any] | Columns
                   ) -> tuple[list[list[int]], list[ChunkResult]]:
        """Run the tasks, each worker taking the next one from a shared queue when it is free;
        return the positions each worker took (in the order it ran them) and the chunk results
        in worker order."""
        raise NotImplementedError

    @abstractmethod
    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        """Run chunk w (a list of tasks, or :class:`Columns`) on worker w; return the chunk
        results in worker order, each chunk's results as a list or as :class:`Columns`."""

    def close(self) -> None:
        """Release workers (idempotent)."""
        self._close_resident_sets()

    def _close_resident_sets(self) -> None:
        """Free the workers' memory of the resident sets still open (coordinator only)."""
        if self.is_coordinator:
            for resident in list(self._resident_sets):
                resident.close()

    def __enter__(self) -> Backend:
        return self

    def __exit__(self, *exc: object) -> None:
        """Make the journal's supersteps durable (however the block ends), then close."""
        try:
            if self.journal is not None:
                self.journal.flush()
        finally:
            self.close()


def _positions(groups: Sequence[Sequence[int]], n: int) -> np.ndarray | None:
    """Where each task's result lies among the workers' results concatenated (``groups``:
    worker w's task indices, in order), or None if they already run 0..n−1 in increasing
    order from group to group: contiguous blocks (ranges: checked in O(P))."""
    if all(isinstance(g, range) and g.step == 1 for g in groups):
        ends = [g for g in groups if len(g)]
        if (not ends or ends[0].start == 0) and all(
                a.stop == b.start for a, b in itertools.pairwise(ends)) \
                and sum(map(len, ends)) == n:
            return None
    order = np.fromiter(itertools.chain.from_iterable(groups), dtype=np.intp, count=n)
    if np.all(order[1:] > order[:-1]):
        return None
    position = np.empty(n, dtype=np.intp)
    position[order] = np.arange(n)
    return position
