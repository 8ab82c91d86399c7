"""Where the formation's outer problem is feasible: every agent's inner problem has a solution.

Three mechanisms:

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
* **Phase 1** (any model, constraint, target and coupling, where the start is infeasible):
  each agent's elastic inner problem (:func:`elastic_shape`, ``DmocShape.elastic`` or
  ``MsEndpointShape.elastic`` for an ODE agent: slack on
  the end conditions, control bounds and inequality rows, the total slack minimised) gives
  s_i(φ_i) ≥ 0, 0 exactly where the agent is feasible, and ds_i/dz from its multipliers
  (:func:`elastic_slacks`); :func:`phase_one` drives S = Σ_i s_i to zero with the outer
  problem's own freedom (a family's shift, the coupling's free directions, the assignment
  of agents to the formation's points) or raises :class:`NoFeasibleFormation` with the
  smallest S it reached. The outer solvers call it only where their start's inner solves
  fail: a feasible start costs nothing more.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import Columns
from ocpar.formation.couplings.coupling import PROJECTION_TOL, ShiftFamily
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import EllipsoidSurface, Surface
from ocpar.ocp import DmocShape, MsEndpointShape, solve_tasks

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
    """Mask (p,): agent ``agents[k]`` cannot reach its target at ``phi[k]`` (an angle, a
    slot index, or on a surface ``phi`` (p, 2) its parameters) by its exact reach set (False
    where none is known)."""
    out = np.zeros(len(agents), dtype=bool)
    sets = problem.reach_sets()
    if not sets:
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
    skip = outside_reach(problem, agents, rows[:, 0] if rows.shape[1] == 1 else rows)
    todo = np.flatnonzero(~skip)
    failed, first = 0, ""
    if len(todo):
        sols = backend.superstep_columns(solve_tasks, problem.tasks_for(agents[todo],
                                                                        rows[todo].ravel()))
        success = np.asarray(sols.column("success"), dtype=bool)
        solved = np.asarray(sols.column("cost"), dtype=float)
        costs[todo[success]] = solved[success]
        gradient = np.asarray(sols.column("cost_gradient"), float)[
            :, problem.end_position_params]
        gradients[todo[success]] = gradient[success]
        bad = np.flatnonzero(~success)
        failed = len(bad)
        if failed:
            k = int(todo[bad[0]])
            first = (f"agent {agents[k]} ending at phi = {rows[k].tolist()}: "
                     f"{sols.column('status')[bad[0]]}")
    return InnerCosts(costs, len(todo), failed, int(np.sum(skip)), first, gradients)


# ----------------------------------------------------------------------------------------
# Phase 1: the elastic inner problem, any model, target and coupling
# ----------------------------------------------------------------------------------------

#: A total slack at most this counts as feasible. Each slack is measured against a
#: characteristic size (:mod:`ocpar.ocp.dmoc`: the end position's in the length unit, the end
#: velocity's times T, a control bound's and a path row's relative to the bound), so it is
#: 1e-8 length units or 1e-8 of a bound. Pairs the hard solve solves where the elastic
#: measure is in doubt are 0 exactly (:func:`elastic_slacks`).
SLACK_TOL = 1e-8
#: An elastic slack above :data:`SLACK_TOL` but at most this is checked by the hard solve
#: (IPOPT can stop at "Solved_To_Acceptable_Level" short of 0: 2e-8 was reported for a
#: feasible agent past the obstacle example's disc).
CONFIRM_SLACK = 1e-5
#: Shifts of a family at which the total slack is evaluated (one superstep each scan) before
#: descent: a coarse scan, and a finer one only if no descent from the first reached S = 0.
PHASE_ONE_SCANS = (8, 64)
#: Turned copies of a start on an ellipsoid with rotational symmetry (one superstep).
PHASE_ONE_TURNS = 32
#: Turned starts phase 1 descends from at most, the least total slack first.
PHASE_ONE_STARTS = 4
#: Steps of one descent of phase 1 at most (each a superstep of n elastic solves, plus halvings).
PHASE_ONE_STEPS = 60
#: A descent whose accepted step lowers S by less than this fraction has stalled at a local
#: minimum above 0 (S falls to 0 in few steps near a feasible region: it grows linearly).
STALL_RTOL = 0.02
#: The Polyak step s/|g|² (the step to the zero of a function of linear growth) is taken
#: this much longer, so that it crosses into the feasible region rather than onto its edge.
POLYAK_OVERSHOOT = 1.5


class InnerSolveFailed(RuntimeError):
    """Some inner solves of a superstep failed; the outer problem cannot go on."""


class NoFeasibleFormation(InnerSolveFailed):
    """Phase 1 found no formation with every agent feasible; ``slack`` the smallest total
    slack Σ_i s_i it reached."""

    def __init__(self, message: str, slack: float) -> None:
        super().__init__(message)
        self.slack = slack


def elastic_shape(shape: DmocShape | MsEndpointShape) -> DmocShape | MsEndpointShape:
    """``shape``'s elastic (phase-1) NLP (:mod:`ocpar.ocp.dmoc`,
    :mod:`ocpar.ocp.ms_endpoint`), solved by IPOPT (the
    batched ``sqpmethod`` spends its iteration limit on the degenerate ℓ1 problem: ~0.4 s a
    batch against ~3 ms a task): built once per shape and worker like any other, by the
    same cache."""
    return dataclasses.replace(shape, elastic=True, solver="ipopt")


def elastic_problem(problem: FormationProblem) -> FormationProblem:
    """``problem`` with every agent's shape elastic (once per problem)."""
    cached = problem.__dict__.get("_elastic")
    if cached is None:
        cached = problem.with_shapes(elastic_shape)
        object.__setattr__(problem, "_elastic", cached)
    return cached


