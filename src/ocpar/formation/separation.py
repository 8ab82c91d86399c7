"""Closest approach between agents on their continuous-time paths.

The path between DMOC nodes is the linear interpolant: DMOC's discrete velocity on interval k
is (q_k+1 − q_k)/h, constant over the interval, and the midpoint discrete Lagrangian
evaluates L at the linear interpolant's midpoint, so the piecewise-linear path through the
nodes q_k at t_k = k T/N is the curve whose action DMOC approximates. Between two nodes the
relative position of two agents, r(s) = d_k + s (d_k+1 − d_k) with s = (t − t_k)/h ∈ [0, 1], is
linear in t, so the minimum of |r| on the interval is exact: the clamped minimiser of a
quadratic, s* = clip(−d_k·e / e·e, 0, 1) with e = d_k+1 − d_k (:func:`interval_closest`).

Which pairs to test: a uniform grid (spatial hash) over the boxes swept by each agent on each
(sub-)interval, grown by the radius, gives candidate pairs; the exact test then keeps those
that come within the radius (:func:`close_pairs`). Intervals along which agents travel far
compared with their spacing are cut into equal sub-intervals first (the path stays linear on
each, so nothing changes but the boxes' size). The cost grows about linearly with the number
of agents n. :func:`closest_approach` bounds the minimum by an actual pair distance found in
one sort per node and keeps the pairs within that bound: its result equals the all-pairs
minimum.

Positions are the agents' translational coordinates, shape (n, N+1, dim), in the model's
length unit (for a formation: :meth:`ocpar.formation.FormationProblem.positions`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Sub-intervals per DMOC interval at most, when agents travel far compared with their spacing.
MAX_REFINE = 64
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
        start, step = rel[:, :-1], np.diff(rel, axis=1)
        step_sq = np.einsum("mkd,mkd->mk", step, step)
        toward = -np.einsum("mkd,mkd->mk", start, step)
        s = np.divide(toward, step_sq, out=np.zeros_like(toward), where=step_sq > 0)
        np.clip(s, 0.0, 1.0, out=s)
        # (1 − s) d_k + s d_k+1: exactly the node values at s = 0 and s = 1
        point = (1.0 - s)[..., None] * start + s[..., None] * rel[:, 1:]
        distance[lo:lo + CHUNK] = np.linalg.norm(point, axis=-1)
        fraction[lo:lo + CHUNK] = s
    return distance, fraction


def _refined(positions: np.ndarray, radius: float) -> np.ndarray:
    """The same paths with each interval cut into m equal sub-intervals (nodes added on the
    linear segments), m chosen so that a typical sub-segment is about as long as the agents'
    typical spacing or the radius, whichever is larger."""
    n, _, dim = positions.shape
    travel = float(np.median(np.abs(np.diff(positions, axis=1)).max(axis=-1)))
    spans = np.ptp(positions[:, [0, -1]], axis=0)                     # (2, dim)
    volume = np.prod(np.maximum(spans, spans.max(axis=1, keepdims=True) / n), axis=1)
    spacing = float(np.max((volume / n) ** (1.0 / dim)))
    scale = max(spacing, radius)
    refine = 1 if scale <= 0 else int(min(MAX_REFINE, max(1, math.ceil(travel / scale))))
    if refine == 1:
        return positions
    s = np.arange(refine) / refine
    start, step = positions[:, :-1], np.diff(positions, axis=1)
    fine = start[:, :, None, :] + s[None, None, :, None] * step[:, :, None, :]
    return np.concatenate([fine.reshape(n, -1, dim), positions[:, -1:]], axis=1)


def _candidates(positions: np.ndarray, radius: float) -> np.ndarray:
    """Pairs (m, 2), i < j, sorted, whose boxes swept on some interval come within
    ``radius`` of each other in every coordinate: a superset of the pairs whose paths do."""
    n, nodes, dim = positions.shape
    if n < 2:
        return np.empty((0, 2), dtype=np.intp)
    grow = 0.5 * radius * (1 + 1e-9) + 1e-12 * (1.0 + np.abs(positions).max())
    lo = np.minimum(positions[:, :-1], positions[:, 1:]) - grow       # (n, N, dim)
    hi = np.maximum(positions[:, :-1], positions[:, 1:]) + grow
    extent = (hi - lo).max(axis=-1)
    cell = float(np.quantile(extent, 0.9))
    origin = lo.min(axis=(0, 1))
    while True:
        first = np.floor((lo - origin) / cell).astype(np.int64)
        counts = np.floor((hi - origin) / cell).astype(np.int64) - first + 1
        span = int(first.max() + counts.max()) + 1
        cells_per_box = counts.prod(axis=-1)
        if (span ** dim * (nodes - 1) < 2 ** 62
                and cells_per_box.sum() <= 4 * 2 ** dim * cells_per_box.size):
            break
        cell *= 2.0
    # one entry per (agent, interval, cell touched by its box)
    total = cells_per_box.ravel()
    box = np.repeat(np.arange(total.size), total)
    local = np.arange(box.size) - np.repeat(np.cumsum(total) - total, total)
    agent, interval = np.divmod(box, nodes - 1)
    key = interval.astype(np.int64)
    flat_first, flat_counts = first.reshape(-1, dim), counts.reshape(-1, dim)
    for d in range(dim):
        c = flat_counts[box, d]
        key = key * span + flat_first[box, d] + local % c
        local //= c
    order = np.argsort(key, kind="stable")
    key, agent = key[order], agent[order]
    # all pairs within each run of equal keys
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.repeat(np.r_[starts[1:], key.size], np.diff(np.r_[starts, key.size]))
    partners = ends - np.arange(key.size) - 1
    left = np.repeat(np.arange(key.size), partners)
    right = left + 1 + np.arange(left.size) - np.repeat(np.cumsum(partners) - partners,
                                                        partners)
    a, b = agent[left], agent[right]
    codes = np.unique(np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b))
    codes = codes[codes // n != codes % n]
    return np.column_stack(np.divmod(codes, n)).astype(np.intp)


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
    pairs = _candidates(_refined(positions, radius), radius)
    if not len(pairs):
        return pairs
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
    bound = _upper_bound(positions)
    pairs = _candidates(_refined(positions, bound), bound)   # holds every pair within bound
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
        if not len(pairs):
            continue
        gaps = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
        short = np.flatnonzero(gaps < distance)
        if len(short):
            k = short[np.argmin(gaps[short])]
            i, j = pairs[k]
            raise ValueError(f"min separation {distance:g} cannot be met: agents {i} and {j} "
                             f"are {gaps[k]:.6g} apart at their {name} positions")
