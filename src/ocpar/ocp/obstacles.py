"""Static obstacles in position space, and their exact keep-out on a DMOC path.

An obstacle is a convex set the positions r (d configuration entries) must stay out of at
all times of the continuous path, which DMOC represents as linear between nodes:

- :class:`Ellipsoid` {r : |A (r − c)| < 1}, A = diag(1/a) Rᵀ with semi-axes a along the
  rows of R (``axes``); :func:`Sphere` is the ellipsoid with equal semi-axes (a ball in d
  dimensions);
- :class:`HalfSpace` {r : n·r < b} (keep n·r ≥ b: a wall, a floor).

The NLP's formulation (:func:`obstacle_rows`; :mod:`ocpar.ocp.dmoc`, ``DmocShape.obstacles``):
in the scaled coordinates y = A (r − c) the ellipsoid is the unit ball, and a segment
[y_a, y_b] stays at distance ≥ 1 from its centre exactly when some plane separates them:
there is an n ∈ R^d with |n|² ≤ 1, n·y_a ≥ 1 and n·y_b ≥ 1 (⇐: every point of the segment
has n·y ≥ 1, so |y| ≥ 1; ⇒: n the unit direction of the segment's point nearest the centre).
Each interval k gets its own plane n_k per ellipsoid as inner decision variables, with the
three rows 1 − |n_k|² ≥ 0, n_k·y(q_k) − 1 ≥ 0, n_k·y(q_{k+1}) − 1 ≥ 0 (also on the first and
last intervals, whose boundary nodes are data: their rows bind n_k there). The constraint is
exact on the continuous path, smooth, in any dimension. A half-space is linear: n·r(q_k) ≥ b
at the free nodes (the path is linear between nodes; the boundary nodes are data, checked
by whoever builds the problem).

The same keep-out without planes (:func:`segment_rows`): one row per interval and ellipsoid,
|y*|² − 1 ≥ 0 at the scaled segment's point y* nearest the centre; exact too, C¹ but not C²
where y* reaches a node. It has no variables a QP sees without curvature (a plane no row
binds), so the batched solves use it, then return to the planes (:func:`canonical_planes`,
:func:`plane_multipliers`) and check the answer on the planes' NLP.

Which side a path passes an ellipsoid on is a discrete choice the guess of the planes and
the path makes (:func:`side_guesses`). :func:`guess_planes` gives each interval the unit
direction of its segment's point nearest the centre; :func:`canonical_planes` the planes
the sensitivities are computed with (unique where an obstacle binds, fixed where none).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

#: A guess's path is pushed out of an obstacle it enters to this scaled radius (1 + margin).
PUSH_RADIUS = 1.1
#: Where a guess's path enters more obstacles than this, both sides are tried for the first
#: this many of them (2^this solves at most); the others keep the side of their nearest point.
SIDE_OBSTACLES = 3


@dataclass(frozen=True)
class Ellipsoid:
    """Keep out of {r : |A (r − c)| < 1}: ``center`` c (d,), ``semi_axes`` a (d,) > 0 along
    the rows of ``axes`` (d, d, orthonormal; None: the coordinate axes); ``name`` labels it."""

    center: tuple[float, ...]
    semi_axes: tuple[float, ...]
    axes: tuple[tuple[float, ...], ...] | None = None
    name: str = "ellipsoid"

    def __post_init__(self) -> None:
        center = _vector(self.name, "center", self.center)
        d = len(center)
        semi_axes = _vector(self.name, "semi_axes", self.semi_axes, d)
        if not np.all(semi_axes > 0):
            raise ValueError(f"obstacle {self.name}: semi_axes must be > 0, got {semi_axes}")
        axes = np.eye(d) if self.axes is None else np.asarray(self.axes, float)
        if axes.shape != (d, d) or not np.allclose(axes @ axes.T, np.eye(d), atol=1e-9):
            raise ValueError(f"obstacle {self.name}: axes must be {d} orthonormal rows")
        object.__setattr__(self, "center", tuple(center.tolist()))
        object.__setattr__(self, "semi_axes", tuple(semi_axes.tolist()))
        object.__setattr__(self, "axes", tuple(map(tuple, axes.tolist())))

    @property
    def dim(self) -> int:
        return len(self.center)

    @property
    def scale(self) -> float:
        """The smallest semi-axis (length unit)."""
        return min(self.semi_axes)

    @property
    def matrix(self) -> np.ndarray:
        """A (d, d): r is inside when |A (r − c)| < 1."""
        return np.asarray(self.axes) / np.asarray(self.semi_axes)[:, None]

    def scaled(self, r: np.ndarray) -> np.ndarray:
        """y = A (r − c) of positions r (..., d)."""
        return (np.asarray(r) - np.asarray(self.center)) @ self.matrix.T

    def unscaled(self, y: np.ndarray) -> np.ndarray:
        """r = c + A⁻¹ y of scaled positions y (..., d)."""
        return np.asarray(self.center) + (np.asarray(y) * np.asarray(self.semi_axes)) \
            @ np.asarray(self.axes)

    def clearance(self, start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """On segments from ``start`` to ``end`` (..., d): min(a)(min_s |y(s)| − 1) (exact
        for a sphere, a lower bound of the distance otherwise) and the s of the nearest
        point."""
        size, s = segment_closest(self.scaled(start), self.scaled(end))
        return self.scale * (size - 1.0), s

    def plane(self, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The tangent half-spaces n·r ≥ b that keep out of the ellipsoid, facing positions
        ``point`` (m, d) (not the centre): n = Aᵀ ŷ (m, d), b = n·c + 1 (m,)."""
        y = self.scaled(point)
        length = np.linalg.norm(y, axis=1)
        y_hat = np.where(length[:, None] > 0, y / np.maximum(length, 1e-300)[:, None],
                         np.eye(self.dim)[0])
        normal = y_hat @ self.matrix
        return normal, normal @ np.asarray(self.center) + 1.0


