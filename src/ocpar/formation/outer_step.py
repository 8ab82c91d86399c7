"""The outer step's arithmetic on the workers: a shift of the formation's family per
superstep, a few sums per worker back (SPMD, as the PUB implementation and mpi-sppy do it).

Where the coupling's solutions through the start form a one-parameter family φ(θ) (a
circle's common rotation, equal arc length's shift:
:class:`~ocpar.formation.couplings.coupling.ShiftFamily`), the outer problem is Newton's
method in θ alone (:func:`~ocpar.formation.hierarchical.solve_outer_newton`).
Each of its supersteps needs J = Σ_i Ĵ_i, dJ/dθ = Σ_i g_i φ_i′, Σ_i |g_i φ_i′| (its scale)
and d²J/dθ² = Σ_i h_i φ_i′² + g_i φ_i″, with g_i = dĴ_i/dφ_i and h_i = d²Ĵ_i/dφ_i²
(:class:`~ocpar.formation.hierarchical.OuterObjective`). Here a superstep carries only θ and
the family's map (and, the first time an agent meets the family, its base angle u_i; the
first time it is solved, its boundary data): each worker computes its agents' φ_i(θ), their
targets z(φ_i), solves them (:func:`~ocpar.ocp.endpoint_agents.solve_agents`, whose
solutions stay resident), forms the per-agent terms and sums them over the engine's
reduction units (:mod:`ocpar.bsp.resident`); the coordinator adds the units' sums in unit
order. So per superstep a worker sends back four sums and a failure count per unit
(~1,000 units at any n above 2,000 agents) instead of an outcome per agent, the coordinator
computes no O(n) term, and the sums are the same bits on any number of workers (below
2,048 agents every agent is its own unit: the sums are those of the coordinator-side
arithmetic, bit for bit).

A free common final time (:mod:`ocpar.formation.final_time`) makes T an outer variable
beside θ: the superstep carries T too (one number; the agents' shapes take it as their
last parameter, set on the workers), and each agent adds dJ_i*/dT, d²J_i*/dT² and the
cross term d²Ĵ_i/dθ dT = (∂²J_i*/∂q_N ∂T · z′(φ_i)) φ_i′ to its terms
(:func:`~ocpar.ocp.endpoint_agents.duration_terms`), summed over the same units: the
superstep then gives the whole gradient and Hessian of J in (θ, T).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import LISTED, SHARED, STACKED, Columns
from ocpar.bsp.partition import unit_blocks
from ocpar.formation.couplings.coupling import ShiftFamily, shifted
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.curve import CircleEvaluator, CurveEvaluator
from ocpar.ocp.contract import PrepareTask, Shape, prepare_solvers
from ocpar.ocp.endpoint_agents import AgentState, agent_tasks, duration_terms, solve_agents


@dataclass(frozen=True)
class ShiftTask:
    """One agent's solve at the family's shift ``theta`` (rad; with ``chart`` and the
    target curve's :attr:`~ocpar.formation.Curve.evaluator` ``curve``, shared by a
    superstep's agents,
    :class:`~ocpar.formation.couplings.coupling.ShiftFamily`):
    ``base`` its base angle u_i where the family is new to it (None: the one it has),
    ``params`` its DMOC boundary data (4 nq,) on its first solve (None: the ones it has, its
    end position moved to z(φ_i)); ``duration`` the common T of shapes with
    ``free_duration`` (None: T fixed)."""

    shape: Shape
    theta: float
    chart: CurveEvaluator | None
    curve: CurveEvaluator | CircleEvaluator
    base: float | None
    params: np.ndarray | None
    duration: float | None


@dataclass
class ShiftState(AgentState):
    """What stays on an agent's worker: its latest solution and boundary data
    (:class:`~ocpar.ocp.endpoint_agents.AgentState`) and its base angle ``base`` (rad) in
    the family."""

    base: float


@dataclass
class ShiftTerms:
    """One agent's share of the outer step at θ: ``cost`` Ĵ_i, ``slope`` g_i φ_i′,
    ``scale`` |g_i φ_i′|, ``curvature`` h_i φ_i′² + g_i φ_i″; where T is free
    ``time_slope`` dJ_i*/dT, ``time_curvature`` d²J_i*/dT² and ``cross`` d²Ĵ_i/dθ dT (NaN
    where T is fixed); ``success``, the solver's ``status`` and the failure policy's
    ``attempts``."""

    cost: float
    slope: float
    scale: float
    curvature: float
    time_slope: float
    time_curvature: float
    cross: float
    success: bool
    status: str
    attempts: int


@dataclass
class UnitTerms:
    """The sums of a reduction unit's :class:`ShiftTerms` (``cost``, ``slope``, ``scale``,
    ``curvature``, ``time_slope``, ``time_curvature``, ``cross``), its ``failed`` solves,
    the first failed agent's row in the unit (``first_failed``, −1 if none) and status
    (``first_status``), and its ``retries`` (attempts beyond the first)."""

    cost: float
    slope: float
    scale: float
    curvature: float
    time_slope: float
    time_curvature: float
    cross: float
    failed: int
    first_failed: int
    first_status: str
    retries: int


#: The summed fields of :class:`ShiftTerms`, in :class:`UnitTerms`' order.
SUMS = ("cost", "slope", "scale", "curvature", "time_slope", "time_curvature", "cross")


def solve_shifted(tasks: Columns, states: Columns | None) -> tuple[Columns, Columns]:
    """Resident kernel: the agents' solves at the shift of ``tasks`` (Columns of
    :class:`ShiftTask`), each from its previous state (``states``: Columns of
    :class:`ShiftState`; None on the first task), and their :class:`ShiftTerms`; returns
    the terms and the new :class:`ShiftState` s."""
    k = len(tasks)
    theta, chart, curve = (tasks.fields[name][1] for name in ("theta", "chart", "curve"))
    kind, base = tasks.fields["base"]
    base = np.asarray(states.column("base") if kind == SHARED else base, float)
    phi, along, bend = shifted(base + theta, chart)
    d, duration = curve.dim, tasks.fields["duration"][1]
    if states is None:
        agents = agent_tasks(_shapes(tasks), d, params=np.asarray(tasks.column("params")),
                             duration=duration)
    else:
        agents = agent_tasks(_shapes(tasks), d, end=curve.evaluate(phi, 0), duration=duration)
    outcomes, solved = solve_agents(agents, states)
    d_end = np.asarray(outcomes.column("end_gradient"))
    nq = d_end.shape[1]
    tangent = curve.evaluate(phi, 1)
    # as OuterObjective.gradient and .hessian_diagonal compute them, row by row
    g = np.sum(d_end * np.hstack([tangent, np.zeros((k, nq - d))]), axis=1)
    h = (np.einsum("id,ide,ie->i", tangent, np.asarray(outcomes.column("end_hessian")),
                   tangent)
         + np.sum(d_end[:, :d] * curve.evaluate(phi, 2), axis=1))
    slope = g * along
    if duration is None:
        time_slope = time_curvature = cross = np.full(k, np.nan)
    else:
        time_slope, time_curvature, d_end_time = duration_terms(agents, solved)
        cross = np.sum(d_end_time * tangent, axis=1) * along
    terms = Columns(cls=ShiftTerms, length=k, fields={
        "cost": outcomes.fields["cost"], "slope": (STACKED, slope),
        "scale": (STACKED, np.abs(slope)), "curvature": (STACKED, h * along**2 + g * bend),
        "time_slope": (STACKED, time_slope), "time_curvature": (STACKED, time_curvature),
        "cross": (STACKED, cross),
        "success": outcomes.fields["success"], "status": outcomes.fields["status"],
        "attempts": outcomes.fields["attempts"]})
    states = Columns(cls=ShiftState, length=k,
                     fields=solved.fields | {"base": (STACKED, base)})
    return terms, states


def solve_formation_agents(tasks: Columns, states: Columns | None
                           ) -> tuple[Columns, Columns]:
    """Resident kernel of a formation's agents
    (:class:`~ocpar.formation.hierarchical.OuterObjective`): a shift of the family
    (Columns of :class:`ShiftTask`: :func:`solve_shifted`) or given end positions
    (Columns of :class:`~ocpar.ocp.endpoint_agents.AgentTask`:
    :func:`~ocpar.ocp.endpoint_agents.solve_agents`, after which the agents hold no base
    angle)."""
    if tasks.cls is ShiftTask:
        return solve_shifted(tasks, states)
    return solve_agents(tasks, states)


def _shapes(tasks: Columns) -> object:
    """The DMOC shape column of ``tasks``: one shared shape, or the agents' own."""
    kind, data = tasks.fields["shape"]
    return data if kind == SHARED else list(data)


