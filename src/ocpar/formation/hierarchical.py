"""The hierarchical scheme (paper §IV): outer optimisation over φ, one superstep of n inner
DMOC solves per outer evaluation.

Outer problem: min_φ Σ_i Ĵ_i(φ_i) s.t. c(φ) = 0 (the problem's coupling,
:mod:`ocpar.formation.couplings.coupling`; by default the scaled g = dG/dφ of the paper's
potential). The outer gradient comes from the inner sensitivities (envelope theorem):
dĴ_i/dφ_i = (dJ*_i/dq_N) · dq_N/dφ_i, dq_N/dφ_i = z′(φ_i) in the position entries, for any
curve z. Each Ĵ_i depends on φ_i alone, so the Hessian of J is diagonal,
h_i = z′ᵀ H_pos z′ + ∇_pos J*_i · z″ (H_pos = d²J*_i/dq_N² in the position entries, from the
inner KKT system). Three outer solvers:

* :func:`solve_outer_newton` (``newton``, the default): projected Newton on the manifold
  c(φ) = 0 with that diagonal Hessian, any curve and coupling; a handful of supersteps at
  any n where c = 0 leaves one free shift or none;
* :func:`solve_outer` (``sqp``, the paper's): SLSQP on J/J_0 in all n angles, any curve;
* :func:`solve_outer_offset` (``offset``, circles only): from equidistant angles, c(φ) = 0
  keeps them equidistant in the same order, so the feasible set is the one-parameter family
  φ_i = φ_i⁰ + θ; minimise J over the common offset θ (dJ/dθ = Σ_i dĴ_i/dφ_i). Same optimum,
  and the coordinator's work no longer grows like n³ (SLSQP's dense QP).

Every solver starts where each agent's inner problem is feasible: where the given start is
not, phase 1 (:func:`~ocpar.formation.feasibility.phase_one`, the agents' elastic inner
problems) finds a feasible formation first, or the problem is refused
(:class:`~ocpar.formation.feasibility.NoFeasibleFormation`); a later step whose inner solves
fail is rejected (``newton``), counts J = +∞ (``sqp``), or hands ``offset`` over to the shift
Newton search.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ocpar.bsp import Backend, ResidentSet
from ocpar.bsp.columns import Columns
from ocpar.bsp.partition import unit_size
from ocpar.formation.couplings.coupling import (
    PROJECTION_TOL,
    RANK_RTOL,
    PotentialCoupling,
    ShiftFamily,
)
from ocpar.formation.couplings.potential import equidistance_error
from ocpar.formation.feasibility import (
    InnerSolveFailed,
    NoFeasibleFormation,
    PhaseOne,
    feasible_window,
    parameter_gradient,
    phase_one,
)
from ocpar.formation.outer_step import (
    ShiftValues,
    combine,
    shift_tasks,
    solve_formation_agents,
    unit_terms,
)
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import EllipsoidSurface, Surface
from ocpar.ocp.endpoint_agents import agent_tasks

#: Second iterate of the offset search (rad): 1/60 of a slot for the paper's 60 agents.
OFFSET_FIRST_STEP = 1.7e-3

#: Longest step of the common offset θ in :func:`solve_outer_newton` (rad): beyond, a small
#: positive d²J/dθ² (near an inflection of J(θ)) is no model of J.
MAX_OFFSET_STEP = np.pi / 2

#: J values this close (relative) count as equal: the offset search starting at the optimum
#: (e.g. after the optimal ordering) ends where rounding decides.
ROUNDING_RTOL = 1e-12


class OuterObjective:
    """Σ_i Ĵ_i(φ_i) and its gradient, one superstep per new φ (cached for the last φ).

    The agents are resident on the backend's workers (:mod:`ocpar.ocp.endpoint_agents`): a
    superstep sends each agent's boundary data (on its first superstep; later only the
    position part of its end configuration, z(φ_i)) and gathers its
    :class:`~ocpar.ocp.endpoint_agents.AgentOutcome` (J*, dJ*/dq_N, the end Hessian's position
    block), as columns (:meth:`outcomes`); the inner solutions (paths, controls) stay on the
    workers, each agent's the fallback start of its next solve, until :meth:`solutions`
    gathers them (once per φ). :meth:`close` frees the workers' memory of them.
    """

    def __init__(
        self,
        problem: FormationProblem,
        backend: Backend,
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.problem, self.backend, self.progress = problem, backend, progress
        self.inner_solves = 0
        self.failed_solves = 0
        self.retries = 0
        #: Phase 1's outcome where the start was infeasible (None: it was feasible).
        self.phase_one: PhaseOne | None = None
        self.last_outcomes: Columns | None = None
        self._agents = backend.resident(solve_formation_agents, problem.agents)
        self._phi: np.ndarray | None = None   # the last superstep's angles, or
        self._shift: tuple[ShiftFamily, float] | None = None   # its family and shift
        self._family: ShiftFamily | None = None   # the family the agents hold
        self._family_words: tuple[ShiftFamily, str] | None = None   # its feasibility, said
        self._gathered: Columns | None = None  # the solutions at last_phi, once gathered

    @property
    def last_phi(self) -> np.ndarray | None:
        """The angles of the last superstep (None before the first); after a
        :meth:`shifted` superstep, its family's angles at its shift (computed here once)."""
        if self._phi is None and self._shift is not None:
            family, theta = self._shift
            self._phi = family.angles(theta)[0]
        return self._phi

    def outcomes(self, phi: np.ndarray) -> Columns:
        """The agents' outcomes at angles φ (Columns of
        :class:`~ocpar.ocp.endpoint_agents.AgentOutcome`): one superstep, unless φ is the last
        one asked for. Raises :class:`InnerSolveFailed` if a solve failed."""
        phi = np.asarray(phi, float)
        if self.last_outcomes is None or not np.array_equal(phi, self.last_phi):
            problem, d = self.problem, self.problem.curve.dim
            if self._agents.version == 0:
                tasks = agent_tasks(problem.shape, d, params=problem.boundary_params_rows(
                    np.arange(problem.agents), phi))
            else:  # the agents keep the rest of their boundary data
                tasks = agent_tasks(problem.shape, d, end=problem.final_positions(phi))
            outcomes = self._agents.step(tasks)
            self.inner_solves += len(outcomes)
            self.retries += int(np.sum(np.asarray(outcomes.column("attempts")) - 1))
            failed = np.flatnonzero(~np.asarray(outcomes.column("success"), dtype=bool))
            self.failed_solves += len(failed)
            self._phi, self._shift, self.last_outcomes = phi.copy(), None, outcomes
            self._gathered, self._family = None, None   # (the agents' new states: no base)
            self._report(phi, f"{float(np.sum(outcomes.column('cost'))):.12e}")
            if len(failed):
                raise InnerSolveFailed(
                    f"{len(failed)} inner solve(s) failed, first agent {failed[0]}: "
                    f"{outcomes.column('status')[failed[0]]}"
                )
        return self.last_outcomes  # type: ignore[return-value]

    def shifted(self, family: ShiftFamily, theta: float, duration: float | None = None
                ) -> ShiftValues:
        """J, dJ/dθ, Σ|g_i φ_i′| and d²J/dθ² at the shift θ (rad) of ``family``, and where
        the agents' shapes take T as a parameter (``free_duration``) at T = ``duration``
        also dJ/dT, d²J/dT² and d²J/dθ dT: one superstep whose arithmetic the workers do
        (:mod:`ocpar.formation.outer_step`: θ (and T) out, a few sums per reduction unit
        back). Raises :class:`InnerSolveFailed` if a solve failed."""
        first = self._agents.version == 0
        tasks = shift_tasks(self.problem, family, theta, first, family is not self._family,
                            duration)
        rows = self._agents.step(tasks, reduce=unit_terms)
        self._family = family
        values = combine(rows, unit_size(self.problem.agents))
        self.inner_solves += self.problem.agents
        self.retries += values.retries
        self.failed_solves += values.failed
        self._phi, self._shift, self.last_outcomes, self._gathered = \
            None, (family, theta), None, None
        if self.progress is not None:
            self._report(None, f"{values.value:.12e}" if duration is None else
                         f"{values.value:.12e}  T {duration:.12g}  dJ/dT {values.time_slope:.6e}")
        if values.failed:
            raise InnerSolveFailed(f"{values.failed} inner solve(s) failed, first agent "
                                   f"{values.first_failed}: {values.first_status}")
        return values

    def solutions(self, phi: np.ndarray) -> Columns:
        """The inner solutions at angles φ (Columns of
        :class:`~ocpar.ocp.endpoint_agents.AgentState`, a :class:`~ocpar.ocp.DmocSolution`
        with its boundary data: costs (n,), paths (n, N+1, nq), controls (n, N, nu), ...):
        :meth:`reach`, then one superstep that gathers the solutions from the workers (once
        per φ; the separation rounds and a failed run's answer need them here; a finished
        run checks and writes them where they are, :mod:`ocpar.formation.finish`)."""
        self.reach(phi)
        return self.last_solutions  # type: ignore[return-value]

    def reach(self, phi: np.ndarray) -> None:
        """Make ``phi`` the last superstep's angles (one superstep, unless they are): the
        agents' solutions on the workers are then those at ``phi``. Raises
        :class:`InnerSolveFailed` if a solve failed."""
        if self.last_phi is None or not np.array_equal(phi, self.last_phi):
            self.outcomes(phi)

    @property
    def agents(self) -> ResidentSet:
        """The resident set of the agents (their solutions on the workers)."""
        return self._agents

    @property
    def last_solutions(self) -> Columns | None:
        """The inner solutions of the last superstep, gathered from the workers on first use
        (None before the first superstep); also after a superstep whose solves failed."""
        if self._phi is None and self._shift is None:
            return None
        if self._gathered is None:
            self._gathered = self._agents.collect()
            if self.progress is not None:
                trace = self.backend.traces[-1]
                self.progress(f"superstep {trace.index:4d}  gathered the {trace.tasks} agents' "
                              f"paths  wall {trace.wall_s * 1e3:7.1f} ms")
        return self._gathered

    def close(self) -> None:
        """Free the workers' memory of the agents' solutions (then no more supersteps)."""
        self._agents.close()

    def value(self, phi: np.ndarray) -> float:
        return float(np.sum(self.outcomes(phi).column("cost")))

    def gradient(self, phi: np.ndarray) -> np.ndarray:
        """dJ/dφ (n k,) from each agent's dJ*/dq_N (entries 2nq..3nq of dJ*/dp): on a curve
        dJ*/dq_N · z′(φ_i), on a surface (∂z/∂φ_i)ᵀ ∇_pos J*_i (agent i's at 2i, 2i+1)."""
        d_end = np.asarray(self.outcomes(phi).column("end_gradient"))
        return parameter_gradient(self.problem, phi, d_end)

    def hessian_diagonal(self, phi: np.ndarray) -> np.ndarray:
        """d²J/dφ_i² (n,): z′(φ_i)ᵀ H_pos z′(φ_i) + ∇_pos J*_i · z″(φ_i), with H_pos the
        position block (d × d, d = curve.dim) of each agent's d²J*/dq_N² and ∇_pos J*_i the
        position entries of dJ*/dq_N. The off-diagonal entries are zero (Ĵ_i depends on φ_i
        alone)."""
        outcomes = self.outcomes(phi)
        d = self.problem.curve.dim
        h_pos = np.asarray(outcomes.column("end_hessian"))
        d_pos = np.asarray(outcomes.column("end_gradient"))[:, :d]
        tangent = self.problem.curve.tangents(phi)
        curvature = self.problem.curve.curvatures(phi)
        return (np.einsum("id,ide,ie->i", tangent, h_pos, tangent)
                + np.sum(d_pos * curvature, axis=1))

    def hessian_blocks(self, phi: np.ndarray) -> np.ndarray:
        """The diagonal blocks d²J/dφ_i² (n, k, k) of J's block-diagonal Hessian: on a curve
        :meth:`hessian_diagonal` (k = 1); on a surface Tᵀ H_pos T + Σ_d ∇_pos,d J*_i ∂²z_d/∂φ_i²
        with T = ∂z/∂φ_i (3 × 2)."""
        if not isinstance(self.problem.curve, Surface):
            return self.hessian_diagonal(phi)[:, None, None]
        outcomes = self.outcomes(phi)
        d = self.problem.curve.dim
        h_pos = np.asarray(outcomes.column("end_hessian"))
        d_pos = np.asarray(outcomes.column("end_gradient"))[:, :d]
        at = np.reshape(phi, (-1, 2))
        along = self.problem.curve.jacobians(at)
        return (np.einsum("ida,ide,ieb->iab", along, h_pos, along)
                + np.einsum("id,idab->iab", d_pos, self.problem.curve.second_derivatives(at)))

    def _report(self, phi: np.ndarray | None, cost: str) -> None:
        """The progress line of the last superstep at angles ``phi`` (None: a family's shift,
        whose feasibility is its start's), the total ``cost`` as text."""
        if self.progress is None:
            return
        trace = self.backend.traces[-1]
        feasibility = self._family_feasibility() if phi is None else self._feasibility(phi)
        self.progress(
            f"superstep {trace.index:4d}  cost {cost}  {feasibility}  "
            f"wall {trace.wall_s * 1e3:7.1f} ms  overhead {trace.overhead_s * 1e3:6.1f} ms"
        )

    def _family_feasibility(self) -> str:
        """The feasibility words of the agents' family (c(φ(θ)) = 0 at every shift: those of
        its angles at the first shift reported, computed once)."""
        family, theta = self._shift  # type: ignore[misc]
        if self._family_words is None or self._family_words[0] is not family:
            self._family_words = (family, self._feasibility(family.angles(theta)[0]))
        return self._family_words[1]

    def _feasibility(self, phi: np.ndarray) -> str:
        """How far ``phi`` is from the coupling's solutions, in the progress line's words."""
        # on a circle the gaps' deviation, O(n log n): |c(φ)| would cost O(n²) per superstep
        # (50 ms at 1000 agents, as much as the superstep itself on 64 workers)
        if self.problem.on_circle:
            feasibility = f"equidistance {equidistance_error(phi):.1e} rad"
        elif isinstance(self.problem.curve, Slots):
            feasibility = f"distinct slots {np.unique(phi).size} of {phi.size}"
        else:
            residual = self.problem.coupling.residual(phi, self.problem.curve)
            feasibility = f"coupling {np.max(np.abs(residual)):.1e}"
        return feasibility


