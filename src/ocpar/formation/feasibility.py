"""Where the formation's outer problem is feasible: every agent's inner problem has a solution.

Two mechanisms, one per kind of knowledge:

* **Exact reach sets** (box- or norm-limited point masses at rest at both ends,
  :mod:`ocpar.ocp.reach`): along a family of formations φ(θ) (a circle's common rotation,
  equal arc length's shift: :class:`~ocpar.formation.couplings.coupling.ShiftFamily`) agent i's
  target
  is reachable where e_i(θ) = excess of z(φ_i(θ)) − start_i over its reach set is ≤ 0;
  the feasible shifts are where E(θ) = max_i e_i(θ) ≤ 0 (:func:`feasible_window`: E on a
  grid of :data:`WINDOW_GRID` shifts over one period, the interval's ends by bisection).
  E is Lipschitz (|dE/dθ| ≤ L = max_i |z′(φ_i)| |dφ_i/dθ|, estimated on the grid with a
  margin of 2), so a feasible shift can hide between grid points only next to one where
  E ≤ L · spacing / 2; those are polished by a bounded local minimisation, and if none
  reaches E ≤ 0 the formation is refused (one line naming the agent that misses its reach
  at the best shift, and its limit). The start is the feasible shift nearest the given
  one, :data:`WINDOW_MARGIN` of the interval's width inside it; the outer Newton search
  stays inside the interval.
* **Failures as data** (any model and constraint): :func:`inner_costs` returns +∞ for an
  inner problem whose solve failed (and, where the reach set is exact, for one outside it,
  without solving it), so that cost tables and scans carry infeasibility as a value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.couplings.coupling import ShiftFamily
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import Surface
from ocpar.ocp import solve_tasks

#: Shifts (per period 2π) at which the largest reach excess E(θ) is evaluated.
WINDOW_GRID = 2048
#: Shifts per block of that evaluation (bounds its memory: block × n × d floats).
WINDOW_BLOCK = 64
#: The start lies at least this fraction of its feasible interval's width inside it.
WINDOW_MARGIN = 0.1


@dataclass(frozen=True)
class ShiftWindow:
    """The feasible interval ``low`` < θ < ``high`` (rad) of a family's shift that holds
    ``start``, the shift to start from (θ = 0 itself where it lies
    :data:`WINDOW_MARGIN` inside); the whole period if ``low`` = −∞."""

    low: float
    high: float
    start: float


def reach_excess(problem: FormationProblem, family: ShiftFamily, thetas: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """E(θ) = max_i e_i(θ) (K,) at the shifts ``thetas`` (K,) (length unit; ≤ 0: every agent
    with an exact reach set reaches its target) and the agent attaining it (K,); None if no
    agent has an exact reach set."""
    sets = problem.reach_sets()
    if not sets:
        return None
    starts = problem.positions(problem.starts)
    excess = np.full(len(thetas), -np.inf)
    worst = np.full(len(thetas), -1)
    for block in np.array_split(np.arange(len(thetas)), -(-len(thetas) // WINDOW_BLOCK)):
        phi = np.stack([family.angles(float(thetas[m]))[0] for m in block])   # (b, n)
        moves = problem.final_positions(phi.ravel()).reshape(*phi.shape, -1) - starts
        for reach, agents in sets:
            e = reach.excess(moves[:, agents])   # (b, len(agents))
            k = np.argmax(e, axis=1)
            top = e[np.arange(len(block)), k]
            better = top > excess[block]
            excess[block[better]], worst[block[better]] = top[better], agents[k[better]]
    return excess, worst


def _lipschitz(problem: FormationProblem, family: ShiftFamily, thetas: np.ndarray) -> float:
    """An estimate of max |dE/dθ| (length unit per rad): max_i |z′(φ_i)| |dφ_i/dθ| over the
    grid ``thetas``, with a margin of 2."""
    bound = 0.0
    for theta in thetas[:: max(1, len(thetas) // 64)]:
        phi, along, _ = family.angles(float(theta))
        speed = np.linalg.norm(problem.curve.tangents(phi), axis=1) * np.abs(along)
        bound = max(bound, float(np.max(speed)))
    return 2 * bound


def feasible_window(problem: FormationProblem, family: ShiftFamily) -> ShiftWindow | None:
    """The feasible interval of ``family``'s shift nearest θ = 0 and the start in it (module
    docstring); None where no agent's reach set is known exactly. Raises ValueError (one
    line, naming the agent and its limit) if no shift is feasible."""
    spacing = 2 * np.pi / WINDOW_GRID
    thetas = (np.arange(WINDOW_GRID) - WINDOW_GRID // 2) * spacing
    found = reach_excess(problem, family, thetas)
    if found is None:
        return None
    from scipy.optimize import minimize_scalar

    excess = found[0]

    def at(theta: float) -> float:
        return float(reach_excess(problem, family, np.array([theta]))[0][0])

    if np.all(excess <= 0):
        return ShiftWindow(-np.inf, np.inf, 0.0)
    if np.any(excess <= 0):   # the feasible grid shift nearest θ = 0
        inside = np.flatnonzero(excess <= 0)
        index = int(inside[np.argmin(np.abs(thetas[inside]))])
        centre = float(thetas[index])
    else:   # a feasible shift can hide between grid points only where E ≤ L · spacing / 2
        bound = _lipschitz(problem, family, thetas) * spacing / 2
        best = (np.inf, 0.0)
        for k in np.argsort(excess)[: int(np.sum(excess <= bound))] if bound > 0 else []:
            polish = minimize_scalar(at, bounds=(thetas[k] - spacing, thetas[k] + spacing),
                                     method="bounded", options={"xatol": 1e-12})
            best = min(best, (float(polish.fun), float(polish.x)))
            if polish.fun <= 0:
                break
        if not best[0] <= 0:
            theta = best[1] if np.isfinite(best[0]) else float(thetas[np.argmin(excess)])
            value, agent = (float(v[0]) for v in reach_excess(problem, family,
                                                               np.array([theta])))
            agent = int(agent)
            reach = next(r for r, members in problem.reach_sets() if agent in members)
            raise ValueError(
                f"{problem.limit_label(agent, reach)}: no formation lets every agent reach "
                f"its target from rest to rest: at the best shift ({theta:.4g} rad from the "
                f"initial guess) agent {agent} (mass {problem.shapes[agent].model.mass:g}) "
                f"still misses its reach by {value:.4g} (length unit)")
        centre, index = best[1], None
    low, high = (_end(at, centre, direction, spacing, excess, index)
                 for direction in (-1.0, 1.0))
    margin = WINDOW_MARGIN * (high - low)
    start = 0.0 if low + margin <= 0 <= high - margin else \
        float(np.clip(0.0, low + margin, high - margin))
    return ShiftWindow(low, high, start)


def _end(at, centre: float, direction: float, spacing: float, grid: np.ndarray,
         index: int | None) -> float:
    """The end, towards ``direction`` (±1), of the interval of E ≤ 0 that holds ``centre``
    (E(centre) ≤ 0): steps of the grid ``spacing`` until E > 0 (a period at most; read off
    the ``grid`` values where ``centre`` is its point ``index``), then bisection (Brent)."""
    from scipy.optimize import brentq
    inner = centre
    for step in range(1, WINDOW_GRID + 1):
        outer = inner + direction * spacing
        value = at(outer) if index is None else grid[(index + int(direction) * step)
                                                     % WINDOW_GRID]
        if value > 0:
            return brentq(at, min(inner, outer), max(inner, outer), xtol=1e-13)
        inner = outer
    return direction * np.inf   # E ≤ 0 at every grid shift this way: the whole period


def feasible_start(problem: FormationProblem, phi0: np.ndarray) -> np.ndarray:
    """``phi0`` moved along its family (:meth:`~ocpar.formation.couplings.coupling.Coupling.family`)
    to the feasible start of :func:`feasible_window`; ``phi0`` itself where there is no
    family or no exact reach set. Raises ValueError if no formation of the family is
    feasible."""
    if isinstance(problem.curve, Slots | Surface) or not problem.reach_sets():
        return phi0
    family = problem.coupling.family(phi0, problem.curve)
    if family is None:
        return phi0
    window = feasible_window(problem, family)
    if window is None or window.start == 0.0:
        return phi0
    return family.angles(window.start)[0]


def outside_reach(problem: FormationProblem, agents: np.ndarray, phi: np.ndarray
                  ) -> np.ndarray:
    """Mask (p,): agent ``agents[k]`` cannot reach its target at ``phi[k]`` (an angle, or a
    slot index) by its exact reach set (False where none is known)."""
    out = np.zeros(len(agents), dtype=bool)
    sets = problem.reach_sets()
    if not sets or isinstance(problem.curve, Surface):
        return out
    starts = problem.positions(problem.starts)
    for reach, members in sets:
        rows = np.flatnonzero(np.isin(agents, members))
        if len(rows):
            ends = problem.final_positions(phi[rows])
            out[rows] = reach.excess(ends - starts[agents[rows]]) > 0
    return out


@dataclass
class InnerCosts:
    """Ĵ (p,) of each pair, +∞ where infeasible; ``solved`` inner solves, ``failed`` of them
    failed, ``skipped`` pairs outside an exact reach set (not solved), and the first
    failure's words (``first_failure``, "" if none); ``gradients`` (p, d) dĴ/dz, the
    derivative of each pair's cost in its end position z (the first d entries of q_N, the
    target's dimension; cost unit per length unit), NaN where the cost is +∞."""

    costs: np.ndarray
    solved: int
    failed: int
    skipped: int
    first_failure: str
    gradients: np.ndarray | None = None