def Sphere(center: Sequence[float], radius: float, name: str = "sphere") -> Ellipsoid:
    """The ball |r − c| < ``radius`` (an :class:`Ellipsoid` with equal semi-axes)."""
    center = _vector(name, "center", center)
    return Ellipsoid(tuple(center.tolist()), (float(radius),) * len(center), name=name)


@dataclass(frozen=True)
class HalfSpace:
    """Keep n·r ≥ b: ``normal`` n (d,), ``offset`` b; ``name`` labels it."""

    normal: tuple[float, ...]
    offset: float
    name: str = "half-space"

    def __post_init__(self) -> None:
        normal = _vector(self.name, "normal", self.normal)
        length = float(np.linalg.norm(normal))
        if not length > 0 or not math.isfinite(float(self.offset)):
            raise ValueError(f"obstacle {self.name}: needs a non-zero normal and a finite "
                             f"offset")
        object.__setattr__(self, "normal", tuple((normal / length).tolist()))
        object.__setattr__(self, "offset", float(self.offset) / length)

    @property
    def dim(self) -> int:
        return len(self.normal)

    @property
    def scale(self) -> float:
        return 1.0

    def clearance(self, start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """n·r − b at the nearer end of each segment (the distance to the plane; negative on
        the wrong side), and that end's s."""
        n = np.asarray(self.normal)
        a, b = np.asarray(start) @ n - self.offset, np.asarray(end) @ n - self.offset
        return np.minimum(a, b), (b < a).astype(float)

    def plane(self, point: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The half-space itself, for each of the m ``point`` rows."""
        m = len(point)
        return np.tile(self.normal, (m, 1)), np.full(m, self.offset)


Obstacle = Ellipsoid | HalfSpace


def _vector(obstacle: str, field: str, value: object, size: int | None = None) -> np.ndarray:
    """``value`` as a float vector (``size`` entries if given, finite), or one ValueError
    naming the obstacle and its ``field``."""
    try:
        array = np.asarray(value, float).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"obstacle {obstacle}: {field} must be numbers") from None
    if (size is not None and array.size != size) or not array.size or \
            not np.all(np.isfinite(array)):
        raise ValueError(f"obstacle {obstacle}: {field} must be {size or 'd'} finite numbers, "
                         f"got {value!r}")
    return array


def check_obstacles(obstacles: object, dim: int) -> tuple[Obstacle, ...]:
    """``obstacles`` as a tuple of :class:`Ellipsoid`/:class:`HalfSpace` in ``dim``
    dimensions, or one ValueError naming the field."""
    if obstacles is None:
        return ()
    if isinstance(obstacles, Ellipsoid | HalfSpace) or not isinstance(obstacles, Sequence):
        raise ValueError("obstacles: must be a list of Sphere, Ellipsoid or HalfSpace")
    for i, obstacle in enumerate(obstacles):
        if not isinstance(obstacle, Ellipsoid | HalfSpace):
            raise ValueError(f"obstacles[{i}]: must be a Sphere, Ellipsoid or HalfSpace, got "
                             f"{type(obstacle).__name__}")
        if obstacle.dim != dim:
            raise ValueError(f"obstacles[{i}] ({obstacle.name}): lies in {obstacle.dim}-D, the "
                             f"agents' positions in {dim}-D")
    return tuple(obstacles)


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


def ellipsoids(obstacles: Sequence[Obstacle]) -> tuple[Ellipsoid, ...]:
    """The ellipsoids among ``obstacles`` (the ones with planes), in order."""
    return tuple(o for o in obstacles if isinstance(o, Ellipsoid))


def obstacle_rows(obstacles: Sequence[Obstacle], nodes: Sequence[ca.SX], planes: ca.SX
                  ) -> list[ca.SX]:
    """The NLP rows (each ≥ 0, module docstring) keeping the path with node positions
    ``nodes`` (N+1 of them, each (d,)) out of ``obstacles``: per interval k, per ellipsoid e
    (in order) 1 − |n|², n·y(q_k) − 1, n·y(q_{k+1}) − 1 with n = ``planes`` entries
    ((k m_e + e) d, +d); then per half-space, n·r − b at the free nodes 1..N−1."""
    balls = ellipsoids(obstacles)
    intervals, dim = len(nodes) - 1, len(balls[0].center) if balls else 0
    rows = []
    for k in range(intervals):
        for e, ball in enumerate(balls):
            n = planes[(k * len(balls) + e) * dim:(k * len(balls) + e + 1) * dim]
            a, c = ca.DM(ball.matrix), ca.DM(ball.center)
            rows += [1 - ca.sumsqr(n)] + [ca.dot(n, a @ (nodes[node] - c)) - 1
                                          for node in (k, k + 1)]
    return rows + _half_space_rows(obstacles, nodes)


def _half_space_rows(obstacles: Sequence[Obstacle], nodes: Sequence[ca.SX]) -> list[ca.SX]:
    """n·r − b at the free nodes 1..N−1, per half-space among ``obstacles`` in order."""
    return [ca.dot(ca.DM(o.normal), nodes[k]) - o.offset for o in obstacles
            if isinstance(o, HalfSpace) for k in range(1, len(nodes) - 1)]


#: A segment of :func:`segment_rows` whose squared length in the ellipsoid's scaled space is
#: at most this is a point (s = 0; |y*| then differs from the segment's by at most 1e-12).
#: The quotient that places y* on a segment has no finite derivatives at a segment of length
#: 0: a node that repeats, as an ODE agent's sub-step states do in a guess at rest (zero
#: speed and control), made the rows' Hessian NaN there (IPOPT: Invalid_Number_Detected,
#: every elastic solve of phase 1 failed and its search had no point to go on from).
POINT_CHORD = 1e-24


def segment_rows(obstacles: Sequence[Obstacle], nodes: Sequence[ca.SX]) -> list[ca.SX]:
    """The keep-out of :func:`obstacle_rows` without planes: per interval k, per ellipsoid
    (in order) |y*|² − 1 ≥ 0, y* the point of the scaled segment [y(q_k), y(q_{k+1})]
    nearest the centre (its parameter s clipped to [0, 1]); then the same half-space rows.
    Exact (the segment clears the ellipsoid exactly when |y*| ≥ 1) and C¹ (the derivative
    is that at fixed s: 2(1 − s) y*, 2 s y*), not C² where s reaches 0 or 1. One row per
    interval instead of three and no plane variables: no directions of zero curvature where
    an obstacle is far, which the planes' free variables give a QP."""
    balls = ellipsoids(obstacles)
    rows = []
    for k in range(len(nodes) - 1):
        for ball in balls:
            a, c = ca.DM(ball.matrix), ca.DM(ball.center)
            start, end = a @ (nodes[k] - c), a @ (nodes[k + 1] - c)
            step = end - start
            length = ca.dot(step, step)
            chord = length > POINT_CHORD   # else a point: s = 0 (:data:`POINT_CHORD`)
            toward = ca.if_else(chord, -ca.dot(start, step) / ca.if_else(chord, length, 1), 0)
            s = ca.fmin(ca.fmax(toward, 0), 1)
            rows.append(ca.sumsqr(start + s * step) - 1)
    return rows + _half_space_rows(obstacles, nodes)


def plane_multipliers(obstacles: Sequence[Obstacle], positions: np.ndarray,
                      multipliers: np.ndarray) -> np.ndarray:
    """The multipliers (k, 3 N m_e + half-space rows) of :func:`obstacle_rows` that go with
    those of :func:`segment_rows` (k, N m_e + half-space rows) on paths with node positions
    (k, N+1, d), the planes those of :func:`canonical_planes`: per interval and ellipsoid
    λ (1, 2(1 − s), 2 s) for 1 − |n|², n·y_a − 1, n·y_b − 1 (s as in :func:`segment_rows`;
    then ∂L/∂n = 2 λ (y* − n) = 0 where the interval binds); the half-space rows' as they
    are."""
    balls = ellipsoids(obstacles)
    k, nodes = positions.shape[:2]
    count = (nodes - 1) * len(balls)
    if not balls:
        return multipliers
    s = np.stack([segment_closest(b.scaled(positions[:, :-1]), b.scaled(positions[:, 1:]))[1]
                  for b in balls], axis=2).reshape(k, count)
    lam = multipliers[:, :count]
    rows = np.stack([lam, 2 * (1 - s) * lam, 2 * s * lam], axis=2).reshape(k, 3 * count)
    return np.hstack([rows, multipliers[:, count:]])


def _nearest_directions(ball: Ellipsoid, positions: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """For paths with node positions (k, N+1, d): each interval's scaled distance from the
    centre (k, N) and the unit direction (k, N, d) of its point nearest the centre in the
    scaled space (a segment through the centre: perpendicular to it, :func:`_perpendicular`)."""
    y = ball.scaled(positions)
    size, s = segment_closest(y[:, :-1], y[:, 1:])
    point = (1 - s[..., None]) * y[:, :-1] + s[..., None] * y[:, 1:]
    through = size <= 1e-12
    direction = point / np.where(through, 1.0, size)[..., None]
    if np.any(through):
        direction[through] = _perpendicular(y[:, 1:][through] - y[:, :-1][through])
    return size, direction


def _perpendicular(step: np.ndarray) -> np.ndarray:
    """Unit vectors (m, d) perpendicular to ``step`` (m, d): the coordinate axis least
    aligned with it, with its component along it removed (the first axis for a zero step)."""
    step = np.asarray(step, float)
    d = step.shape[1]
    length = np.linalg.norm(step, axis=1, keepdims=True)
    unit = np.where(length > 0, step / np.maximum(length, 1e-300), 0.0)
    axis = np.eye(d)[np.argmin(np.abs(unit), axis=1)]
    out = axis - np.sum(axis * unit, axis=1, keepdims=True) * unit
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def guess_planes(obstacles: Sequence[Obstacle], positions: np.ndarray) -> np.ndarray:
    """The plane block of a guess (k, N m_e d) for paths with node positions (k, N+1, d):
    each interval's unit direction (scaled) of its segment's point nearest each ellipsoid's
    centre (on the side the path passes)."""
    balls = ellipsoids(obstacles)
    k, nodes, d = positions.shape
    if not balls:
        return np.zeros((k, 0))
    planes = np.stack([_nearest_directions(b, positions)[1] for b in balls], axis=2)
    return planes.reshape(k, (nodes - 1) * len(balls) * d)


def canonical_planes(obstacles: Sequence[Obstacle], positions: np.ndarray, tol: float,
                     loaded: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The planes the sensitivities use, for solved paths with node positions (k, N+1, d)
    whose ellipsoid rows of :func:`obstacle_rows` (k, 3 N m_e) carry a multiplier where
    ``loaded``: an interval binds where it comes within ``tol`` (scaled) of an ellipsoid or
    a row of its carries a multiplier; there the plane is the unit direction n* of its point
    nearest the centre (unique there), elsewhere n* shrunk to (1 + 1/δ)/2 · n* (δ > 1 its
    scaled distance: every row strictly inactive). Returns the plane block (k, N m_e d), the
    activity of those rows (k, 3 N m_e: 1 − |n|² where the interval binds, an end row where
    it binds and the row is within ``tol`` of 1 or loaded) and the planes whose variables
    are frozen, no row binding them (k, N m_e d)."""
    balls = ellipsoids(obstacles)
    k, d = positions.shape[0], positions.shape[2]
    if not balls:
        return np.zeros((k, 0)), np.zeros((k, 0), bool), np.zeros((k, 0), bool)
    planes, rows, frozen = [], [], []
    loaded = np.asarray(loaded, bool).reshape(k, -1, len(balls), 3)
    for e, ball in enumerate(balls):
        size, direction = _nearest_directions(ball, positions)
        binds = (size <= 1 + tol) | loaded[:, :, e].any(axis=-1)
        scale = np.where(binds, 1.0, (1 + 1 / np.maximum(size, 1.0)) / 2)
        n = direction * scale[..., None]
        y = ball.scaled(positions)
        ends = [np.einsum("kjd,kjd->kj", direction, y[:, :-1]) - 1,
                np.einsum("kjd,kjd->kj", direction, y[:, 1:]) - 1]
        rows.append(np.stack([binds] + [binds & ((end <= tol) | loaded[:, :, e, j + 1])
                                        for j, end in enumerate(ends)], axis=-1))
        planes.append(n)
        frozen.append(np.repeat(~binds[..., None], d, axis=-1))
    return (np.stack(planes, axis=2).reshape(k, -1), np.stack(rows, axis=2).reshape(k, -1),
            np.stack(frozen, axis=2).reshape(k, -1))


def entered(obstacles: Sequence[Obstacle], positions: np.ndarray
            ) -> list[tuple[int, np.ndarray]]:
    """The ellipsoids a path with node positions (N+1, d) enters, in order: (index among
    :func:`ellipsoids`, the unit direction (d,) in the scaled space of the path's point nearest the
    centre, the side the path passes it on)."""
    hits = []
    for e, ball in enumerate(ellipsoids(obstacles)):
        size, direction = _nearest_directions(ball, positions[None])
        j = int(np.argmin(size[0]))
        if size[0, j] < 1:
            hits.append((e, direction[0, j]))
    return hits


def on_near_side(obstacles: Sequence[Obstacle], reference: np.ndarray,
                 positions: np.ndarray) -> bool:
    """Whether a path with node positions ``positions`` (N+1, d) passes every ellipsoid that
    the path ``reference`` (N+1, d) enters on the side of ``reference``'s point nearest its
    centre (the scaled directions of the two paths' nearest points at an acute angle; True
    where ``reference`` enters none): the side :func:`side_guesses` tries first."""
    balls = ellipsoids(obstacles)
    for e, side in entered(obstacles, reference):
        size, direction = _nearest_directions(balls[e], positions[None])
        if not float(direction[0, int(np.argmin(size[0]))] @ side) > 0:
            return False
    return True


def side_guesses(obstacles: Sequence[Obstacle], positions: np.ndarray
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """The guesses (path (N+1, d), plane block (N m_e d,)) whose sides to try, from a guess
    path with node positions (N+1, d): the path and :func:`guess_planes` if it enters no
    ellipsoid; else, for each choice of side of the first :data:`SIDE_OBSTACLES` ellipsoids
    it enters (+ first: the side of the path's point nearest the centre), its free nodes
    inside pushed out along that side's direction u to the scaled radius
    :data:`PUSH_RADIUS` (the others pushed to their nearest side), each interval's plane
    the direction of its nearest point, or u where it still cuts the ellipsoid."""
    balls = ellipsoids(obstacles)
    hits = entered(obstacles, positions)
    if not hits:
        return [(positions, guess_planes(obstacles, positions[None])[0])]
    guesses = []
    for signs in itertools.product((1.0, -1.0), repeat=min(len(hits), SIDE_OBSTACLES)):
        path = positions.copy()
        for (e, side), sign in itertools.zip_longest(hits, signs, fillvalue=1.0):
            ball, u = balls[e], sign * side
            y = ball.scaled(path[1:-1])
            along = y @ u
            inside = np.einsum("md,md->m", y, y) < PUSH_RADIUS**2
            t = -along + np.sqrt(np.maximum(along**2 - np.sum(y**2, axis=1) + PUSH_RADIUS**2,
                                            0.0))
            y[inside] += t[inside, None] * u
            path[1:-1] = ball.unscaled(y)
        planes = guess_planes(obstacles, path[None]).reshape(len(path) - 1, len(balls), -1)
        for (e, side), sign in itertools.zip_longest(hits, signs, fillvalue=1.0):
            size, _ = _nearest_directions(balls[e], path[None])
            planes[size[0] < 1, e] = sign * side
        guesses.append((path, planes.ravel()))
    return guesses


def keep_out_rows(data: ca.SX, points: list[ca.SX], steps: int, n: int, slots: int,
                  positions: list[int], slack: ca.SX) -> list[ca.SX]:
    """The keep-out half-spaces' rows n·r − b + σ ≥ 0 (a formation's separation rounds) at
    the points of a path's polyline: ``points`` (n ``steps`` + 1) the nodes and, with
    ``steps`` > 1, the ``steps`` − 1 states between each two (an RK4 path's sub-steps), r their
    entries ``positions``; for each interval k and slot s, from the keep-out block ``data``
    (per interval and slot: the normal n, then the offsets b⁰ at node k and b¹ at node k + 1,
    b linear in time between) and the slack σ[k·slots + s]. The first and last points are
    data (the boundary), not rows."""
    dim = len(positions)
    rows = []
    for k in range(n):
        for s in range(slots):
            start = (k * slots + s) * (dim + 2)
            normal = data[start:start + dim]
            first, last = data[start + dim], data[start + dim + 1]
            rows += [ca.dot(normal, points[k * steps + j][positions])
                     - ((1 - j / steps) * first + j / steps * last) + slack[k * slots + s]
                     for j in range(steps + 1) if 0 < k * steps + j < n * steps]
    return rows
