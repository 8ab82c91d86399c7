"""Quality metrics of an approximate Pareto front against a reference front (all minimised).

Fronts are arrays of shape (n, m), one row of objective values per point. Every metric works on
fronts normalised with the reference front's ideal and nadir points, as in the MACS paper's §V
(GD and IGD "computed on a rescaled front in the interval [0, 1]").
"""

from __future__ import annotations

from collections.abc import Sequence

import moocore
import numpy as np


def _points(front: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(front, dtype=float)
    if points.ndim != 2:
        raise ValueError(f"{name} must have shape (n, m), got {points.shape}")
    return points


def normalise(front: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``front`` scaled objective-wise by the reference front's ideal point z* (column minima)
    and nadir point z^N (column maxima): (f − z*)/(z^N − z*), shape (n, m). The reference
    front itself maps into [0, 1]^m."""
    points, ref = _points(front, "front"), _points(reference, "reference")
    if points.shape[1] != ref.shape[1] or ref.shape[0] == 0:
        raise ValueError(f"front {points.shape} and reference {ref.shape} do not match")
    ideal, nadir = ref.min(axis=0), ref.max(axis=0)
    span = nadir - ideal
    if np.any(span <= 0):
        raise ValueError("the reference front has no extent in some objective")
    return (points - ideal) / span


def _nearest_point_distances(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """For each row of ``points``, the Euclidean distance to the nearest row of ``targets``."""
    out = np.empty(len(points))
    for start in range(0, len(points), 512):
        chunk = points[start:start + 512]
        diff = chunk[:, None, :] - targets[None, :, :]
        out[start:start + 512] = np.sqrt(np.min(np.einsum("ijk,ijk->ij", diff, diff), axis=1))
    return out


def _polyline_distances(points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """For each row of ``points``, the Euclidean distance to the polyline through ``vertices``
    (in order)."""
    if len(vertices) == 1:
        return _nearest_point_distances(points, vertices)
    a, b = vertices[:-1], vertices[1:]
    ab = b - a
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), np.finfo(float).tiny)
    out = np.empty(len(points))
    for start in range(0, len(points), 512):
        chunk = points[start:start + 512]
        ap = chunk[:, None, :] - a[None, :, :]
        t = np.clip(np.einsum("ijk,jk->ij", ap, ab) / length2, 0.0, 1.0)
        diff = ap - t[:, :, None] * ab[None, :, :]
        out[start:start + 512] = np.sqrt(np.min(np.einsum("ijk,ijk->ij", diff, diff), axis=1))
    return out


def generational_distance(
    front: np.ndarray, reference: np.ndarray, *, interpolate: bool = True
) -> float:
    """Generational distance GD = (1/n) Σ_i d(f_i, R), the mean over the n points f_i of
    ``front`` of the Euclidean distance to the nearest point of the reference R, both
    normalised by :func:`normalise` (dimensionless).

    With ``interpolate`` (default; two objectives only) R is the piecewise-linear curve through
    the reference points sorted by J1, so GD does not depend on where the reference happens to
    be sampled; otherwise R is the set of reference points (the textbook definition).
    """
    points = normalise(front, reference)
    ref = normalise(reference, reference)
    if len(points) == 0:
        return float("nan")
    if not interpolate:
        return float(np.mean(_nearest_point_distances(points, ref)))
    if ref.shape[1] != 2:
        raise ValueError("interpolate=True needs two objectives")
    ref = ref[np.lexsort((ref[:, 1], ref[:, 0]))]
    return float(np.mean(_polyline_distances(points, ref)))


def inverted_generational_distance(front: np.ndarray, reference: np.ndarray) -> float:
    """Inverted generational distance IGD = (1/N) Σ_j min_i ‖r_j − f_i‖, the mean over the N
    reference points r_j of the Euclidean distance to the nearest point f_i of ``front``, both
    normalised by :func:`normalise` (dimensionless; point to point)."""
    points = normalise(front, reference)
    ref = normalise(reference, reference)
    if len(points) == 0:
        return float("nan")
    return float(np.mean(_nearest_point_distances(ref, points)))


def hypervolume(
    front: np.ndarray, reference: np.ndarray, ref_point: Sequence[float] | None = None
) -> float:
    """Hypervolume of the normalised ``front`` (see :func:`normalise`) bounded by ``ref_point``
    (in normalised units; default 1.1 in every objective): the measure of the objective-space
    region dominated by the front and dominating ``ref_point``. Points that do not strictly
    dominate ``ref_point`` contribute nothing. Computed by ``moocore.hypervolume``
    (minimisation)."""
    points = normalise(front, reference)
    ref_point = np.full(points.shape[1], 1.1) if ref_point is None else np.asarray(
        ref_point, dtype=float)
    if ref_point.shape != (points.shape[1],):
        raise ValueError(f"ref_point must have {points.shape[1]} values, got {ref_point.shape}")
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        return 0.0
    return float(moocore.hypervolume(points, ref=ref_point))


def _ordered(front: np.ndarray) -> np.ndarray:
    """A two-objective front's points (n, 2) sorted by J1 (then J2)."""
    points = _points(front, "front")
    if points.shape[1] != 2:
        raise ValueError("the spread along a front needs two objectives")
    return points[np.lexsort((points[:, 1], points[:, 0]))]


def arc_lengths(front: np.ndarray) -> np.ndarray:
    """Cumulative arc length (n,) of the polyline through a two-objective ``front`` (n, 2)
    sorted by J1, in the front's own units (normalise first), from 0."""
    points = _ordered(front)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def igd_floor(reference: np.ndarray, n: int) -> float:
    """The least IGD (:func:`inverted_generational_distance`) against ``reference`` (N, 2) of
    any ``n`` of its own points: the best n-point subset, by dynamic programming over the
    points sorted by J1 with each point served by a contiguous run of them (exact when the
    nearest chosen point of every reference point is one of the two around it along the
    front, as on a monotone front sampled finely). O(N² n) time, O(N²) memory."""
    ref = _ordered(normalise(reference, reference))
    count = len(ref)
    if not 1 <= n <= count:
        raise ValueError(f"n must be in [1, {count}], got {n}")
    within = np.cumsum(np.linalg.norm(ref[:, None, :] - ref[None, :, :], axis=2), axis=0)
    # cost[a, b]: the least Σ distance of points a..b to one of them (c in a..b)
    cost = np.full((count, count), np.inf)
    beyond = np.triu(np.ones((count, count), dtype=bool), k=1)  # [b, c]: c > b
    for a in range(count):
        sums = within[a:, a:] - (within[a - 1, a:] if a else 0.0)  # [b - a, c - a]
        cost[a, a:] = np.where(beyond[a:, a:], np.inf, sums).min(axis=1)
    best = cost[0].copy()  # best[b]: points 0..b served by the subsets chosen so far
    for _ in range(n - 1):
        best = np.array([np.min(best[:b] + cost[1:b + 1, b], initial=np.inf)
                         for b in range(count)])
    return float(best[-1] / count)


def spacing(front: np.ndarray, samples: int = 200) -> dict:
    """How evenly a two-objective ``front`` (k ≥ 2, 2) is spread along itself, in objectives
    normalised to its own ideal and nadir: ``gaps`` (k−1,) the arc lengths between
    consecutive points sorted by J1, ``igd`` the IGD of the points against ``samples``
    points equally spaced in arc length along the polyline through them, and ``floor`` the
    least IGD of any k of those samples (:func:`igd_floor`): the floor estimated from the
    members alone (``igd``/``floor`` − 1 is how far their placement is above it)."""
    points = normalise(front, front)
    ordered, lengths = _ordered(points), arc_lengths(points)
    along = np.linspace(0.0, lengths[-1], samples)
    curve = np.column_stack([np.interp(along, lengths, ordered[:, j]) for j in range(2)])
    return {"gaps": np.diff(lengths),
            "igd": float(np.mean(_nearest_point_distances(curve, ordered))),
            "floor": igd_floor(curve, len(ordered))}