def feasible_point(objective: OuterObjective, phi: np.ndarray) -> np.ndarray:
    """``phi`` (on c(φ) = 0) made the last superstep's angles, or, where an agent's inner
    problem is infeasible there, phase 1's feasible formation
    (:func:`~ocpar.formation.feasibility.phase_one`, which raises
    :class:`NoFeasibleFormation` if it finds none). Costs nothing beyond that superstep
    where ``phi`` is feasible."""
    try:
        objective.reach(phi)
        return phi
    except NoFeasibleFormation:
        raise
    except InnerSolveFailed:
        problem = objective.problem
        family = problem.coupling.family(phi, problem.curve)
        found = phase_one(problem, objective.backend, phi, family, progress=objective.progress)
        objective.inner_solves += found.inner_solves
        objective.phase_one = found
        objective.reach(found.phi)
        return found.phi


def solve_outer(
    objective: OuterObjective, phi0: np.ndarray, tol: float, max_iterations: int
) -> tuple[np.ndarray, int, bool, str]:
    """SLSQP on J(φ)/J(φ_0) s.t. c(φ) = 0, from ``phi0`` or, where an agent's inner problem
    is infeasible there, from phase 1's feasible point (:func:`feasible_point`); an iterate
    whose inner solves fail counts J = +∞ there (SLSQP's line search then backtracks into
    the feasible region). Returns (φ, iterations, success, message)."""
    from scipy.optimize import minimize
    curve, coupling = objective.problem.curve, objective.problem.coupling
    phi0 = feasible_point(objective, phi0)
    scale = 1.0 / max(objective.value(phi0), 1e-300)

    def value(phi: np.ndarray) -> float:
        try:
            return objective.value(phi) * scale
        except InnerSolveFailed:
            return np.inf

    result = minimize(
        value,
        phi0,
        jac=lambda phi: objective.gradient(phi) * scale,
        method="SLSQP",
        constraints=[
            {
                "type": "eq",
                "fun": lambda phi: coupling.residual(phi, curve),
                "jac": lambda phi: coupling.jacobian(phi, curve),
            }
        ],
        options={"ftol": tol, "maxiter": max_iterations},
    )
    return np.asarray(result.x, float), int(result.nit), bool(result.success), str(result.message)


