"""Obstacle rounds (:func:`avoid_obstacles`), for a problem with obstacles and no minimum
separation (with one, the separation rounds of :mod:`ocpar.formation.keep_out` impose the
obstacles' planes too): after the outer solve, keep every path clear of the problem's
obstacles (:mod:`ocpar.formation.obstacles`) on the continuous path, as the separation
rounds do: each round reads the latest paths and gives every interval that comes within
:data:`~ocpar.formation.obstacles.OBSTACLE_MARGIN` (scaled: |A (r − c)| < 1 + margin) of an
obstacle a half-space that keeps the whole segment out of it, the obstacle's tangent plane
(:func:`~ocpar.formation.obstacles.obstacle_half_spaces`). The agents with such intervals
re-solve their own DMOC problems (one superstep; keep-out slots of :mod:`ocpar.ocp.dmoc`,
elastic with the penalty :data:`~ocpar.formation.keep_out.PENALTY`, warm-started from their
latest path); the others keep theirs. Rounds repeat until every clearance is ≥ 0 (to
:data:`~ocpar.formation.obstacles.CLEARANCE_TOL` relative) and no node moved by more than
:data:`~ocpar.formation.keep_out.CHANGE_RTOL` of the smallest obstacle scale, or the round
limit. The clearance of the returned paths is computed, not assumed.

The final angles φ stay those of the obstacle-free outer solve (the rounds move the paths,
not the formation), as with the separation rounds; the cost increase is reported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import Columns
from ocpar.formation.keep_out import CHANGE_RTOL, PENALTY, resolve_with_keep_outs
from ocpar.formation.obstacles import (
    OBSTACLE_SLOTS,
    Clearance,
    cleared,
    closest_obstacle,
    obstacle_half_spaces,
)
from ocpar.formation.problem import FormationProblem


@dataclass
class ObstacleRounds:
    """Outcome of :func:`avoid_obstacles`: ``q``, ``u``, ``costs`` as the separation rounds'
    (:class:`~ocpar.formation.keep_out.Separation`), ``closest`` the smallest clearance,
    ``met`` whether it is ≥ 0 (:func:`~ocpar.formation.obstacles.cleared`), ``rounds``,
    ``change`` the last round's largest node move, ``inner_solves``, ``failed_solves``,
    ``retries``."""

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
    outcome = ObstacleRounds(q, u, costs, closest, cleared(closest, obstacles), 0, 0.0)
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
        outcome.met = cleared(outcome.closest, obstacles)
        if progress is not None:
            c = outcome.closest
            progress(f"obstacle round {outcome.rounds:3d}  agents {len(agents):6d}  "
                     f"clearance {c.distance:.6e} (agent {c.agent}, obstacle {c.obstacle})  "
                     f"moved {outcome.change:.1e}  cost {float(np.sum(costs)):.12e}")
    return outcome

