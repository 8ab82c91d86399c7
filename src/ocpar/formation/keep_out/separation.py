"""Closest approach between agents on their continuous-time paths.

The path between DMOC nodes is the linear interpolant: DMOC's discrete velocity on interval k
is (q_k+1 − q_k)/h, constant over the interval, and the midpoint discrete Lagrangian
evaluates L at the linear interpolant's midpoint, so the piecewise-linear path through the
nodes q_k at t_k = k T/N is the curve whose action DMOC approximates. Between two nodes the
relative position of two agents, r(s) = d_k + s (d_k+1 − d_k) with s = (t − t_k)/h ∈ [0, 1], is
linear in t, so the minimum of |r| on the interval is exact: the clamped minimiser of a
quadratic, s* = clip(−d_k·e / e·e, 0, 1) with e = d_k+1 − d_k (:func:`interval_closest`).

Which pairs to test, without testing all pairs (:func:`close_pairs`): each interval, the agents
are sorted by the Z-order key of their midpoints into an implicit binary tree of boxes that
bound their positions at the interval's start and end; node pairs are refined from the root
down, and a pair of boxes is dropped where the box of their relative positions, which moves
linearly over the interval, stays outside the radius (:func:`_may_meet`, exact for the L∞
distance of boxes); the agent pairs of the leaf pairs left get the exact test. Agents that
travel together, however far, stay in small boxes relative to each other, and agents that
cross are dropped unless they pass close at about the same time, so the cost is about
n log n per interval unless many pairs really come within the radius. :func:`closest_approach`
bounds the minimum by an actual pair distance (neighbours in order along the first coordinate,
at every node) and tests the pairs within that bound: its result equals the all-pairs minimum.

Positions are the agents' translational coordinates, shape (n, N+1, dim), in the model's
length unit (for a formation: :meth:`ocpar.formation.FormationProblem.positions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ocpar.ocp.obstacles import segment_closest

#: Separation counts as met at D (1 − this): the keep-outs hold to the solver's accuracy.
SEPARATION_RTOL = 1e-9

if TYPE_CHECKING:
    from ocpar.bsp import Backend

#: Agents per leaf of the tree over one interval's segments (see :func:`_interval_within`).
LEAF = 2
#: Bits per coordinate of the Z-order key that sorts agents into the tree (at most 62/dim).
KEY_BITS = 16
#: Pairs per chunk of the exact test (bounds its temporary arrays to a few hundred MB).
CHUNK = 200_000
#: Node pairs per chunk of a level of the tree (:func:`_interval_within`): each chunk's
#: temporary arrays (~200 bytes per pair) stay in the cache and on the heap. Whole levels at
#: 1,000,000 agents (~2.7 million pairs) took ~1.8x the CPU time, much of it page faults of
#: fresh arrays.
PAIR_CHUNK = 8_192
#: A search cut into C spatial cells cuts at the first tree level with at least this many
#: nodes per cell (:func:`_interval_within`): the levels above are every cell's (few pairs).
CELL_NODES = 16


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


def _zorder(points: np.ndarray) -> np.ndarray:
    """Z-order (Morton) keys (n,) of ``points`` (n, dim): each coordinate scaled to
    :data:`KEY_BITS` bits (at most 62/dim) over the points' bounding box, bits interleaved."""
    n, dim = points.shape
    bits = max(1, min(KEY_BITS, 62 // dim))
    low, span = points.min(axis=0), np.ptp(points, axis=0)
    scale = np.divide(2.0**bits - 1, span, out=np.zeros(dim), where=span > 0)
    grid = ((points - low) * scale).astype(np.int64)
    key = np.zeros(n, np.int64)
    for bit in range(bits - 1, -1, -1):
        for d in range(dim):
            key = (key << 1) | ((grid[:, d] >> bit) & 1)
    return key


def _tree_levels(x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The implicit binary tree over the rows of ``x`` (n, m) in their order, root first: per
    level the nodes' boxes lo, hi (nodes, m) and row counts (nodes,). Leaf j holds rows
    j·LEAF … j·LEAF + count − 1; node j's children are nodes 2j and 2j + 1 of the next level
    (a level of odd length gets an empty last node: box lo = +inf, hi = −inf, count 0)."""
    starts = np.arange(0, len(x), LEAF)
    lo, hi = np.minimum.reduceat(x, starts), np.maximum.reduceat(x, starts)
    count = np.diff(np.r_[starts, len(x)])
    levels = []
    while True:
        if len(count) > 1 and len(count) % 2:
            lo = np.vstack([lo, np.full((1, x.shape[1]), np.inf)])
            hi = np.vstack([hi, np.full((1, x.shape[1]), -np.inf)])
            count = np.r_[count, 0]
        levels.append((lo, hi, count))
        if len(count) == 1:
            return levels[::-1]
        lo, hi = np.minimum(lo[::2], lo[1::2]), np.maximum(hi[::2], hi[1::2])
        count = count[::2] + count[1::2]


def _children(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The child node pairs of node pairs (a, b), a ≤ b: (a, a) has three, (2a, 2a),
    (2a, 2a + 1) and (2a + 1, 2a + 1); a < b four. Children keep a ≤ b."""
    other = a != b
    return (np.concatenate([2 * a, 2 * a, 2 * a + 1, 2 * a[other] + 1]),
            np.concatenate([2 * b, 2 * b + 1, 2 * b + 1, 2 * b[other]]))


def _box_terms(lo: np.ndarray, hi: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Per node, the terms (nodes, 2, 2 dim) of :func:`_may_meet`'s affine functions at the
    interval's start and end: of the first node of a pair [lo − reach, −hi − reach], of the
    second [−hi, lo]."""
    dim = lo.shape[1] // 2
    first = np.empty((len(lo), 2, 2 * dim))
    second = np.empty_like(first)
    for end in (0, 1):
        at = slice(end * dim, (end + 1) * dim)
        first[:, end, :dim], first[:, end, dim:] = lo[:, at] - reach, -hi[:, at] - reach
        second[:, end, :dim], second[:, end, dim:] = -hi[:, at], lo[:, at]
    return first, second


def _may_meet(first: np.ndarray, second: np.ndarray, a: np.ndarray, b: np.ndarray
              ) -> np.ndarray:
    """Whether node boxes a and b (each index (m,)) may come within the ``reach`` of
    :func:`_box_terms` (which gave ``first``, ``second``) of each other at some s ∈ [0, 1] of
    the interval (m,), a necessary condition for any of their pairs.

    A box (lo, hi) bounds its agents' positions at the interval's start and end. The pair's
    relative position at s lies in the box whose bounds interpolate linearly between those of
    the boxes' differences at s = 0 and s = 1, lo_a − hi_b … hi_a − lo_b: per axis it is
    within ``reach`` of 0 where two affine functions of s are ≤ 0, lo_a − hi_b − reach and
    lo_b − hi_a − reach. Each holds on a sub-interval of [0, 1] (before or after the s where
    it crosses 0): the pair may meet only if all of them overlap."""
    g = first[a] + second[b]
    g0, g1 = g[:, 0], g[:, 1]                     # at s = 0 and s = 1, (m, 2 dim)
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = g0 / (g0 - g1)
    start = np.where(g0 > 0, cross, 0.0)
    end = np.where(g1 > 0, cross, 1.0)
    for column in range(1, g0.shape[1]):   # a loop over the few columns beats .max(axis=1)
        np.maximum(start[:, 0], start[:, column], out=start[:, 0])
        np.minimum(end[:, 0], end[:, column], out=end[:, 0])
    start, end = start[:, 0], end[:, 0]
    # a function > 0 at both ends crosses 0 outside [0, 1] (or never: ±inf, or start > 1)
    return (start <= end) & (start <= 1.0) & (end >= 0.0)


def _leaf_pairs(a: np.ndarray, b: np.ndarray, count: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The row pairs (i, j) of leaf pairs (a, b), a ≤ b (within a leaf i < j)."""
    rows = []
    for p in range(LEAF):
        for q in range(LEAF):
            keep = (p < count[a]) & (q < count[b]) & ((a < b) | (p < q))
            rows.append((a[keep] * LEAF + p, b[keep] * LEAF + q))
    return (np.concatenate([i for i, _ in rows]), np.concatenate([j for _, j in rows]))


def _interval_within(x: np.ndarray, reach: float, cell: int = 0, cells: int = 1
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Agent pairs (i, j) (each (m,), unordered) whose segments come within ``reach`` of each
    other on one interval by the exact test: ``x`` (n, 2 dim) holds each agent's position at
    the interval's start and at its end.

    The agents are sorted by the Z-order key of their midpoints into an implicit binary tree
    of boxes (:func:`_tree_levels`); node pairs are refined from the root down, level by
    level, keeping those whose boxes may meet (:func:`_may_meet`); the agent pairs of the
    surviving leaf pairs get the exact test. Agents that travel together, however far, stay
    in small boxes relative to each other, so the work is about n log n for paths that do not
    crowd within ``reach``.

    ``cells`` > 1 cuts the search into that many spatial cells, runs of the Z-order: from
    the first level of at least :data:`CELL_NODES` nodes a cell each, only the pairs whose
    first node lies in cell ``cell`` are refined (the other node wherever it is: the halo);
    the cells' pairs together are the whole search's."""
    dim = x.shape[1] // 2
    order = np.argsort(_zorder(0.5 * (x[:, :dim] + x[:, dim:])), kind="stable")
    x = x[order]
    a = b = np.zeros(1, np.intp)
    levels = _tree_levels(x)
    split = cells == 1
    for depth, (lo, hi, count) in enumerate(levels):
        terms = _box_terms(lo, hi, reach)
        cut = not split and (len(count) >= CELL_NODES * cells or depth == len(levels) - 1)
        kept_a, kept_b = [a[:0]], [b[:0]]
        for chunk in range(0, len(a), PAIR_CHUNK):   # the node pairs of this level, by chunk
            ca, cb = a[chunk:chunk + PAIR_CHUNK], b[chunk:chunk + PAIR_CHUNK]
            if depth:
                ca, cb = _children(ca, cb)
                filled = (count[ca] > 0) & (count[cb] > 0)
                ca, cb = ca[filled], cb[filled]
            if cut:
                mine = ca * cells // len(count) == cell
                ca, cb = ca[mine], cb[mine]
            meet = _may_meet(*terms, ca, cb)
            kept_a.append(ca[meet])
            kept_b.append(cb[meet])
        a, b = np.concatenate(kept_a), np.concatenate(kept_b)
        split = split or cut
    found_i, found_j = [], []
    for chunk in range(0, len(a), PAIR_CHUNK):
        i, j = _leaf_pairs(a[chunk:chunk + PAIR_CHUNK], b[chunk:chunk + PAIR_CHUNK],
                           levels[-1][2])
        relative = x[i] - x[j]
        distance, _ = segment_closest(relative[:, :dim], relative[:, dim:])
        close = distance <= reach
        found_i.append(order[i[close]])
        found_j.append(order[j[close]])
    return np.concatenate(found_i), np.concatenate(found_j)


def _within(positions: np.ndarray, radius: float) -> np.ndarray:
    """Pairs (m, 2), i < j, sorted, that come within ``radius`` on some interval by the exact
    test on that interval, with a slack of 1e-9 radius (a superset of :func:`close_pairs`
    that rounding cannot shrink), found without testing all pairs: interval by interval
    (:func:`_interval_within`)."""
    n, nodes, _ = positions.shape
    reach = radius * (1 + 1e-9) + 1e-12 * (1.0 + np.abs(positions).max())
    found = [np.empty(0, np.int64)]
    for k in range(nodes - 1):
        i, j = _interval_within(positions[:, k:k + 2].reshape(n, -1), reach)
        found.append(np.minimum(i, j).astype(np.int64) * n + np.maximum(i, j))
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
    of neighbours in order along the first coordinate, at every node (node by node: the sort of
    one node's column ~4x faster than the strided sort of all at once, 0.6 against 2.4 CPU s
    at 1,000,000 agents)."""
    best = math.inf
    for k in range(positions.shape[1]):
        nodes = positions[:, k]
        ranked = nodes[np.argsort(nodes[:, 0], kind="stable")]
        best = min(best, float(np.linalg.norm(np.diff(ranked, axis=0), axis=-1).min()))
    return best


@dataclass(frozen=True)
class IntervalTask:
    """One interval's closest approach to find (:func:`interval_minimum`): the agents'
    positions at its start and end ``segments`` (n, 2, dim), the ``bound`` (length unit) an
    actual pair distance at some node of the paths (:func:`_upper_bound`), ``scale``
    max |position| over the paths (the slack of the test); the search cut into ``cells``
    spatial cells, this task's is ``cell`` (:func:`_interval_within`)."""

    segments: np.ndarray
    bound: float
    scale: float
    cell: int = 0
    cells: int = 1


@dataclass(frozen=True)
class IntervalMinimum:
    """The closest pair on one interval, among pairs that come within the bound there:
    ``distance`` (inf if none), the pair (``i``, ``j``), i < j ((−1, −1) if none), the first
    ``fraction`` s ∈ [0, 1] of the interval where it occurs."""

    distance: float
    i: int
    j: int
    fraction: float


def interval_minimum(task: IntervalTask) -> IntervalMinimum:
    """Engine kernel: the exact closest approach on the interval of ``task`` among the pairs
    within its bound (:func:`_interval_within`; the closest pair of the whole paths is among
    them on its interval); ties go to the first pair in (i, j) order."""
    n = len(task.segments)
    reach = task.bound * (1 + 1e-9) + 1e-12 * (1.0 + task.scale)
    i, j = _interval_within(task.segments.reshape(n, -1), reach, task.cell, task.cells)
    if not len(i):
        return IntervalMinimum(math.inf, -1, -1, math.nan)
    pairs = np.unique(np.minimum(i, j).astype(np.int64) * n + np.maximum(i, j))
    first, second = np.divmod(pairs, n)
    relative = task.segments[first] - task.segments[second]
    distance, fraction = segment_closest(relative[:, 0], relative[:, 1])
    best = int(np.argmin(distance))
    return IntervalMinimum(float(distance[best]), int(first[best]), int(second[best]),
                           float(fraction[best]))


#: Most points :func:`closest_pair` searches with the interval tree; above, SciPy's k-d tree
#: (measured on this 2-core machine, on a circle and in a cube: the tree 0.04 s at 10,000
#: points, 0.16 s at 50,000 and 0.5 s at 100,000; ``cKDTree`` 0.06 s at 100,000, but
#: importing ``scipy.spatial`` takes 0.22 s).
TREE_POINTS = 50_000


def closest_pair(points: np.ndarray) -> tuple[float, tuple[int, int]]:
    """The smallest distance between two of ``points`` (m, d), m ≥ 2, and a pair (i, j),
    i < j, at that distance: as the closest approach of agents standing still
    (:func:`interval_minimum` on a zero-length interval) up to :data:`TREE_POINTS` points,
    above by SciPy's ``cKDTree``."""
    points = np.asarray(points, float)
    if len(points) <= TREE_POINTS:
        still = IntervalTask(np.stack([points, points], axis=1), _upper_bound(points[:, None]),
                             float(np.abs(points).max()))
        found = interval_minimum(still)
        return found.distance, (found.i, found.j)
    from scipy.spatial import cKDTree
    distance, index = cKDTree(points).query(points, k=2)
    i = int(np.argmin(distance[:, 1]))
    j = int(index[i, 1] if index[i, 1] != i else index[i, 0])   # a duplicate may come first
    return float(distance[i, 1]), (min(i, j), max(i, j))


def closest_approach(positions: np.ndarray, duration: float,
                     backend: Backend | None = None) -> ClosestApproach:
    """Closest approach of any two agents on piecewise-linear paths.

    ``positions`` (n, N+1, dim) node positions at t_k = k T/N, ``duration`` T (time unit).
    Equal to the all-pairs minimum (ties: the first pair in (i, j) order, then the earliest
    interval). Interval by interval (:func:`interval_minimum`), each within a bound that an
    actual pair distance gives (:func:`_upper_bound`): with a ``backend``, one superstep of
    tasks on its workers (not recorded as the run's), each interval cut into spatial cells
    where the workers outnumber the intervals (⌈P/N⌉ cells each: :func:`_interval_within`);
    the same numbers (each interval's and cell's arithmetic is its own).
    """
    positions = _check_positions(positions)
    n, nodes, _ = positions.shape
    if n < 2:
        return ClosestApproach(math.inf, (-1, -1), math.nan)
    bound, scale = _upper_bound(positions), float(np.abs(positions).max())
    cells = 1 if backend is None else -(-backend.workers // (nodes - 1))
    tasks = [IntervalTask(segments, bound, scale, cell, cells)
             for segments in (np.ascontiguousarray(positions[:, k:k + 2])
                              for k in range(nodes - 1))
             for cell in range(cells)]
    # equal cost estimates: under MPI the ranks take the tasks from a shared queue; not a
    # step of the run (neither traced nor journaled)
    minima = (backend.superstep(interval_minimum, tasks, costs=[1.0] * len(tasks),
                                record=False)
              if backend is not None else [interval_minimum(task) for task in tasks])
    # the smallest distance; ties to the first pair, then the earliest interval
    t = min(range(len(minima)), key=lambda t: (minima[t].distance, minima[t].i, minima[t].j,
                                                t))
    best, k = minima[t], t // cells
    return ClosestApproach(best.distance, (best.i, best.j),
                           (k + best.fraction) * duration / (nodes - 1))


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