def solve_outer_offset(
    objective: OuterObjective, phi0: np.ndarray, tol: float, max_iterations: int
) -> tuple[np.ndarray, int, bool, str]:
    """Minimise J(φ⁰ + θ) over the common offset θ (rad) by the secant method on
    dJ/dθ = Σ_i dĴ_i/dφ_i = 0, from θ = 0 and θ = :data:`OFFSET_FIRST_STEP` (one superstep per
    iterate: each gives J and dJ/dθ). ``phi0`` must be equidistant. Converged when
    θ changes by less than ``tol``·(1 + |θ|) and J did not increase (beyond rounding:
    :data:`ROUNDING_RTOL`, then φ⁰ is returned). Where φ⁰ is infeasible (an agent's inner
    problem), phase 1 (:func:`feasible_point`) moves it first; where a secant iterate's
    inner solves fail, :func:`_shift_newton` (which stays inside the feasible offsets)
    finishes from φ⁰. Returns (φ, iterations, success, message).
    Only for a problem on a :class:`~ocpar.formation.Circle` (ValueError otherwise)."""
    from scipy.optimize import root_scalar
    objective.problem.require_circle("outer 'offset'")
    error = equidistance_error(phi0)
    if error > 1e-9:
        raise ValueError(f"outer 'offset' needs equidistant starting angles; their gaps are "
                         f"off by up to {error:.1e} rad")
    phi0 = feasible_point(objective, phi0)   # phase 1 where φ0 is infeasible
    start_value = objective.value(phi0)  # the same superstep as dJ/dθ at θ = 0
    try:
        result = root_scalar(lambda theta: float(np.sum(objective.gradient(phi0 + theta))),
                             x0=0.0, x1=OFFSET_FIRST_STEP, method="secant", xtol=tol,
                             rtol=tol, maxiter=max_iterations)
    except InnerSolveFailed:   # a secant iterate left the feasible offsets
        phi, iterations, success, message = _shift_newton(objective, ShiftFamily(phi0), tol,
                                                          max_iterations)
        return phi, iterations, success, (f"{message} (the secant search left the feasible "
                                          f"offsets: finished by the shift Newton search, "
                                          f"which stays inside them)")
    theta = float(result.root)
    value = objective.value(phi0 + theta)
    same = abs(value - start_value) <= ROUNDING_RTOL * abs(start_value)
    if value > start_value and same:  # φ⁰ was the optimum already: rounding decided
        theta = 0.0
    success = bool(result.converged) and (value <= start_value or same)
    message = (result.flag if success or not result.converged
               else "the offset found does not lower J")
    return phi0 + theta, int(result.iterations), success, message


