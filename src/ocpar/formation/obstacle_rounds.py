"""Obstacle rounds (:func:`avoid_obstacles`): after the outer solve, keep every path clear of the
problem's obstacles (:mod:`ocpar.formation.obstacles`) on the continuous path, as the separation
rounds of :mod:`ocpar.formation.keep_out`: each round reads the latest paths and gives every
interval that comes within :data:`OBSTACLE_MARGIN` (scaled: |A (r − c)| < 1 + margin) of an
obstacle a half-space that keeps the whole segment out of it, the obstacle's tangent plane
n·r ≥ n·c + 1 with n = Aᵀ ŷ, ŷ the unit direction (in the scaled space) of the segment's
point nearest the centre (the obstacle lies entirely on the other side: a supporting plane
of a convex set). On an interval with a fixed node (the first and the last) ŷ is that
node's direction instead, so that the fixed node, outside the obstacle, meets it too. A
half-space obstacle is its own plane. The agents with such intervals re-solve their own
DMOC problems (one superstep; keep-out slots of :mod:`ocpar.ocp.dmoc`, elastic with the
penalty :data:`~ocpar.formation.keep_out.PENALTY`, warm-started from their latest path); the
others keep theirs. Rounds repeat until every clearance is ≥ 0 (to
:data:`CLEARANCE_TOL` relative) and no node moved by more than
:data:`~ocpar.formation.keep_out.CHANGE_RTOL` of the smallest obstacle scale, or the round
limit. The clearance of the returned paths is computed, not assumed.

The final angles φ stay those of the obstacle-free outer solve (the rounds move the paths,
not the formation), as with the separation rounds; the cost increase is reported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import Columns
from ocpar.formation.keep_out import CHANGE_RTOL, PENALTY, resolve_with_keep_outs
from ocpar.formation.obstacles import (
    Clearance,
    Obstacle,
    closest_obstacle,
    segment_clearance,
)
from ocpar.formation.problem import FormationProblem
from ocpar.ocp.dmoc import UNUSED_OFFSET

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


@dataclass
class ObstacleRounds:
    """Outcome of :func:`avoid_obstacles`: ``q``, ``u``, ``costs`` as the separation rounds'
    (:class:`~ocpar.formation.keep_out.Separation`), ``closest`` the smallest clearance,
    ``met`` whether it is ≥ 0 (to :data:`CLEARANCE_TOL`), ``rounds``, ``change`` the last
    round's largest node move, ``inner_solves``, ``failed_solves``, ``retries``."""

    q: np.ndarray
    u: np.ndarray
    costs: np.ndarray
    closest: Clearance
    met: bool
    rounds: int
    change: float
    inner_solves: int = 0
    failed_solves: int = 0
    retries: int = 0


def avoid_obstacles(problem: FormationProblem, backend: Backend, phi: np.ndarray, base: Columns,
                    max_rounds: int, progress: Callable[[str], None] | None = None
                    ) -> ObstacleRounds:
    """Obstacle rounds (module docstring) for ``problem``'s obstacles from the obstacle-free
    inner solutions ``base`` (one per agent, at angles ``phi`` (n,) rad), at most
    ``max_rounds`` rounds."""
    obstacles = problem.obstacles
    slots = min(OBSTACLE_SLOTS, len(obstacles))
    positions_of = problem.positions
    slotted = problem.with_shapes(lambda shape: dataclasses.replace(
        shape, keep_out_slots=slots, keep_out_positions=problem.position_indices,
        solver="ipopt"))
    duration = problem.common_shape.duration
    scale = min(o.scale for o in obstacles)
    n = problem.agents
    free_cost = np.asarray(base.column("cost"), float)
    q, u = np.array(base.column("q"), float), np.array(base.column("u"), float)
    costs = free_cost.copy()
    boundary = problem.boundary_params_rows(np.arange(n), phi)
    penalty = PENALTY * max(float(np.max(free_cost)), 1e-300) / scale
    closest = closest_obstacle(positions_of(q), obstacles, duration)
    outcome = ObstacleRounds(q, u, costs, closest, _met(closest, scale), 0, 0.0)
    while not (outcome.met and (outcome.rounds == 0 or outcome.change <= CHANGE_RTOL * scale)
               ) and outcome.rounds < max_rounds:
        before = positions_of(q)
        data, agents = obstacle_half_spaces(before, obstacles, slots)
        if not len(agents):
            outcome.change = 0.0
            break
        resolve_with_keep_outs(slotted, backend, agents, boundary, data, penalty, outcome)
        outcome.change = float(np.abs(positions_of(q) - before).max())
        outcome.closest = closest_obstacle(positions_of(q), obstacles, duration)
        outcome.met = _met(outcome.closest, scale)
        if progress is not None:
            c = outcome.closest
            progress(f"obstacle round {outcome.rounds:3d}  agents {len(agents):6d}  "
                     f"clearance {c.distance:.6e} (agent {c.agent}, obstacle {c.obstacle})  "
                     f"moved {outcome.change:.1e}  cost {float(np.sum(costs)):.12e}")
    return outcome


def _met(closest: Clearance, scale: float) -> bool:
    return closest.distance >= -CLEARANCE_TOL * scale