def inner_costs(problem: FormationProblem, backend: Backend, agents: np.ndarray,
                phi: np.ndarray) -> InnerCosts:
    """Ĵ of agent ``agents[k]`` ending at ``phi[k]`` (an angle, rad, or a slot index): one
    superstep of inner solves for the pairs inside their exact reach sets (all where none
    is known); failed solves and pairs outside are +∞ (failures are data)."""
    agents = np.asarray(agents, dtype=np.intp)
    rows = np.asarray(phi, float).reshape(len(agents), -1)   # on a surface 2 per pair
    costs = np.full(len(agents), np.inf)
    d = problem.curve.dim
    gradients = np.full((len(agents), d), np.nan)
    skip = outside_reach(problem, agents, rows[:, 0]) if rows.shape[1] == 1 \
        else np.zeros(len(agents), dtype=bool)
    todo = np.flatnonzero(~skip)
    failed, first = 0, ""
    if len(todo):
        sols = backend.superstep_columns(solve_tasks, problem.tasks_for(agents[todo],
                                                                        rows[todo].ravel()))
        success = np.asarray(sols.column("success"), dtype=bool)
        solved = np.asarray(sols.column("cost"), dtype=float)
        costs[todo[success]] = solved[success]
        nq = problem.common_shape.model.nq
        gradient = np.asarray(sols.column("cost_gradient"), float)[:, 2 * nq: 2 * nq + d]
        gradients[todo[success]] = gradient[success]
        bad = np.flatnonzero(~success)
        failed = len(bad)
        if failed:
            k = int(todo[bad[0]])
            first = (f"agent {agents[k]} ending at phi = {rows[k].tolist()}: "
                     f"{sols.column('status')[bad[0]]}")
    return InnerCosts(costs, len(todo), failed, int(np.sum(skip)), first, gradients)