def solve_outer_newton(
    objective: OuterObjective, phi0: np.ndarray, tol: float, max_iterations: int
) -> tuple[np.ndarray, int, bool, str]:
    """Projected Newton on the feasible manifold c(φ) = 0 of the problem's coupling
    (:mod:`ocpar.formation.couplings.coupling`), with the diagonal Hessian
    (:meth:`OuterObjective.hessian_diagonal`). Returns (φ, iterations, success, message); one
    superstep per iterate gives J, its gradient g and Hessian diagonal h.

    * Where the solutions through φ0 form a one-parameter family φ(θ) (a common shift: the
      potential on a circle, equal arc length on any curve), Newton's method on J(φ(θ)) in
      θ alone (:func:`_shift_newton`): a handful of supersteps at any n.
    * Where they are isolated (the potential off a circle: dc/dφ, the scaled Hessian of the
      potential, is nonsingular at its minima, if nearly singular for many agents: see
      :func:`~ocpar.formation.couplings.potential.relax`), the projection of φ0 is the answer: one
      evaluation (0 iterations), converged if it reached max |c_k| ≤ :data:`PROJECTION_TOL`.
    * On a surface with rotational symmetry (a sphere, an ellipsoid of revolution) the
      potential coupling's solutions are isolated up to its rotations: Newton's method over them,
      applied rigidly to the projection's points (:func:`rotation_newton`).
    * Otherwise (a user's coupling with r free directions), Newton steps in the tangent
      space of c = 0 with the Lagrangian's Hessian, each projected back onto c = 0
      (:func:`tangent_newton`): dense, its superstep count grows with r, not with n.
    """
    problem = objective.problem
    family = problem.coupling.family(phi0, problem.curve)
    if family is not None:
        return _shift_newton(objective, family, tol, max_iterations)
    phi = problem.coupling.project(phi0, problem.curve)
    phi = feasible_point(objective, phi)
    residual = float(np.max(np.abs(problem.coupling.residual(phi, problem.curve))))
    if residual > PROJECTION_TOL:
        return phi, 0, False, (f"the projection did not reach c(phi) = 0 (max |c| "
                               f"{residual:.1e})")
    if isinstance(problem.coupling, PotentialCoupling) and isinstance(
            problem.curve, EllipsoidSurface) and len(problem.curve.symmetry_axes):
        return rotation_newton(objective, phi, tol, max_iterations)
    if problem.coupling.free_directions(phi, problem.curve).shape[1]:
        return tangent_newton(objective, phi, tol, max_iterations)
    return phi, 0, True, "projected onto c(phi) = 0"