@dataclass
class Slacks:
    """The elastic measures s (p,) ≥ 0 of pairs (agent, end parameter) and ds/dz (p, d) w.r.t.
    the end position z (the slacks' units per length unit, :data:`SLACK_TOL`); ``failed``
    elastic solves failed (the first's words in ``first_failure``), ``solves`` the elastic
    and hard solves made."""

    slack: np.ndarray
    end_gradient: np.ndarray
    failed: int = 0
    first_failure: str = ""
    solves: int = 0


def elastic_slacks(problem: FormationProblem, backend: Backend, agents: np.ndarray,
                   phi: np.ndarray) -> Slacks:
    """s_i of agent ``agents[k]`` ending at ``phi[k]`` (an angle, a surface's 2 parameters,
    or a slot index; rows of ``phi``), one superstep of elastic solves (0: feasible), and
    ds_i/dz from their multipliers. An elastic solve that fails (it has a solution for every
    p) counts as +∞ with a zero gradient. The hard solve is the truth where the elastic
    measure is in doubt (:func:`_in_doubt`: a slack above :data:`SLACK_TOL` but at most
    :data:`CONFIRM_SLACK`, an IPOPT stop short of 0; any slack above :data:`SLACK_TOL` of
    an agent with obstacles, whose elastic NLP has local minima above 0): those pairs' hard
    inner problems are solved (a second superstep, :func:`inner_costs`), and a pair it
    solves is feasible, s = 0, ds/dz = 0."""
    agents = np.asarray(agents, dtype=np.intp)
    rows = np.asarray(phi, float).reshape(len(agents), -1)
    elastic = elastic_problem(problem)
    sols = backend.superstep_columns(solve_tasks, elastic.tasks_for(agents, rows.ravel()))
    success = np.asarray(sols.column("success"), dtype=bool)
    slack = np.maximum(np.where(success, np.asarray(sols.column("cost"), dtype=float),
                                np.inf), 0.0)
    gradient = np.where(success[:, None], _end_gradients(problem, agents, sols), 0.0)
    bad = np.flatnonzero(~success)
    first = (f"agent {agents[bad[0]]} ending at phi = {rows[bad[0]].tolist()}: "
             f"{sols.column('status')[bad[0]]}") if len(bad) else ""
    doubt = np.flatnonzero(_in_doubt(problem, agents, slack))
    solves = len(agents)
    if len(doubt):
        hard = inner_costs(problem, backend, agents[doubt], rows[doubt])
        solves += hard.solved
        feasible = doubt[np.isfinite(hard.costs)]
        slack[feasible], gradient[feasible] = 0.0, 0.0
    return Slacks(slack, gradient, len(bad), first, solves)


