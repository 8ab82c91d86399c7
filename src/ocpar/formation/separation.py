"""Closest approach between agents on their continuous-time paths.

The path between DMOC nodes is the linear interpolant: DMOC's discrete velocity on interval k
is (q_k+1 − q_k)/h, constant over the interval, and the midpoint discrete Lagrangian
evaluates L at the linear interpolant's midpoint, so the piecewise-linear path through the
nodes q_k at t_k = k T/N is the curve whose action DMOC approximates. Between two nodes the
relative position of two agents, r(s) = d_k + s (d_k+1 − d_k) with s = (t − t_k)/h ∈ [0, 1], is
linear in t, so the minimum of |r| on the interval is exact: the clamped minimiser of a
quadratic, s* = clip(−d_k·e / e·e, 0, 1) with e = d_k+1 − d_k (:func:`interval_closest`).

Which pairs to test, without testing all pairs (:func:`close_pairs`): each interval, seen in
the frame of the agents' median velocity, is a task; the boxes each agent sweeps over it,
grown by half the radius, go into a uniform grid (a spatial hash); pairs whose boxes overlap
in a cell shared by few agents get the exact test. A crowded cell (agents travelling far
compared with their spacing, or a bundle of paths) becomes two tasks: the two halves of the
time slice, in the frame of the mean velocity of its agents, whose boxes are then smaller
(frames and slices change no distance, so no pair is missed). The cost grows about linearly
with the number of agents n for spread-out paths; a bundle that converges (many paths passing
near one point at about the same time) costs more. :func:`closest_approach` bounds the
minimum by an actual pair distance (neighbours in order along the first coordinate, at every
node) and tests the pairs within that bound: its result equals the all-pairs minimum.

Positions are the agents' translational coordinates, shape (n, N+1, dim), in the model's
length unit (for a formation: :meth:`ocpar.formation.FormationProblem.positions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Grid cells are this many times a task's mean box (or a quarter of its largest box) wide.
CELL = 2.0
#: A grid cell shared by more agents than this is split in time (see :func:`_within`)...
CROWD = 16
#: ... at most this many times (then all pairs of a crowded cell are tested).
MAX_DEPTH = 16
#: Most agents in one batch of tasks, and most pairs in one batch of exact tests.
BUDGET = 2_000_000
#: Pairs per chunk of the exact test (bounds its temporary arrays to a few hundred MB).
CHUNK = 200_000


@dataclass(frozen=True)
class ClosestApproach:
    """The closest approach of any two agents.

    ``distance`` min over pairs and times of |r_i(t) − r_j(t)| (model's length unit);
    ``agents`` the pair (i, j), i < j, where it occurs ((−1, −1) with fewer than 2 agents,
    distance inf); ``time`` t where it occurs (model's time unit, 0 … T).
    """

    distance: float
    agents: tuple[int, int]
    time: float


def _check_positions(positions: np.ndarray) -> np.ndarray:
    array = np.asarray(positions, float)
    if array.ndim != 3 or array.shape[1] < 2:
        raise ValueError(f"positions must have shape (n_agents, N+1, dim) with N >= 1, got "
                         f"{array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError("positions must be finite")
    return array


def segment_closest(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimum of |(1 − s) d0 + s d1| over s ∈ [0, 1] for relative positions ``start`` d0
    and ``end`` d1 (..., dim): the distance (...) and the first s (...) where it occurs."""
    step = end - start
    step_sq = np.einsum("...d,...d->...", step, step)
    toward = -np.einsum("...d,...d->...", start, step)
    s = np.divide(toward, step_sq, out=np.zeros_like(toward), where=step_sq > 0)
    np.clip(s, 0.0, 1.0, out=s)
    # (1 − s) d0 + s d1: exactly the node values at s = 0 and s = 1
    point = (1.0 - s)[..., None] * start + s[..., None] * end
    return np.linalg.norm(point, axis=-1), s


def interval_closest(positions: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact closest approach of each pair on each interval.

    ``positions`` (n, N+1, dim) nodes of piecewise-linear paths; ``pairs`` (m, 2) agent
    indices. Returns the minimum distance (m, N) on each interval and the fraction s (m, N)
    in [0, 1] of the interval where it occurs (the first one if the distance is constant).
    """
    positions = _check_positions(positions)
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    intervals = positions.shape[1] - 1
    distance = np.empty((len(pairs), intervals))
    fraction = np.empty((len(pairs), intervals))
    for lo in range(0, len(pairs), CHUNK):
        chunk = pairs[lo:lo + CHUNK]
        rel = positions[chunk[:, 0]] - positions[chunk[:, 1]]   # (m, N+1, dim)
        distance[lo:lo + CHUNK], fraction[lo:lo + CHUNK] = segment_closest(rel[:, :-1],
                                                                            rel[:, 1:])
    return distance, fraction


def _run_entries(runs: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Indices of the entries of runs of sorted entries starting at ``runs`` with ``sizes``
    entries each, run after run."""
    return np.repeat(runs, sizes) + np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes,
                                                                       sizes)


def _pairs_in_runs(runs: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (left, right), left < right, of entries within each run (see
    :func:`_run_entries`)."""
    index = _run_entries(runs, sizes)
    partners = np.repeat(runs + sizes, sizes) - index - 1
    left = np.repeat(index, partners)
    return left, left + 1 + _run_entries(np.zeros_like(partners), partners)


def _batches(weights: np.ndarray, limit: int) -> list[np.ndarray]:
    """Consecutive index ranges of ``weights`` (≥ 0) whose sums stay within ``limit`` (a
    single heavier item makes a batch of its own)."""
    batches, first = [], 0
    total = np.cumsum(weights)
    while first < len(weights):
        base = total[first - 1] if first else 0
        last = max(first + 1, int(np.searchsorted(total, base + limit, side="right")))
        batches.append(np.arange(first, last))
        first = last
    return batches


def _within(positions: np.ndarray, radius: float) -> np.ndarray:
    """Pairs (m, 2), i < j, sorted, that come within ``radius`` on some interval by the exact
    test on that interval, with a slack of 1e-9 radius (a superset of :func:`close_pairs`
    that rounding cannot shrink), found without testing all pairs.

    A task is a time slice [s0, s1] of one interval seen in a frame moving with velocity u,
    and the agents that take part; its agents' boxes swept over the slice (grown by half the
    radius) go into a uniform grid. Pairs that share a cell with few others and whose boxes
    overlap get the exact test; a crowded cell becomes two tasks, the two halves of its slice
    in the frame of its agents' mean velocity (agents moving together then sweep small
    boxes). Frames and slices do not change which pairs come close, so nothing is missed.
    Tasks wait in a queue in batches of at most BUDGET agents; pairs are tested in batches of
    at most BUDGET.
    """
    n, nodes, dim = positions.shape
    intervals = nodes - 1
    start, step = positions[:, :-1], np.diff(positions, axis=1)     # (n, N, dim)
    scale = 1e-12 * (1.0 + np.abs(positions).max())
    grow = 0.5 * radius * (1 + 1e-9) + scale
    found = [np.empty(0, np.int64)]
    # first tasks: each interval, all agents, the frame of the median velocity
    queue = [(np.array([k]), np.array([[0.0, 1.0]]), np.median(step[:, k], axis=0)[None],
              np.zeros(n, np.intp), np.arange(n), 0) for k in range(intervals)]
    while queue:
        task_k, task_s, task_u, member_task, member, depth = queue.pop()
        k = task_k[member_task]
        a, v = start[member, k], step[member, k] - task_u[member_task]
        lo = a + task_s[member_task, :1] * v
        hi = a + task_s[member_task, 1:] * v
        lo, hi = np.minimum(lo, hi) - grow, np.maximum(lo, hi) + grow
        extent = (hi - lo).max(axis=1)
        bounds = np.r_[0, np.flatnonzero(np.diff(member_task)) + 1]   # members are by task
        count = np.diff(np.r_[bounds, len(member)])
        cell = np.maximum(CELL * np.add.reduceat(extent, bounds) / count,
                          0.25 * np.maximum.reduceat(extent, bounds))
        origin = np.repeat(np.minimum.reduceat(lo, bounds), count, axis=0)
        while True:   # cells so coarse that (task, cell) fits one int64 key
            scaled_lo, scaled_hi = ((x - origin) / np.repeat(cell, count)[:, None]
                                    for x in (lo, hi))
            if len(cell) * (float(scaled_hi.max()) + 2) ** dim < 2.0 ** 62:
                break
            cell = 2 * cell
        first = np.floor(scaled_lo).astype(np.int64)
        cells = np.floor(scaled_hi).astype(np.int64) - first + 1
        # one entry per (member, cell its box touches), keyed by (task, cell)
        per_member = cells.prod(axis=1)
        entry = np.repeat(np.arange(len(member)), per_member)
        local = _run_entries(np.zeros_like(per_member), per_member)
        span = int((first + cells).max()) + 1
        key = member_task[entry].astype(np.int64)
        coord = np.empty((entry.size, dim), np.int64)
        for d in range(dim):
            c = cells[entry, d]
            coord[:, d] = first[entry, d] + local % c
            key = key * span + coord[:, d]
            local //= c
        order = np.argsort(key, kind="stable")
        key, entry, coord = key[order], entry[order], coord[order]
        runs = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        sizes = np.diff(np.r_[runs, key.size])
        # split a crowded cell while its boxes are mostly motion (halving the slice shrinks
        # them) and the depth allows
        motion = np.add.reduceat(extent[entry] - 2 * grow, runs) / sizes
        split = (sizes > CROWD) & (motion > 2 * grow) & (depth < MAX_DEPTH)
        final = np.flatnonzero((sizes > 1) & ~split)
        for batch in _batches(sizes[final] * (sizes[final] - 1) // 2, BUDGET):
            left, right = _pairs_in_runs(runs[final[batch]], sizes[final[batch]])
            ma, mb = entry[left], entry[right]
            # boxes that overlap, counted once: in the cell of their overlap's lower corner
            keep = np.all((lo[ma] <= hi[mb]) & (lo[mb] <= hi[ma]), axis=1)
            keep &= np.all(np.floor(np.maximum(scaled_lo[ma], scaled_lo[mb])) == coord[left],
                           axis=1)
            ma, mb = ma[keep], mb[keep]
            i, j = np.minimum(member[ma], member[mb]), np.maximum(member[ma], member[mb])
            at = k[ma]
            distance, _ = segment_closest(positions[i, at] - positions[j, at],
                                           positions[i, at + 1] - positions[j, at + 1])
            close = distance <= radius * (1 + 1e-9) + scale
            found.append(i[close].astype(np.int64) * n + j[close])
        # each split cell: two tasks (halves of its slice), frame of its members' mean velocity
        split = np.flatnonzero(split)
        for batch in _batches(2 * sizes[split], BUDGET):
            runs_b, sizes_b = runs[split[batch]], sizes[split[batch]]
            parent = member_task[entry[runs_b]]
            agents = member[entry[_run_entries(runs_b, sizes_b)]]
            group = np.repeat(np.arange(len(runs_b)), sizes_b)
            velocity = step[agents, task_k[parent][group]]
            mean_u = np.stack([np.bincount(group, velocity[:, d]) for d in range(dim)], 1) \
                / sizes_b[:, None]
            middle = task_s[parent].mean(axis=1)
            queue.append((np.r_[task_k[parent], task_k[parent]],
                          np.r_[np.column_stack([task_s[parent, 0], middle]),
                                np.column_stack([middle, task_s[parent, 1]])],
                          np.r_[mean_u, mean_u], np.r_[group, group + len(runs_b)],
                          np.r_[agents, agents], depth + 1))
    return np.column_stack(np.divmod(np.unique(np.concatenate(found)), n)).astype(np.intp)


def _pair_minima(positions: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's minimum distance over the whole path (m,) and the time of it in intervals
    (m,) (interval index + fraction)."""
    distance, fraction = interval_closest(positions, pairs)
    k = np.argmin(distance, axis=1)
    rows = np.arange(len(pairs))
    return distance[rows, k], k + fraction[rows, k]


def close_pairs(positions: np.ndarray, radius: float) -> np.ndarray:
    """Pairs (m, 2), i < j, sorted, whose piecewise-linear paths come within ``radius`` (≥ 0,
    length unit) of each other at some time: exactly those, not a superset."""
    positions = _check_positions(positions)
    if not radius >= 0 or not math.isfinite(radius):
        raise ValueError(f"radius must be finite and >= 0, got {radius}")
    pairs = _within(positions, radius)
    minima, _ = _pair_minima(positions, pairs)
    return pairs[minima <= radius]


def _upper_bound(positions: np.ndarray) -> float:
    """An actual pair distance at some node (so at least the closest approach): the nearest
    of neighbours in order along the first coordinate, at every node."""
    order = np.argsort(positions[..., 0], axis=0, kind="stable")      # (n, N+1)
    ranked = np.take_along_axis(positions, order[..., None], axis=0)
    return float(np.linalg.norm(np.diff(ranked, axis=0), axis=-1).min())


def closest_approach(positions: np.ndarray, duration: float) -> ClosestApproach:
    """Closest approach of any two agents on piecewise-linear paths.

    ``positions`` (n, N+1, dim) node positions at t_k = k T/N, ``duration`` T (time unit).
    Equal to the all-pairs minimum (ties: the first pair in (i, j) order, then the earliest
    interval).
    """
    positions = _check_positions(positions)
    n, nodes, _ = positions.shape
    if n < 2:
        return ClosestApproach(math.inf, (-1, -1), math.nan)
    pairs = _within(positions, _upper_bound(positions))   # holds the closest pair
    minima, when = _pair_minima(positions, pairs)
    best = int(np.argmin(minima))
    i, j = (int(x) for x in pairs[best])
    return ClosestApproach(float(minima[best]), (i, j),
                           float(when[best]) * duration / (nodes - 1))


def positions_at(positions: np.ndarray, time: float, duration: float) -> np.ndarray:
    """Every agent's position (n, dim) at ``time`` (0 … ``duration``) on the piecewise-linear
    paths through ``positions`` (n, N+1, dim)."""
    positions = _check_positions(positions)
    intervals = positions.shape[1] - 1
    where = min(max(time / duration, 0.0), 1.0) * intervals
    k = min(int(where), intervals - 1)
    s = where - k
    return (1.0 - s) * positions[:, k] + s * positions[:, k + 1]


def check_separation_feasible(start: np.ndarray, final: np.ndarray, distance: float) -> None:
    """Raise ValueError (one line naming the two agents and their distance) if two agents'
    ``start`` (n, dim) or two ``final`` (n, dim) positions are closer than ``distance``
    (length unit): no path can then keep every pair ``distance`` apart."""
    if not distance >= 0 or not math.isfinite(distance):
        raise ValueError(f"min separation must be finite and >= 0, got {distance}")
    for name, points in (("start", start), ("final", final)):
        points = np.asarray(points, float)
        if points.ndim != 2:
            raise ValueError(f"{name} positions must have shape (n, dim), got {points.shape}")
        still = np.repeat(points[:, None, :], 2, axis=1)
        pairs = close_pairs(still, distance)
        gaps = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
        short = np.flatnonzero(gaps < distance)
        if len(short):
            k = short[np.argmin(gaps[short])]
            i, j = pairs[k]
            raise ValueError(f"min separation {distance:g} cannot be met: agents {i} and {j} "
                             f"are {gaps[k]:.6g} apart at their {name} positions")