def _shift_newton(objective: OuterObjective, family: ShiftFamily, tol: float,
                  max_iterations: int) -> tuple[np.ndarray, int, bool, str]:
    """Newton's method on J(φ(θ)) over the family's shift θ (rad):
    dJ/dθ = Σ g_i dφ_i/dθ, d²J/dθ² = Σ h_i (dφ_i/dθ)² + g_i d²φ_i/dθ² (on a circle
    dφ_i/dθ = 1). The step θ ← θ − (dJ/dθ)/(d²J/dθ²) is safeguarded: no step longer than
    :data:`MAX_OFFSET_STEP`; where d²J/dθ² ≤ 0 a step of half a slot (π/n) downhill (a
    stationary θ there is a maximum: not converged); a step that raises J beyond rounding
    (:data:`ROUNDING_RTOL`) is rejected and halved; once a minimum is bracketed
    (dJ/dθ < 0 left of dJ/dθ > 0), a step leaving the bracket is replaced by the secant step
    inside it (bisection after a rejected step). Converged when |dJ/dθ| ≤ ``tol``
    Σ|g_i dφ_i/dθ| with d²J/dθ² > 0, or an accepted step was at most ``tol``·(1 + |θ|).

    Feasibility (:mod:`ocpar.formation.feasibility`): where the agents' reach sets are exact,
    θ starts at the feasible start of :func:`~ocpar.formation.feasibility.feasible_window`
    and stays inside its interval (a step beyond an end goes half way to it). Any model: a
    step whose inner solves fail is rejected (halved) and bounds the interval; if the start
    fails, phase 1 (:func:`~ocpar.formation.feasibility.phase_one`) finds a feasible one on
    the family (or refuses the problem: :class:`NoFeasibleFormation`)."""

    def evaluate(theta: float) -> tuple[float, float, float, float]:
        at = objective.shifted(family, theta)
        return at.value, at.slope, at.scale, at.curvature

    window = feasible_window(objective.problem, family)
    low, high, theta = (-np.inf, np.inf, 0.0) if window is None else \
        (window.low, window.high, window.start)
    n = objective.problem.agents
    try:
        value, slope, scale, curvature = evaluate(theta)
    except InnerSolveFailed:   # an infeasible start: phase 1 along the family
        found = phase_one(objective.problem, objective.backend, family.angles(theta)[0],
                          family, low, high, objective.progress)
        objective.inner_solves += found.inner_solves
        objective.phase_one = found
        theta = found.theta
        value, slope, scale, curvature = evaluate(theta)
    # the latest (θ, dJ/dθ) with dJ/dθ < 0 and with dJ/dθ > 0
    below = (theta, slope) if slope < 0 else None
    above = (theta, slope) if slope > 0 else None
    shrink = 1.0  # halved after each rejected step
    for iteration in range(max_iterations):
        if abs(slope) <= tol * scale and curvature > 0:
            return family.angles(theta)[0], iteration, True, "|sum of dJ/dphi_i| below tolerance"
        step = shrink * (np.clip(-slope / curvature, -MAX_OFFSET_STEP, MAX_OFFSET_STEP)
                         if curvature > 0 else -(np.sign(slope) or 1.0) * np.pi / n)
        if below is not None and above is not None and below[0] < above[0] \
                and not below[0] < theta + step < above[0]:  # a minimum is bracketed
            (a, g_a), (b, g_b) = below, above
            step = (a - g_a * (b - a) / (g_b - g_a) if shrink == 1 else (a + b) / 2) - theta
        if not low < theta + step < high:   # half way to the feasible interval's end
            step = ((high if step > 0 else low) - theta) / 2
        trial = theta + step
        try:
            t_value, t_slope, t_scale, t_curvature = evaluate(trial)
        except InnerSolveFailed:   # infeasible (or unsolved) there: a rejected step
            low, high = (low, trial) if trial > theta else (trial, high)
            shrink /= 2
            continue
        if t_slope < 0:
            below = (trial, t_slope)
        elif t_slope > 0:
            above = (trial, t_slope)
        if t_value <= value + ROUNDING_RTOL * abs(value):
            theta, value, slope, scale, curvature = trial, t_value, t_slope, t_scale, t_curvature
            shrink = 1.0
            if abs(step) <= tol * (1 + abs(theta)):
                return family.angles(theta)[0], iteration + 1, True, _step_stop(
                    theta, slope, tol * scale, low, high)
        else:
            shrink /= 2
    return family.angles(theta)[0], max_iterations, False, "iteration limit reached"