def _end_gradients(problem: FormationProblem, agents: np.ndarray, sols: Columns
                   ) -> np.ndarray:
    """ds/dz (k, d) of the elastic solutions ``sols`` of ``agents``: their ``cost_gradient``'s
    end-position entries (each shape's ``boundary_size`` + ``end_position_entries``)."""
    d = problem.curve.dim
    gradients = sols.column("cost_gradient")
    out = np.empty((len(agents), d))
    for shape, members in problem.agents_by_shape().items():
        rows = np.flatnonzero(np.isin(agents, members))
        if len(rows):
            entries = shape.boundary_size + shape.end_position_entries(d)
            out[rows] = np.asarray([gradients[k] for k in rows])[:, entries]
    return out


def _in_doubt(problem: FormationProblem, agents: np.ndarray, slack: np.ndarray
              ) -> np.ndarray:
    """Mask: the elastic slack of agent ``agents[k]``, ``slack[k]``, is to be checked by the
    hard solve (:func:`elastic_slacks`)."""
    above = np.isfinite(slack) & (slack > SLACK_TOL)
    shapes = problem.shapes
    obstacles = np.array([bool(shapes[i].obstacles) for i in range(problem.agents)])
    return above & ((slack <= CONFIRM_SLACK) | obstacles[agents])


def parameter_gradient(problem: FormationProblem, phi: np.ndarray, d_end: np.ndarray
                       ) -> np.ndarray:
    """d/dφ (n k,) of Σ_i f_i(z(φ_i)) from each agent's df_i/dz, ``d_end`` (n, ≥ d): on a
    curve df_i/dz · z′(φ_i), on a surface (∂z/∂φ_i)ᵀ ∇f_i (agent i's at 2i, 2i+1)."""
    if isinstance(problem.curve, Surface):
        along = problem.curve.jacobians(np.reshape(phi, (-1, 2)))
        return np.einsum("id,idk->ik", d_end[:, : along.shape[1]], along).ravel()
    tangents = problem.curve.tangents(phi)
    return np.sum(d_end[:, : tangents.shape[1]] * tangents, axis=1)


@dataclass
class PhaseOne:
    """Outcome of :func:`phase_one`: ``phi`` where Σ_i s_i ≤ :data:`SLACK_TOL` (the start
    of phase 2), ``theta`` its shift where the search ran along a family (else None),
    ``slack`` the total there, ``inner_solves`` elastic (and, for an assignment, hard) solves
    made, ``steps`` descent steps taken."""

    phi: np.ndarray
    theta: float | None
    slack: float
    inner_solves: int
    steps: int


def phase_one(problem: FormationProblem, backend: Backend, phi0: np.ndarray,
              family: ShiftFamily | None = None, low: float = -np.inf, high: float = np.inf,
              progress: Callable[[str], None] | None = None) -> PhaseOne:
    """A feasible formation from an infeasible start ``phi0`` (on c(φ) = 0): minimise the
    total slack S(φ) = Σ_i s_i(φ_i) of the agents' elastic inner problems
    (:func:`elastic_slacks`) over the outer problem's own freedom until S ≤ :data:`SLACK_TOL`:

    * along ``family`` (its shift θ in (``low``, ``high``), a period if unbounded): S at
      the shifts of each scan of :data:`PHASE_ONE_SCANS` in one superstep, then descent from
      each of the scan's local minima, least first, while within twice the least S (one start
      per basin the scan resolves: a descent from another of its points ends at the same
      minimum; none from where an earlier descent ended), the finer scan only if no descent
      from the coarse one reached S = 0;
    * otherwise along the coupling's free directions Z at φ (none where its solutions are
      isolated): steps −α ZZᵀ∇S, each retracted onto c = 0;
    * where the coupling's solutions may be permuted among the agents (the permuted φ still
      solves c = 0: the potential; the slots), the assignment of the agents to the start's
      points minimising S (an n × n table of elastic solves, one superstep), then among the
      assignments with every pair feasible the cheapest (a superstep of hard solves of those
      pairs); then the descent again.

    A descent step is the Polyak step α = :data:`POLYAK_OVERSHOOT` S/|ZZᵀ∇S|² (S grows
    linearly outside the feasible set), at most π/2 in any angle, halved until S falls and
    doubled (up to that) after each step that lowers it: near a minimum of S above 0, where
    the Polyak step is far too long, the length that last lowered S is kept. Raises
    :class:`NoFeasibleFormation` (one line: the smallest S found, the agent with the largest
    s_i there) if S stays above :data:`SLACK_TOL`."""
    search = _Search(problem, backend, progress)
    if isinstance(problem.curve, Slots):
        return search.assign(np.asarray(phi0, float), final=True)
    if family is not None:
        return search.along_family(family, low, high)
    # the start, and turned copies of its points where they solve c = 0, least S first
    starts = search.turned(np.asarray(phi0, float).ravel())
    for k in range(min(PHASE_ONE_STARTS, len(starts))):
        phi = search.descend(starts[k])
        if search.best[0] <= SLACK_TOL:
            break
    if search.best[0] > SLACK_TOL and search.permutable(phi):
        phi = search.assign(phi).phi
        if search.best[0] > SLACK_TOL:
            phi = search.descend(phi)
    return search.result(phi, None)


