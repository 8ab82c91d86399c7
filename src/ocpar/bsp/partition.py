"""How a superstep's tasks are split among workers."""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from numbers import Integral

import numpy as np

#: How much makespan the engine gives up to keep work in place: ``lpt`` keeps a task on its
#: previous worker where that costs at most this fraction of the makespan
#: (:func:`sticky_longest_first`), and a resident set's blocks move only when their estimated
#: imbalance (max/mean load) exceeds 1 + this (:mod:`ocpar.bsp.resident`).
AFFINITY_TOLERANCE = 0.05


def contiguous_blocks(n_tasks: int, n_workers: int) -> list[range]:
    """Split task indices 0..n_tasks-1 into n_workers contiguous blocks whose sizes differ by
    at most one. The first ``n_tasks % n_workers`` blocks get the extra task: under MPI worker
    0 is the coordinator's own process, whose chunk needs no messages (see
    :func:`longest_first`)."""
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    base, extra = divmod(n_tasks, n_workers)
    blocks, start = [], 0
    for w in range(n_workers):
        size = base + (1 if w < extra else 0)
        blocks.append(range(start, start + size))
        start += size
    return blocks


def cost_balanced_blocks(costs: Sequence[float] | np.ndarray, n_workers: int) -> list[range]:
    """Split indices 0..n-1 (n = ``len(costs)``) into n_workers contiguous blocks of nearly
    equal total estimated cost (``costs`` ≥ 0, one per index): boundary k is the index b whose
    prefix sum Σ_{i<b} costs[i] is closest to k/n_workers of the total (the lower one on a
    tie). Deterministic; equal costs give :func:`contiguous_blocks` where n_workers divides n
    (otherwise blocks whose sizes differ by at most one), all-zero costs give
    :func:`contiguous_blocks`. A block may be empty (an index whose cost outweighs a
    worker's share)."""
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    costs = np.asarray(costs, dtype=float)
    if costs.ndim != 1 or not np.all(np.isfinite(costs)) or np.any(costs < 0):
        raise ValueError("costs must be a 1-D sequence of finite numbers ≥ 0")
    prefix = np.concatenate([[0.0], np.cumsum(costs)])
    if prefix[-1] <= 0:
        return contiguous_blocks(len(costs), n_workers)
    targets = prefix[-1] * np.arange(1, n_workers) / n_workers
    above = np.minimum(np.searchsorted(prefix, targets), len(costs))  # first prefix ≥ target
    below = np.maximum(above - 1, 0)
    closer = np.where(targets - prefix[below] <= prefix[above] - targets, below, above)
    bounds = [0, *np.maximum.accumulate(closer).tolist(), len(costs)]
    return [range(a, b) for a, b in itertools.pairwise(bounds)]


#: Reduction units: a resident set of n agents is cut into units of ``unit_size(n)``
#: consecutive agents, at least this many units where n allows (module-level, so that a
#: unit's size depends on n alone, never on the worker count).
MIN_UNITS = 1024
#: ... and units of at most this many agents (a unit's row summarises them: the rows a
#: superstep's reduction returns grow like n / MAX_UNIT_SIZE).
MAX_UNIT_SIZE = 256