def unit_terms(terms: Columns, bounds: np.ndarray) -> Columns:
    """Reducer (:mod:`ocpar.bsp.resident`): the :class:`UnitTerms` of each unit of
    ``terms`` (Columns of :class:`ShiftTerms`, unit j rows bounds[j]:bounds[j+1])."""
    starts, units = bounds[:-1], len(bounds) - 1
    sums = {name: np.add.reduceat(np.asarray(terms.column(name), float), starts)
            if units else np.zeros(0) for name in SUMS}
    failed = ~np.asarray(terms.column("success"), bool)
    attempts = np.asarray(terms.column("attempts"), np.int64) - 1
    counts = np.add.reduceat(failed.astype(np.int64), starts) if units else np.zeros(0, int)
    first = np.full(units, -1, np.int64)
    statuses = [""] * units
    status = terms.column("status")
    for j in np.flatnonzero(counts):   # failures are rare: a loop over the failed units only
        row = int(starts[j] + np.argmax(failed[starts[j]:bounds[j + 1]]))
        first[j], statuses[j] = row - starts[j], status[row]
    return Columns(cls=UnitTerms, length=units, fields={
        **{name: (STACKED, value) for name, value in sums.items()},
        "failed": (STACKED, counts.astype(np.int64)), "first_failed": (STACKED, first),
        "first_status": (SHARED, "") if not np.any(counts) else (LISTED, statuses),
        "retries": (STACKED, np.add.reduceat(attempts, starts) if units
                    else np.zeros(0, np.int64))})