def _basins(totals: np.ndarray, periodic: bool) -> list[int]:
    """The indices of a scan's totals (K,) that are local minima (below the one before, at
    most the one after; a ``periodic`` scan's ends are neighbours, else an end has one), least
    first: one start per basin the scan resolves (a descent from another point of a basin
    ends at its minimum too)."""
    before, after = np.roll(totals, 1), np.roll(totals, -1)
    if not periodic:
        before[0], after[-1] = np.inf, np.inf
    with np.errstate(invalid="ignore"):
        low = (totals < before) & (totals <= after) & np.isfinite(totals)
    if not low.any():   # flat (or one point): the least
        return [int(np.nanargmin(totals))] if np.any(np.isfinite(totals)) else []
    found = np.flatnonzero(low)
    return [int(k) for k in found[np.argsort(totals[found], kind="stable")]]


class _Search:
    """The state of one :func:`phase_one`: solves made, the best (S, φ) seen."""

    def __init__(self, problem: FormationProblem, backend: Backend,
                 progress: Callable[[str], None] | None) -> None:
        self.problem, self.backend, self.progress = problem, backend, progress
        self.solves, self.steps, self.failed, self.first_failure = 0, 0, 0, ""
        self.best: tuple[float, np.ndarray | None, np.ndarray | None] = (np.inf, None, None)

    def measured(self, found: Slacks) -> Slacks:
        """``found``, its elastic solves counted (and their first failure kept)."""
        self.solves += found.solves
        self.failed += found.failed
        self.first_failure = self.first_failure or found.first_failure
        return found

    def slacks(self, phi: np.ndarray) -> Slacks:
        n = self.problem.agents
        found = self.measured(elastic_slacks(self.problem, self.backend, np.arange(n), phi))
        total = float(np.sum(found.slack))
        if total < self.best[0]:
            self.best = (total, np.array(phi, float), found.slack)
        if self.progress is not None:
            self.progress(f"phase 1: total slack {total:.6e}")
        return found

    def result(self, phi: np.ndarray, theta: float | None) -> PhaseOne:
        total, best_phi, slack = self.best
        if not np.isfinite(total):   # no measure: the elastic solves failed (a solver limit)
            raise InnerSolveFailed(f"no feasible start: phase 1's elastic inner problems "
                                   f"failed too ({self.failed} of {self.solves}; first: "
                                   f"{self.first_failure})")
        if not total <= SLACK_TOL:
            worst = int(np.nanargmax(slack)) if slack is not None else 0
            where = ("" if slack is None else
                     f"; agent {worst} the farthest (slack {slack[worst]:.4g})")
            raise NoFeasibleFormation(
                f"no feasible formation: phase 1 (elastic inner problems) reached a smallest "
                f"total slack of {total:.4g} (0: every agent feasible){where}", total)
        return PhaseOne(best_phi if phi is None else phi, theta, total, self.solves,
                        self.steps)

    def along_family(self, family: ShiftFamily, low: float, high: float) -> PhaseOne:
        """Scan, then descent over θ (see :func:`phase_one`)."""
        periodic = not (np.isfinite(low) and np.isfinite(high))
        if periodic:
            low, high = -np.pi, np.pi
        n = self.problem.agents
        ends: list[float] = []   # where the descents so far ended
        for count in PHASE_ONE_SCANS:
            shifts = low + (np.arange(count) + 0.5) * (high - low) / count
            phi = np.stack([family.angles(float(t))[0] for t in shifts])
            found = self.measured(elastic_slacks(self.problem, self.backend,
                                                 np.tile(np.arange(n), count), phi.ravel()))
            slacks = found.slack.reshape(count, n)
            totals = slacks.sum(axis=1)
            if not np.any(np.isfinite(totals)):   # no measure anywhere: the solver's limit
                return self.result(None, None)   # raises
            feasible = np.flatnonzero(totals <= SLACK_TOL)
            if len(feasible):   # a feasible shift on the scan
                k = int(feasible[np.argmin(totals[feasible])])
                theta, self.best = float(shifts[k]), (float(totals[k]), phi[k], slacks[k])
                return self.result(phi[k], theta)
            spacing = (high - low) / count
            for k in _basins(totals, periodic):   # from the least, while the descent stalls above 0
                if any(abs(shifts[k] - end) < spacing / 2 for end in ends):
                    continue   # a descent already ended here: the same minimum
                theta = self._descend_shift(family, float(shifts[k]))
                ends.append(theta)
                if self.best[0] <= SLACK_TOL:
                    return self.result(family.angles(theta)[0], theta)
                if totals[k] > 2 * totals.min():
                    break
        return self.result(None, None)   # raises

    def _descend_shift(self, family: ShiftFamily, theta: float) -> float:
        def at(theta: float) -> tuple[float, float]:
            phi, along, _ = family.angles(theta)
            found = self.slacks(phi)
            slope = float(np.sum(parameter_gradient(self.problem, phi, found.end_gradient)
                                 * along))
            return float(np.sum(found.slack)), slope

        value, slope = at(theta)
        shrink, budget = 1.0, self.steps + PHASE_ONE_STEPS
        while SLACK_TOL < value < np.inf and self.steps < budget and slope != 0:
            step = shrink * float(np.clip(-POLYAK_OVERSHOOT * value / slope,
                                          -np.pi / 2, np.pi / 2))
            self.steps += 1
            t_value, t_slope = at(theta + step)
            if t_value < value:
                stalled = t_value > (1 - STALL_RTOL) * value
                theta, value, slope = theta + step, t_value, t_slope
                shrink = min(1.0, 2 * shrink)
                if stalled:   # a local minimum of S above 0: another start
                    break
            else:
                shrink /= 2
        return theta

    def descend(self, phi: np.ndarray) -> np.ndarray:
        """Polyak steps along the coupling's free directions (see :func:`phase_one`)."""
        coupling, curve = self.problem.coupling, self.problem.curve
        found = self.slacks(phi)
        value = float(np.sum(found.slack))
        shrink, budget = 1.0, self.steps + PHASE_ONE_STEPS
        while SLACK_TOL < value < np.inf and self.steps < budget:
            free = coupling.free_directions(phi, curve)
            if not free.shape[1]:
                break
            g = free @ (free.T @ parameter_gradient(self.problem, phi, found.end_gradient))
            size = float(g @ g)
            if size == 0:
                break
            step = -POLYAK_OVERSHOOT * value / size * g
            step *= shrink * min(1.0, (np.pi / 2) / max(np.max(np.abs(step)), 1e-300))
            self.steps += 1
            trial = coupling.retract(phi + step, curve)
            if np.max(np.abs(coupling.residual(trial, curve))) > PROJECTION_TOL:
                shrink /= 2
                continue
            t_found = self.slacks(trial)
            t_value = float(np.sum(t_found.slack))
            if t_value < value:
                stalled = t_value > (1 - STALL_RTOL) * value
                phi, found, value = trial, t_found, t_value
                shrink = min(1.0, 2 * shrink)
                if stalled:   # a local minimum of S above 0: another start
                    break
            else:
                shrink /= 2
                if shrink < 1e-12:
                    break
        # the least S seen where this one is above the tolerance; where no S was finite (every
        # elastic solve failed), φ: :meth:`result` then says so
        return self.best[1] if value > SLACK_TOL and self.best[1] is not None else phi

    def turned(self, phi: np.ndarray) -> list[np.ndarray]:
        """``phi`` and, on an ellipsoid with rotational symmetry, its points turned by
        :data:`PHASE_ONE_TURNS` rotations about its axes (seeded, about its centre) that
        keep c = 0, ordered by their total slack (one superstep); else ``phi`` alone."""
        surface = self.problem.curve
        if not isinstance(surface, EllipsoidSurface) or not len(surface.symmetry_axes):
            return [phi]
        from scipy.spatial.transform import Rotation
        axes = surface.symmetry_axes
        rng = np.random.default_rng(0)
        vectors = rng.normal(size=(PHASE_ONE_TURNS, len(axes)))
        vectors *= (rng.uniform(0, np.pi, PHASE_ONE_TURNS)
                    / np.linalg.norm(vectors, axis=1))[:, None]
        points = surface.points(np.reshape(phi, (-1, 2))) - surface.center
        coupling = self.problem.coupling
        starts = [surface.locate(surface.center + Rotation.from_rotvec(v @ axes).apply(points)
                                 ).ravel() for v in vectors]
        starts = [phi, *(x for x in starts
                         if np.max(np.abs(coupling.residual(x, surface))) <= PROJECTION_TOL)]
        n = self.problem.agents
        found = self.measured(elastic_slacks(self.problem, self.backend,
                                             np.tile(np.arange(n), len(starts)),
                                             np.concatenate(starts)))
        totals = found.slack.reshape(len(starts), n).sum(axis=1)
        return [starts[k] for k in np.argsort(totals)]

    def permutable(self, phi: np.ndarray) -> bool:
        """Whether the agents may trade the points of ``phi`` (a permutation solves c = 0)."""
        rows = np.reshape(phi, (self.problem.agents, -1))
        swapped = np.roll(rows, 1, axis=0).ravel()
        coupling, curve = self.problem.coupling, self.problem.curve
        return bool(np.max(np.abs(coupling.residual(swapped, curve))) <= PROJECTION_TOL)

    def assign(self, phi: np.ndarray, final: bool = False) -> PhaseOne:
        """The assignment of the agents to the points of ``phi`` (onto slots: to every slot)
        minimising S, then the cheapest with every pair feasible (see :func:`phase_one`)."""
        from scipy.optimize import linear_sum_assignment
        problem, n = self.problem, self.problem.agents
        places = (np.arange(problem.curve.count, dtype=float)[:, None]
                  if isinstance(problem.curve, Slots) else np.reshape(phi, (n, -1)))
        m = len(places)
        agents = np.repeat(np.arange(n), m)
        found = self.measured(elastic_slacks(problem, self.backend, agents,
                                             np.tile(places, (n, 1))))
        table = found.slack.reshape(n, m)
        rows, cols = linear_sum_assignment(np.where(np.isfinite(table), table, 1e300))
        total = float(np.sum(table[rows, cols]))
        chosen = places[cols].ravel()
        if total < self.best[0]:
            self.best = (total, chosen, table[rows, cols])
        if self.progress is not None:
            self.progress(f"phase 1: assignment, total slack {total:.6e}")
        if total > SLACK_TOL:
            if final:
                return self.result(None, None)   # raises
            return PhaseOne(chosen, None, total, self.solves, self.steps)
        feasible = np.flatnonzero(table.ravel() <= SLACK_TOL)
        costs = np.full(n * m, np.inf)
        found_costs = inner_costs(problem, self.backend, agents[feasible],
                                  np.tile(places, (n, 1))[feasible])
        self.solves += found_costs.solved
        costs[feasible] = found_costs.costs
        rows, cols = linear_sum_assignment(np.where(np.isfinite(costs), costs,
                                                    1e300).reshape(n, m))
        if not np.all(np.isfinite(costs.reshape(n, m)[rows, cols])):
            cols = linear_sum_assignment(np.where(np.isfinite(table), table, 1e300))[1]
        chosen = places[cols].ravel()
        self.best = (0.0, chosen, table[rows, cols])
        return PhaseOne(chosen, None, 0.0, self.solves, self.steps)