def _step_stop(theta: float, slope: float, slope_tol: float, low: float, high: float) -> str:
    """Why a shift search whose last accepted step was below tolerance stopped: at a
    stationary θ; or, dJ/dθ not small, at the bound of the shifts where every inner problem
    has a solution that it points past; or at a jump of J (the steps downhill raise J: an
    agent's inner optimum changes branch there, e.g. the side it passes an obstacle on).
    Either of the last two is a local minimum of J over the feasible shifts, not a
    stationary point, and the message says so."""
    if abs(slope) <= slope_tol:
        return "step below tolerance"
    bound = high if slope < 0 else low
    where = (f"the edge of the feasible shifts (beyond {bound:.6g} rad an agent's inner "
             f"problem has no solution)" if np.isfinite(bound) else
             "a jump of J (a step downhill raises it: an agent's inner optimum changes "
             "branch there, e.g. its side of an obstacle)")
    return (f"step below tolerance at {where}: a local minimum at theta = {theta:.6g} rad "
            f"with dJ/dtheta = {slope:.3g}, not a stationary point")


def tangent_newton(objective: OuterObjective, phi: np.ndarray, tol: float,
                    max_iterations: int) -> tuple[np.ndarray, int, bool, str]:
    """Newton's method on the manifold c(φ) = 0 from a point ``phi`` on it: with Z (n, r) an
    orthonormal basis of its tangent space, λ the least-squares multipliers (dc/dφ)ᵀλ = g and
    W = blockdiag(:meth:`OuterObjective.hessian_blocks`) − d²(λᵀc)/dφ² the Lagrangian's
    Hessian, the step −Z (ZᵀWZ)⁻¹ Zᵀg (the reduced Hessian's eigenvalues taken in absolute
    value, its step no longer than :data:`MAX_OFFSET_STEP`), retracted onto c = 0
    (:meth:`~ocpar.formation.couplings.coupling.Coupling.retract`); a step that raises J beyond
    rounding, whose inner solves fail, or from which the retraction does not reach
    max |c_k| ≤ :data:`PROJECTION_TOL`, is halved. Converged when |Zᵀg|_∞ ≤ ``tol`` Σ|g_i|
    with ZᵀWZ positive definite, or a step was at most ``tol``·(1 + |φ|_∞)."""
    from scipy.linalg import block_diag
    coupling, curve = objective.problem.coupling, objective.problem.curve

    def model(phi: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """J at ``phi`` (one superstep), the Newton step there and whether it is converged."""
        g = objective.gradient(phi)
        free = coupling.free_directions(phi, curve)
        weights = np.linalg.lstsq(coupling.jacobian(phi, curve).T, g, rcond=None)[0]
        hessian = block_diag(*objective.hessian_blocks(phi)) \
            - coupling.weighted_hessian(phi, weights, curve)
        eigenvalues, vectors = np.linalg.eigh(free.T @ hessian @ free)
        reduced = free.T @ g
        floor = 1e-12 * max(np.max(np.abs(eigenvalues)), 1e-300)
        step = -free @ (vectors @ ((vectors.T @ reduced) / np.maximum(np.abs(eigenvalues),
                                                                      floor)))
        step *= min(1.0, MAX_OFFSET_STEP / max(np.max(np.abs(step)), 1e-300))
        converged = np.max(np.abs(reduced)) <= tol * np.sum(np.abs(g)) and eigenvalues[0] > 0
        return objective.value(phi), step, converged

    value, step, converged = model(phi)
    shrink = 1.0
    for iteration in range(max_iterations):
        if converged:
            return phi, iteration, True, "reduced gradient below tolerance"
        trial = coupling.retract(phi + shrink * step, curve)
        if np.max(np.abs(coupling.residual(trial, curve))) > PROJECTION_TOL:
            shrink /= 2   # too long a step to retract onto c = 0 from
            continue
        try:
            t_value = objective.value(trial)
        except InnerSolveFailed:   # infeasible (or unsolved) there: a rejected step
            shrink /= 2
            continue
        if t_value <= value + ROUNDING_RTOL * abs(value):
            if np.max(np.abs(shrink * step)) <= tol * (1 + np.max(np.abs(trial))):
                return trial, iteration + 1, True, "step below tolerance"
            phi, shrink = trial, 1.0
            value, step, converged = model(phi)
        else:
            shrink /= 2
    return phi, max_iterations, False, "iteration limit reached"


def rotation_newton(objective: OuterObjective, phi: np.ndarray, tol: float,
                    max_iterations: int) -> tuple[np.ndarray, int, bool, str]:
    """Newton's method on J over the rotations that map the problem's ellipsoid onto itself
    (:attr:`~ocpar.formation.targets.surface.EllipsoidSurface.symmetry_axes` A (k, 3) about its
    centre c), applied rigidly in space to the points of ``phi`` (2n,): x_i(ω) =
    c + exp(Σ_a ω_a [A_a]×) r_i, r_i = x_i − c, each iterate re-charted
    (:meth:`~ocpar.formation.targets.surface.Surface.locate`) for its superstep, so that the chart's
    poles play no part. With v_i = ∇_pos J*_i and H_i its position block: the gradient
    g_a = A_a · Σ_i r_i × v_i and the Hessian H_ab = Σ_i (A_a × r_i)ᵀ H_i (A_b × r_i)
    + A_aᵀ M A_b, M = Σ_i ½ (r_i v_iᵀ + v_i r_iᵀ) − (r_i · v_i) I. The step −H⁺g takes the
    eigenvalues in absolute value and drops those below :data:`RANK_RTOL` times the largest (a
    rotation that changes no cost, e.g. about a line through c that holds every start), is
    at most :data:`MAX_OFFSET_STEP` rad, and is halved while it raises J beyond rounding or
    its inner solves fail (the search stays where every agent is feasible).
    Converged when |g|_∞ ≤ ``tol`` Σ_i |r_i × v_i| with H positive semidefinite (to
    :data:`RANK_RTOL`), or a step of at most ``tol`` rad was taken or was the last to fail
    to lower J. Returns (φ (2n,) of the points
    reached, iterations, success, message)."""
    from scipy.spatial.transform import Rotation
    surface = objective.problem.curve
    if not isinstance(surface, EllipsoidSurface) or not len(surface.symmetry_axes):
        raise ValueError("rotation_newton needs an ellipsoid with rotational symmetry")
    axes, centre = surface.symmetry_axes, surface.center

    def model(phi: np.ndarray) -> tuple[float, np.ndarray, bool]:
        """J at ``phi`` (one superstep), the Newton step in ω (k,) and whether converged."""
        outcomes = objective.outcomes(phi)
        v = np.asarray(outcomes.column("end_gradient"))[:, :3]
        h = np.asarray(outcomes.column("end_hessian"))
        r = surface.points(np.reshape(phi, (-1, 2))) - centre
        torque = np.cross(r, v)
        gradient = axes @ np.sum(torque, axis=0)
        moved = np.cross(axes[None], r[:, None])            # (n, k, 3): A_a × r_i
        m = (0.5 * (np.einsum("id,ie->de", r, v) + np.einsum("id,ie->de", v, r))
             - np.sum(r * v) * np.eye(3))
        hessian = np.einsum("iad,ide,ibe->ab", moved, h, moved) + axes @ m @ axes.T
        eigenvalues, vectors = np.linalg.eigh(hessian)
        floor = RANK_RTOL * max(np.max(np.abs(eigenvalues)), 1e-300)
        kept = np.abs(eigenvalues) > floor
        step = -vectors[:, kept] @ ((vectors[:, kept].T @ gradient) / np.abs(eigenvalues[kept]))
        step *= min(1.0, MAX_OFFSET_STEP / max(np.linalg.norm(step), 1e-300))
        converged = (np.max(np.abs(gradient)) <= tol * np.sum(np.linalg.norm(torque, axis=1))
                     and eigenvalues[0] >= -floor)
        return float(np.sum(outcomes.column("cost"))), step, converged

    def turned(phi: np.ndarray, omega: np.ndarray) -> np.ndarray:
        points = surface.points(np.reshape(phi, (-1, 2))) - centre
        return surface.locate(centre + Rotation.from_rotvec(omega @ axes).apply(points)).ravel()

    phi = np.asarray(phi, float).ravel()
    value, step, converged = model(phi)
    shrink = 1.0
    for iteration in range(max_iterations):
        if converged:
            return phi, iteration, True, "rotation gradient below tolerance"
        trial = turned(phi, shrink * step)
        try:
            t_value = objective.value(trial)
        except InnerSolveFailed:   # infeasible (or unsolved) there: a rejected step
            t_value = np.inf
        if t_value <= value + ROUNDING_RTOL * abs(value):
            if shrink * np.linalg.norm(step) <= tol:
                return trial, iteration + 1, True, "step below tolerance"
            phi, shrink = trial, 1.0
            value, step, converged = model(phi)
        else:
            shrink /= 2
            if shrink * np.linalg.norm(step) <= tol:
                return phi, iteration + 1, True, "no step longer than the tolerance lowers J"
    return phi, max_iterations, False, "iteration limit reached"