def shift_tasks(problem: FormationProblem, family: ShiftFamily, theta: float,
                first: bool, new_family: bool, duration: float | None = None) -> Columns:
    """The superstep's :class:`ShiftTask` s for every agent at the shift ``theta``: with the
    base angles where the family is ``new_family`` to the agents, with their boundary data
    on their ``first`` solve (then at φ(θ), computed here once); at the common T
    ``duration`` where the shapes take it as a parameter (None: T fixed)."""
    n = problem.agents
    params = (problem.boundary_params_rows(np.arange(n), family.angles(theta)[0])
              if first else None)
    return Columns(cls=ShiftTask, length=n, fields={
        "shape": ((SHARED, problem.shape) if not isinstance(problem.shape, tuple)
                  else (LISTED, list(problem.shape))),
        "theta": (SHARED, float(theta)), "chart": (SHARED, family.chart),
        "curve": (SHARED, problem.curve.evaluator),
        "base": (STACKED, family.base) if new_family or first else (SHARED, None),
        "params": (STACKED, params) if first else (SHARED, None),
        "duration": (SHARED, None if duration is None else float(duration))})


def prepare_workers(problem: FormationProblem, backend: Backend) -> None:
    """Build, on each worker, the inner solvers its block of resident agents will solve
    (:func:`~ocpar.ocp.contract.prepare_solvers`: the shapes' transcriptions and their
    batched calls for the block's size): one superstep that is no step of the run, so that
    the solve's first superstep solves only."""
    blocks = unit_blocks(problem.agents, backend.workers)
    if not isinstance(problem.shape, tuple):
        counts = [((problem.shape, len(block)),) for block in blocks]
    else:
        counts = [tuple(Counter(problem.shape[block.start:block.stop]).items())
                  for block in blocks]
    backend.superstep(prepare_solvers, [PrepareTask(c) for c in counts], record=False)


@dataclass(frozen=True)
class ShiftValues:
    """J, dJ/dθ, Σ|g_i φ_i′| and d²J/dθ² at a shift (the units' sums added in unit order),
    where T is free dJ/dT, d²J/dT² and d²J/dθ dT (``time_slope``, ``time_curvature``,
    ``cross``; NaN where T is fixed), the failed solves (with the first failed agent and its
    status) and the retries."""

    value: float
    slope: float
    scale: float
    curvature: float
    time_slope: float
    time_curvature: float
    cross: float
    failed: int
    first_failed: int
    first_status: str
    retries: int


def combine(rows: Columns, unit: int) -> ShiftValues:
    """The :class:`ShiftValues` of a reduced superstep's unit rows (Columns of
    :class:`UnitTerms`, in unit order, units of ``unit`` agents)."""
    counts = np.asarray(rows.column("failed"))
    first, status = -1, ""
    if np.any(counts):
        j = int(np.argmax(counts > 0))
        first = j * unit + int(np.asarray(rows.column("first_failed"))[j])
        status = rows.column("first_status")[j]
    return ShiftValues(*(float(np.sum(np.asarray(rows.column(name)))) for name in SUMS),
                       failed=int(np.sum(counts)), first_failed=first, first_status=status,
                       retries=int(np.sum(np.asarray(rows.column("retries")))))
