"""Static obstacles of a formation: the agents' inner problems keep them clear, this module
checks and reports it on the returned paths.

The obstacles (:class:`Ellipsoid`, :func:`Sphere`, :class:`HalfSpace`) and their exact
formulation in each agent's DMOC NLP (one separating plane per interval and ellipsoid as
inner variables) are in :mod:`ocpar.ocp.obstacles`; a
:class:`~ocpar.formation.FormationProblem` attaches its obstacles to every agent's shape, so
that each Ĵ_i and its sensitivities include them and the outer solver moves the formation
for them.

DMOC's continuous path is linear between nodes, so a path is clear of an obstacle exactly
when every segment is. :func:`segment_clearance` measures it on each segment, independently
of the planes that produced the path: the Euclidean distance for a sphere or a half-space,
and for an ellipsoid the lower bound min(a) (min_s |A (r − c)| − 1) (A⁻¹ stretches by at
least min(a)); negative inside. :func:`passing_sides` says on which side each agent passed
each ellipsoid. An ODE agent's path is no chain of segments: the verification hands these
functions its path re-integrated densely
(:func:`~ocpar.formation.verify.checked_positions`), whose polyline they measure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ocpar.ocp.obstacles import (
    Ellipsoid,
    HalfSpace,
    Obstacle,
    Sphere,
    check_obstacles,
    segment_closest,
)


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
                     duration: float | np.ndarray) -> Clearance:
    """The smallest clearance over agents, intervals and obstacles (:class:`Clearance`) on
    the piecewise-linear paths with nodes ``positions`` (n, N+1, d) over [0, ``duration``]
    (one T, or (n,) each agent's own)."""
    positions = np.asarray(positions, float)
    if not obstacles or not np.all(np.isfinite(positions)):
        return Clearance(math.nan, -1, -1, math.nan)
    gaps = segment_clearance(positions, obstacles)
    agent, k, o = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
    _, s = obstacles[o].clearance(positions[agent, k], positions[agent, k + 1])
    h = float(np.broadcast_to(duration, positions.shape[:1])[agent]) / (positions.shape[1] - 1)
    return Clearance(float(gaps[agent, k, o]), int(agent), int(o), float((k + s) * h))


#: Clearance counts as met at −this · (the obstacle's scale): the planes hold to the
#: solver's accuracy.
CLEARANCE_TOL = 1e-9


def cleared(closest: Clearance, obstacles: Sequence[Obstacle]) -> bool:
    """Whether the clearance ``closest`` is ≥ −:data:`CLEARANCE_TOL` · (the smallest
    obstacle scale, length unit)."""
    return closest.distance >= -CLEARANCE_TOL * min(o.scale for o in obstacles)


def passing_sides(positions: np.ndarray, obstacles: Sequence[Obstacle]
                  ) -> list[list[str | list[float] | None]]:
    """On which side each agent passes each obstacle, from node paths ``positions``
    (n, N+1, d): per agent a list with one entry per obstacle, for an ellipsoid in 2-D
    ``left`` or ``right`` (the centre lies on the agent's left or right at its point of
    closest approach, seen along its direction of travel there), in other dimensions the
    unit vector (d,) from the centre to that point (scaled space); None for a half-space
    (no sides) or a path that is not finite."""
    positions = np.asarray(positions, float)
    n, _, d = positions.shape
    sides: list[list[str | list[float] | None]] = [[] for _ in range(n)]
    finite = np.all(np.isfinite(positions), axis=(1, 2))
    for obstacle in obstacles:
        if not isinstance(obstacle, Ellipsoid):
            for row in sides:
                row.append(None)
            continue
        y = obstacle.scaled(positions)
        size, s = segment_closest(y[:, :-1], y[:, 1:])
        k = np.argmin(np.where(np.isfinite(size), size, np.inf), axis=1)
        a = np.arange(n)
        point = (1 - s[a, k, None]) * y[a, k] + s[a, k, None] * y[a, k + 1]
        step = y[a, k + 1] - y[a, k]
        for i in range(n):
            if not finite[i]:
                sides[i].append(None)
            elif d == 2:   # the centre (origin) seen from the point, against the travel
                cross = step[i, 0] * -point[i, 1] - step[i, 1] * -point[i, 0]
                sides[i].append("left" if cross > 0 else "right")
            else:
                size_i = float(np.linalg.norm(point[i]))
                sides[i].append((point[i] / size_i).tolist() if size_i > 0 else None)
    return sides


__all__ = ["CLEARANCE_TOL", "Clearance", "Ellipsoid", "HalfSpace", "Obstacle", "Sphere",
           "check_obstacles", "cleared", "closest_obstacle", "passing_sides",
           "segment_clearance"]
