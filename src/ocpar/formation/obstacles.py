"""Static obstacles in position space, kept clear on the continuous paths by obstacle rounds.

An obstacle is a convex set the agents' positions r (the d ``position_indices`` of the
configuration) must stay out of at all times:

- :class:`Ellipsoid` {r : |A (r − c)| < 1}, A = diag(1/a) Rᵀ with semi-axes a along the
  columns of the rotation R (``axes`` its rows); :func:`Sphere` is the ellipsoid with equal
  semi-axes (a ball in d dimensions);
- :class:`HalfSpace` {r : n·r < b} (keep n·r ≥ b: a wall, a floor).

DMOC's continuous path is linear between nodes, so a path is clear of an obstacle exactly
when every segment is. :func:`segment_clearance` measures it on each segment: the Euclidean
distance for a sphere or a half-space, and for an ellipsoid the lower bound
min(a) (min_s |A (r(s) − c)| − 1) (A⁻¹ stretches by at least min(a)); negative inside.

:func:`obstacle_half_spaces` gives each interval near an obstacle the obstacle's tangent
plane n·r ≥ n·c + 1, n = Aᵀ ŷ, ŷ the unit direction (in the scaled space) of the segment's
point nearest the centre (the obstacle lies entirely on the other side: a supporting plane
of a convex set); on an interval with a fixed node (the first and the last) ŷ is that node's
direction instead, so that the fixed node, outside the obstacle, meets it too. A half-space
obstacle is its own plane. The rounds that impose these planes are
:mod:`ocpar.formation.obstacle_rounds` (obstacles alone) and
:mod:`ocpar.formation.keep_out` (with a minimum separation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ocpar.formation.separation import segment_closest
from ocpar.ocp.dmoc import UNUSED_OFFSET


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


@dataclass(frozen=True)
class Clearance:
    """The smallest clearance of any agent from any obstacle on the continuous paths:
    ``distance`` (length unit, negative inside; :func:`segment_clearance`), ``agent``,
    ``obstacle`` (index) and ``time`` (NaN, −1, −1, NaN without obstacles or paths)."""

    distance: float
    agent: int
    obstacle: int
    time: float


def segment_clearance(positions: np.ndarray, obstacles: Sequence[Obstacle]) -> np.ndarray:
    """Clearance (n, N, m) of each agent's segment k from obstacle o, positions (n, N+1, d)."""
    positions = np.asarray(positions, float)
    if not obstacles:
        return np.zeros((*positions.shape[:1], positions.shape[1] - 1, 0))
    return np.stack([o.clearance(positions[:, :-1], positions[:, 1:])[0] for o in obstacles],
                    axis=-1)


def closest_obstacle(positions: np.ndarray, obstacles: Sequence[Obstacle],
                     duration: float) -> Clearance:
    """The smallest clearance over agents, intervals and obstacles (:class:`Clearance`) on
    the piecewise-linear paths with nodes ``positions`` (n, N+1, d) over [0, ``duration``]."""
    positions = np.asarray(positions, float)
    if not obstacles or not np.all(np.isfinite(positions)):
        return Clearance(math.nan, -1, -1, math.nan)
    gaps = segment_clearance(positions, obstacles)
    agent, k, o = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
    _, s = obstacles[o].clearance(positions[agent, k], positions[agent, k + 1])
    h = duration / (positions.shape[1] - 1)
    return Clearance(float(gaps[agent, k, o]), int(agent), int(o), float((k + s) * h))


#: Intervals within this (scaled, |A (r − c)| − 1) of an obstacle get its half-space.
OBSTACLE_MARGIN = 0.5
#: Clearance counts as met at −this · (the obstacle's scale): the planes hold to the
#: solver's accuracy.
CLEARANCE_TOL = 1e-9
#: Obstacle half-spaces per interval at most (the nearest obstacles'; a dropped one is caught
#: by the next round's check).
OBSTACLE_SLOTS = 4


def obstacle_half_spaces(positions: np.ndarray, obstacles: Sequence[Obstacle], slots: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Keep-out data (n, N, slots, d + 2) from node positions (n, N+1, d): for each interval
    within :data:`OBSTACLE_MARGIN` of an obstacle (the nearest ``slots`` of them), its
    tangent plane (module docstring), static over the interval; unused slots 0 and
    :data:`~ocpar.ocp.dmoc.UNUSED_OFFSET`. And the agents (sorted) that have any."""
    n, nodes, dim = positions.shape
    intervals = nodes - 1
    data = np.zeros((n, intervals, slots, dim + 2))
    data[..., dim:] = UNUSED_OFFSET
    gaps = segment_clearance(positions, obstacles) / np.array([o.scale for o in obstacles])
    near = gaps < OBSTACLE_MARGIN
    order = np.argsort(np.where(near, gaps, np.inf), axis=-1, kind="stable")[..., :slots]
    for slot in range(min(slots, len(obstacles))):
        for o, obstacle in enumerate(obstacles):
            a, k = np.nonzero((order[..., slot] == o) & near[..., o])
            if not len(a):
                continue
            start, end = positions[a, k], positions[a, k + 1]
            _, s = obstacle.clearance(start, end)
            point = (1 - s[:, None]) * start + s[:, None] * end
            point[k == 0] = start[k == 0]                       # the fixed first node
            point[k == intervals - 1] = end[k == intervals - 1]  # the fixed last node
            normal, offset = obstacle.plane(point)
            data[a, k, slot, :dim] = normal
            data[a, k, slot, dim:] = offset[:, None]
    return data, np.flatnonzero(near.any(axis=(1, 2)))


def cleared(closest: Clearance, obstacles: Sequence[Obstacle]) -> bool:
    """Whether the clearance ``closest`` is ≥ −:data:`CLEARANCE_TOL` · (the smallest
    obstacle scale, length unit)."""
    return closest.distance >= -CLEARANCE_TOL * min(o.scale for o in obstacles)