def unit_size(n: int) -> int:
    """Agents per reduction unit of a resident set of ``n`` agents: ⌊n / MIN_UNITS⌋ clipped to
    [1, MAX_UNIT_SIZE] (1 below 2 MIN_UNITS agents: every agent its own unit). A function of
    n alone: the units, and the sums over them, are the same on any number of workers."""
    return int(min(max(n // MIN_UNITS, 1), MAX_UNIT_SIZE))


def unit_blocks(n: int, n_workers: int, costs: Sequence[float] | np.ndarray | None = None
                ) -> list[range]:
    """Contiguous blocks of agents 0..n-1, one per worker, made of whole reduction units
    (:func:`unit_size`; the last unit may be shorter): :func:`contiguous_blocks` of the
    units, or, given each unit's estimated cost (⌈n / unit_size(n)⌉,),
    :func:`cost_balanced_blocks` of them. Every block starts at a unit's first agent."""
    size = unit_size(n)
    units = -(-n // size)
    if costs is None:
        blocks = contiguous_blocks(units, n_workers)
    else:
        if len(costs) != units:
            raise ValueError(f"{len(costs)} unit costs for {units} units of {n} agents")
        blocks = cost_balanced_blocks(costs, n_workers)
    return [range(min(b.start * size, n), min(b.stop * size, n)) for b in blocks]


def block_loads(costs: Sequence[float] | np.ndarray, blocks: Sequence[range]) -> np.ndarray:
    """The total of ``costs`` over each of the contiguous ``blocks`` (ranges of step 1)."""
    costs = np.asarray(costs, dtype=float)
    prefix = np.zeros(len(costs) + 1)
    np.cumsum(costs, out=prefix[1:])
    return prefix[[b.stop for b in blocks]] - prefix[[b.start for b in blocks]]


def longest_first(costs: list[float], n_workers: int) -> list[list[int]]:
    """Assign task indices to workers by longest-processing-time-first on the given cost
    estimates; ties go to the lowest-numbered least-loaded worker and to the lower task index,
    so the assignment is deterministic. Each worker's indices come back in increasing order.

    Worker 0 first because under MPI it is the coordinator's own process: its chunk is neither
    pickled nor sent, while another rank's tasks and results each cross a message (~0.1–0.4 ms
    on the 2-core test machine). On the pursuit's supersteps of ~5 tasks on 2 ranks, ties to
    rank 0 made the supersteps 0.85× as long as ties to rank 1 (2026-12-02)."""
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    groups: list[list[int]] = [[] for _ in range(n_workers)]
    heap = [(0.0, w) for w in range(n_workers)]  # (load, worker), a heap: sorted
    for i in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
        load, w = heap[0]
        heapq.heapreplace(heap, (load + costs[i], w))
        groups[w].append(i)
    return [sorted(g) for g in groups]


def _least_loaded(loads: list[float]) -> int:
    """The least-loaded worker, ties to the lowest-numbered one (as :func:`longest_first`)."""
    return min(range(len(loads)), key=lambda w: (loads[w], w))


def sticky_longest_first(
    costs: Sequence[float],
    n_workers: int,
    previous: Sequence[int | None] | None = None,
    tolerance: float = 0.05,
) -> list[list[int]]:
    """Longest-processing-time-first on ``costs`` (≥ 0, e.g. each task's measured time in the
    previous superstep) that keeps task i on worker ``previous[i]`` (its worker last superstep:
    warm starts and cached solvers stay local) as long as the makespan stays within
    (1 + ``tolerance``) × the makespan of plain :func:`longest_first`.

    Two greedy passes over the tasks, longest first: a task stays on its previous worker if
    that worker's load stays within the bound, otherwise it goes to the least-loaded worker,
    either at once or after all the kept tasks. Of these two and the plain
    :func:`longest_first` assignment, the one within the bound that keeps the most tasks in
    place wins (earlier on ties), so the makespan never exceeds the bound and no fewer tasks
    stay than with plain longest-first. Entries of ``previous`` that are None or
    ≥ ``n_workers`` (the worker count changed) count as no previous worker; ``previous=None``
    gives :func:`longest_first`. Ties as in :func:`longest_first` (lowest-numbered
    least-loaded worker, lower task index first), so the assignment is deterministic; each
    worker's indices in increasing order.
    """
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    costs = [float(c) for c in costs]
    if any(not math.isfinite(c) or c < 0 for c in costs):
        raise ValueError("costs must be finite and ≥ 0")
    if not (math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be finite and ≥ 0, got {tolerance!r}")
    plain = longest_first(costs, n_workers)
    if previous is None:
        return plain
    if len(previous) != len(costs):
        raise ValueError(f"{len(previous)} previous workers for {len(costs)} tasks")
    for i, w in enumerate(previous):
        if w is not None and (isinstance(w, bool) or not isinstance(w, Integral) or w < 0):
            raise ValueError(f"previous[{i}] must be a worker index ≥ 0 or None, got {w!r}")
    bound = (1.0 + tolerance) * max(sum(costs[i] for i in g) for g in plain)
    order = sorted(range(len(costs)), key=lambda i: (-costs[i], i))
    candidates = [_sticky_pass(costs, order, previous, n_workers, bound, defer)
                  for defer in (False, True)]
    best, best_kept = plain, -1
    for groups in [*candidates, plain]:
        if groups is not None:
            kept = sum(previous[i] == w for w, g in enumerate(groups) for i in g)
            if kept > best_kept:
                best, best_kept = groups, kept
    return [sorted(g) for g in best]


def _sticky_pass(
    costs: list[float],
    order: list[int],
    previous: Sequence[int | None],
    n_workers: int,
    bound: float,
    defer: bool,
) -> list[list[int]] | None:
    """One greedy pass of :func:`sticky_longest_first` over tasks in ``order``: a task stays on
    its previous worker if that worker's load stays ≤ ``bound``; otherwise it goes to the
    least-loaded worker at once (``defer`` False) or after all kept tasks are placed (True).
    None if the makespan ends above ``bound``."""
    loads = [0.0] * n_workers
    groups: list[list[int]] = [[] for _ in range(n_workers)]
    rest = []
    for i in order:
        w = previous[i]
        if w is None or w >= n_workers or loads[w] + costs[i] > bound:
            if defer:
                rest.append(i)
                continue
            w = _least_loaded(loads)
        loads[w] += costs[i]
        groups[w].append(i)
    for i in rest:
        w = _least_loaded(loads)
        loads[w] += costs[i]
        groups[w].append(i)
    return groups if max(loads) <= bound else None
