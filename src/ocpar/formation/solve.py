"""The formation scheme's Python API: :func:`solve_formation`."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.serial import SerialBackend
from ocpar.formation.couplings.coupling import PROJECTION_TOL, PotentialCoupling
from ocpar.formation.couplings.critical_sets import (
    CRITICAL_READINGS,
    CRITICAL_STARTS,
    MAX_CRITICAL_STARTS,
    SATURATION_STARTS,
    IsolatedChoice,
    best_isolated_formation,
)
from ocpar.formation.feasibility import NoFeasibleFormation, feasible_start
from ocpar.formation.final_time import (
    FINAL_TIMES,
    check_final_time,
    solve_free_time,
    solve_per_agent_time,
)
from ocpar.formation.finish import cost_groups, finish, padded_paths, writes_parts
from ocpar.formation.hierarchical import (
    InnerSolveFailed,
    OuterObjective,
    solve_outer,
    solve_outer_newton,
    solve_outer_offset,
)
from ocpar.formation.keep_out.exact import ExactSeparation, separate_exactly
from ocpar.formation.keep_out.obstacles import cleared, closest_obstacle, passing_sides
from ocpar.formation.keep_out.rounds import SEPARATION_RTOL, Separation, separate
from ocpar.formation.keep_out.separation import check_separation_feasible
from ocpar.formation.minimum_time import check_minimum_time, solve_minimum_time
from ocpar.formation.monolithic import solve_monolithic
from ocpar.formation.ordering import ORDERINGS, OrderingResult, optimal_ordering
from ocpar.formation.ordering_bound import GAP_TOL, SEARCH_ROUNDS
from ocpar.formation.outer_step import prepare_workers
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import Fleet, FormationResult
from ocpar.formation.slot_assignment import SlotChoice, assign_slots
from ocpar.formation.targets.slots import SLOT_CANDIDATES, Slots
from ocpar.formation.targets.surface import Surface
from ocpar.formation.verify import (
    Verification,
    checked_positions,
    near_collision_words,
    verify_checked,
    verify_formation,
)
from ocpar.ocp.batch import AUTO_SOLVER, SOLVERS
from ocpar.ocp.dmoc import DmocShape
from ocpar.ocp.solver_options import SOLVER_OPTIONS_HELP, merged, solver_options, used
from ocpar.options import numbers, option

MODES = ("hierarchical", "monolithic")
#: How the hierarchical mode imposes ``min_separation`` (:class:`FormationOptions`).
SEPARATIONS = ("exact", "rounds")
#: The monolithic answer must meet its constraints and bounds to this (the model's units, as
#: evaluated on the returned point) to count as feasible.
MONOLITHIC_VIOLATION_TOL = 1e-6
#: The hierarchical mode's outer solvers by name (see :mod:`ocpar.formation.hierarchical`).
OUTER = {"newton": solve_outer_newton, "sqp": solve_outer, "offset": solve_outer_offset}
OUTER_SOLVERS = tuple(OUTER)


@dataclass(frozen=True)
class FormationOptions:
    """How to solve.

    ``mode``: ``hierarchical`` (an outer solver, inner DMOC solves in supersteps) or
    ``monolithic`` (one IPOPT NLP in the coordinator). ``outer``: the hierarchical mode's
    outer solver (see :mod:`ocpar.formation.hierarchical`), ``newton`` (projected Newton on
    c(φ) = 0 with the diagonal Hessian from the inner sensitivities, any curve: a handful of
    supersteps at any n), ``sqp`` (SLSQP in all angles, the paper's) or ``offset`` (secant
    search over the common offset of equidistant angles, circles only). ``outer_tol`` is
    ``newton``'s relative tolerance on |Σ_i dJ/dφ_i| (against Σ_i |dJ/dφ_i|) or on the
    offset step, SLSQP's ``ftol`` on J/J_0 (keep it above the inner solves' noise), or for
    ``offset`` the relative tolerance on the offset θ; ``monolithic_tol`` is IPOPT's
    ``tol``. ``ordering``: which agent goes to which place on the curve, ``keep`` (the
    initial angles' order, the paper's) or ``optimal``: on a circle
    :func:`ocpar.formation.ordering.optimal_ordering` (run on the backend first; its angles
    start the chosen mode), on any other curve
    :func:`ocpar.formation.couplings.critical_sets.best_isolated_formation` with ``critical`` and
    ``critical_starts`` (its choice is the outer solve). Onto
    :class:`~ocpar.formation.targets.slots.Slots` the outer solve is always the assignment
    (:func:`ocpar.formation.slot_assignment.assign_slots`, ``slot_candidates``). ``offset``
    relies on the circle's symmetry: :func:`solve_formation` refuses it (ValueError) on other
    curves. ``inner_solver``
    (``newton``, ``sqpmethod``, ``ipopt`` or ``auto``: ``DmocShape.chosen_solver``, see
    :mod:`ocpar.ocp.batch`) replaces the problem's ``DmocShape.solver`` for this solve; None
    keeps it. ``min_separation`` D (length unit):
    hierarchical, after the outer solve, separation rounds of keep-out DMOC
    solves (:mod:`ocpar.formation.keep_out.rounds`, at most ``separation_rounds`` supersteps) keep
    every pair ≥ D apart on the continuous paths, or the result's status is
    ``separation_not_met``; then, with ``separation`` ``exact`` (the default), the clusters of
    close agents are solved with their separating planes and the rotation searched
    (:mod:`ocpar.formation.keep_out.exact`: the monolithic optimum; ``rounds``: the rounds'
    answer, separated, not optimal; problems with obstacles keep the rounds' answer);
    monolithic, separating planes in the one NLP (exact,
    :mod:`ocpar.formation.monolithic`); None: no constraint (the paths may cross). A
    problem's obstacles are in every agent's inner problem
    (:mod:`ocpar.formation.keep_out.obstacles`), in both modes; the returned paths are
    checked against them (``obstacles_not_cleared`` if one is inside one). ``final_time``
    (:mod:`ocpar.formation.final_time`): ``fixed`` (the shapes' duration), ``free`` (one
    common T in ``time_bounds`` (T_min, T_max), the cost Σ J_i + ``time_weight`` · T, T
    stationary to ``time_tol``), ``free_per_agent`` (each agent's own T_i there, its cost
    J_i + w T_i) or ``minimum`` (the least T at which a formation is
    reachable, a bracket of relative width ``time_tol``).
    ``solver_options``: the inner solvers' own options by ``SOLVER.NAME``
    (:mod:`ocpar.ocp.solver_options`), set over each shape's own ``solver_options`` for this
    solve (``ipopt.*`` also in the monolithic NLP); checked when the options are made.
    """

    mode: str = option("hierarchical", "hierarchical, or monolithic (one NLP, for reference)",
                       choices=MODES)
    outer: str = option("newton", "hierarchical outer solver: newton (projected Newton with "
                        "the diagonal Hessian from the inner sensitivities: a handful of "
                        "supersteps at any number of agents, any curve), sqp (the paper's "
                        "SLSQP in all angles) or offset (secant search over the common offset "
                        "of equidistant angles, circles only)", choices=OUTER_SOLVERS)
    outer_tol: float = option(1e-12, "newton's relative tolerance on the summed gradient or "
                              "the offset step, SLSQP's ftol on J/J_0, or offset's relative "
                              "tolerance", above=0)
    max_outer_iterations: int = option(200, "outer iterations at most", low=1)
    monolithic_tol: float = option(1e-12, "IPOPT's tol in monolithic mode", above=0)
    ordering: str = option("keep", "which agent goes to which place on the curve: keep (the "
                           "initial guess's order, the paper's) or optimal (on a circle, "
                           "assignment over a table of n^2 inner costs, alternated with the "
                           "common offset; on any other curve, the cheapest of the coupling's "
                           "isolated solution sets and its cheapest assignment)",
                           choices=ORDERINGS)
    critical: str = option("stable", "off a circle, with --ordering optimal: which solutions "
                           "of the coupling to search: stable (local minima of the potential, "
                           "spread-out formations) or any (every critical point, saddles "
                           "included: the paper's g(phi) = 0)", choices=CRITICAL_READINGS)
    critical_starts: int = option(CRITICAL_STARTS, "off a circle, with --ordering optimal: "
                                  "random starts of the search for the coupling's solution "
                                  "sets, besides the initial guess, at least; more until "
                                  "--critical-saturation consecutive starts find no new "
                                  f"set (at most {MAX_CRITICAL_STARTS})", low=1)
    critical_saturation: int = option(SATURATION_STARTS, "off a circle, with --ordering "
                                      "optimal: the search for the coupling's solution sets "
                                      "ends once this many consecutive starts found no new "
                                      "set (0: after --critical-starts exactly)", low=0)
    ordering_gap: float = option(GAP_TOL, "on a circle, with --ordering optimal: the relative "
                                 "gap (best - lower bound) / best at which the search over "
                                 "assignments and rotation stops, proven (where the inner "
                                 "problems are convex in their end position)", above=0)
    ordering_rounds: int = option(SEARCH_ROUNDS, "on a circle, with --ordering optimal: "
                                  "rounds of that search at most (each one superstep of "
                                  "inner solves); stopped there, the run is not_converged "
                                  "with the gap it proved", low=1)
    slot_candidates: int = option(SLOT_CANDIDATES, "onto slots: candidate slots per agent to "
                                  "begin with (its nearest to its start and to its place in "
                                  "the formation), doubled until doubling finds no cheaper "
                                  "assignment; the assignment is exact over them", low=1)
    inner_solver: str | None = option(
        None, "inner DMOC solver: newton (Newton steps on a chunk's KKT systems in one "
        "compiled call; equalities only), sqpmethod (a chunk in one mapped call; both with "
        "IPOPT for the solves that fail their KKT check), ipopt (one IPOPT call per agent) or "
        "auto; default: the problem's DmocShape.solver, auto unless it says otherwise: "
        "newton for inner problems of equalities only, sqpmethod for those with "
        "inequalities (thrust limits and other path constraints, obstacles)",
        choices=(AUTO_SOLVER, *SOLVERS))
    min_separation: float | None = option(
        None, "keep every pair of agents at least this far apart at all times of the "
        "continuous paths (the model's length unit): separation rounds of keep-out DMOC "
        "solves after the outer solve, then (--separation exact) the separating planes and "
        "the formation's rotation optimised in the outer problem (with --mode monolithic: "
        "separating planes in the one NLP); start or final positions closer than this are "
        "refused (default: none, no separation required)", above=0, metavar="D")
    solver_options: dict = option(  # noqa: RUF009 (option() is a dataclass field)
        default_factory=dict, help=SOLVER_OPTIONS_HELP + "; over the problem's "
        "DmocShape.solver_options (ipopt.* also in --mode monolithic)",
        flag="--solver-option", metavar="SOLVER.NAME=VALUE", dotted=True)
    separation_rounds: int = option(30, "separation rounds (supersteps of keep-out solves) "
                                    "at most, with --min-separation", low=1)
    separation: str = option("exact", "with --min-separation in the hierarchical mode: exact "
                             "(after the rounds, the separating planes and the formation's "
                             "rotation are outer variables: the monolithic optimum) or rounds "
                             "(the rounds' answer: separated, not optimal; fewer supersteps)",
                             choices=SEPARATIONS)
    initial_angles: tuple[float, ...] | None = option(
        None, "the start: the final angles (rad), one per agent (on a surface two per agent, "
        "agent i's at 2i, 2i+1), numbers separated by commas; default: the documented "
        "initial guess, moved to the nearest feasible formation where thrust limits are "
        "known exactly; elsewhere an infeasible start goes through phase 1 (elastic inner "
        "problems) first", metavar="PHI,PHI,...")
    initial_rotation: float | None = option(
        None, "the start: the documented initial guess rotated by this angle (rad, added to "
        "every agent's initial angle; curves only; default: not rotated)", metavar="RAD")
    final_time: str = option("fixed", "the horizon T: fixed (the problem's), free (one common "
                             "T in --time-bounds, the cost sum J_i + w T with w = "
                             "--time-weight), free_per_agent (each agent its own T_i in "
                             "--time-bounds, its cost J_i + w T_i) or minimum (the least T at "
                             "which the formation is reachable under the agents' limits, a "
                             "bracket of relative width --time-tol)", choices=FINAL_TIMES)
    time_bounds: tuple[float, ...] | None = option(
        None, "with --final-time free or minimum: T_min,T_max (the model's time unit; "
        "default: none, required by free and free_per_agent; minimum: (0, inf))",
        metavar="T_MIN,T_MAX")
    time_weight: float = option(0.0, "with --final-time free: w, the cost per unit of T "
                                "(cost unit per time unit)", low=0)
    time_tol: float = option(1e-6, "with --final-time free: relative tolerance on dF/dT + w; "
                             "minimum: relative width of the bracket on T", above=0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", dict(solver_options(self.solver_options)))
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; choose one of {', '.join(MODES)}")
        if self.outer not in OUTER_SOLVERS:
            raise ValueError(
                f"unknown outer solver {self.outer!r}; choose one of {', '.join(OUTER_SOLVERS)}")
        if self.ordering not in ORDERINGS:
            raise ValueError(
                f"unknown ordering {self.ordering!r}; choose one of {', '.join(ORDERINGS)}")
        if not (self.outer_tol > 0 and self.monolithic_tol > 0):
            raise ValueError("tolerances must be positive")
        if self.max_outer_iterations < 1:
            raise ValueError("max_outer_iterations must be at least 1")
        if self.min_separation is not None and not (0 < self.min_separation < math.inf):
            raise ValueError(f"min_separation must be a positive finite length, got "
                             f"{self.min_separation}")
        if self.separation not in SEPARATIONS:
            raise ValueError(f"unknown separation {self.separation!r}; choose one of "
                             f"{', '.join(SEPARATIONS)}")
        if self.critical not in CRITICAL_READINGS:
            raise ValueError(f"unknown critical {self.critical!r}; choose one of "
                             f"{', '.join(CRITICAL_READINGS)}")
        if not 0 < self.ordering_gap < 1:
            raise ValueError(f"ordering_gap must be in (0, 1), got {self.ordering_gap!r}")
        for name in ("separation_rounds", "critical_starts",
                     "slot_candidates", "ordering_rounds"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1")
        if self.initial_angles is not None:
            try:
                object.__setattr__(self, "initial_angles", numbers(self.initial_angles))
            except ValueError as exc:
                raise ValueError(f"initial_angles: {exc}") from None
        if self.initial_rotation is not None and not math.isfinite(self.initial_rotation):
            raise ValueError(f"initial_rotation: must be a finite angle (rad), got "
                             f"{self.initial_rotation!r}")
        if self.time_bounds is not None:
            try:
                bounds = numbers(self.time_bounds)
            except ValueError as exc:
                raise ValueError(f"time_bounds: {exc}") from None
            if not (len(bounds) == 2 and 0 < bounds[0] <= bounds[1] < math.inf):
                raise ValueError(f"time_bounds: needs T_min,T_max with 0 < T_min <= T_max < "
                                 f"inf, got {self.time_bounds}")
            object.__setattr__(self, "time_bounds", bounds)
        if self.final_time not in FINAL_TIMES:
            raise ValueError(f"unknown final_time {self.final_time!r}; choose one of "
                             f"{', '.join(FINAL_TIMES)}")
        if not (self.time_weight >= 0 and math.isfinite(self.time_weight)):
            raise ValueError(f"time_weight: must be a finite number >= 0, got "
                             f"{self.time_weight!r}")
        if not self.time_tol > 0:
            raise ValueError("tolerances must be positive")
        if self.initial_angles is not None and self.initial_rotation is not None:
            raise ValueError("initial_angles and initial_rotation: give one start, not both")


def control_squares(problem: FormationProblem, controls: np.ndarray) -> np.ndarray:
    """Each agent's Σ |u|² over its control groups whose cost parts the run reports
    (:func:`~ocpar.formation.finish.cost_groups`), from the controls (n, N, nu): (n, groups),
    as a worker computes its agents' (:mod:`ocpar.formation.finish`)."""
    groups = cost_groups(problem)
    if not groups:
        return np.zeros((len(controls), 0))
    return np.column_stack([np.sum(controls[..., a:b] ** 2, axis=(1, 2))
                            for a, b in groups.values()])


def cost_parts(problem: FormationProblem, squares: np.ndarray) -> dict[str, float]:
    """The total cost h Σ |u|² split into the model's named control groups (e.g. force and
    torque), from each agent's sums ``squares`` (n, groups, :func:`control_squares`) added
    in agent order; empty if the model names none or an agent has a running cost of its
    own."""
    h = problem.common_shape.duration / problem.common_shape.intervals
    return {name: float(h * np.sum(squares[:, j]))
            for j, name in enumerate(cost_groups(problem))}


def given_start(problem: FormationProblem, options: FormationOptions) -> np.ndarray | None:
    """The start the options give (``initial_angles``, or ``initial_rotation`` added to
    :meth:`~ocpar.formation.FormationProblem.initial_phi`), shape
    :attr:`~ocpar.formation.FormationProblem.parameter_shape`; None if they give none.
    ValueError (one line) for a start of the wrong length or onto slots."""
    if options.initial_angles is None and options.initial_rotation is None:
        return None
    if isinstance(problem.curve, Slots):
        raise ValueError("initial_angles/initial_rotation: onto slots the assignment chooses "
                         "the start")
    if options.initial_rotation is not None:
        if isinstance(problem.curve, Surface):
            raise ValueError("initial_rotation: applies to curves; on a surface give "
                             "initial_angles")
        return problem.initial_phi() + options.initial_rotation
    size = problem.agents * problem.parameters
    if len(options.initial_angles) != size:
        raise ValueError(f"initial_angles: needs {size} angles ({problem.agents} agents"
                         f"{' x 2 parameters' if problem.parameters == 2 else ''}), got "
                         f"{len(options.initial_angles)}")
    return np.reshape(np.array(options.initial_angles), problem.parameter_shape)


def check_applicable(problem: FormationProblem, options: FormationOptions) -> None:
    """Raise ValueError (one line) if ``options`` ask for a circle's shortcut (``offset``
    outer solver, ``optimal`` ordering) on a problem whose curve is not a circle, or for a
    ``min_separation`` that the monolithic mode does not offer or that two start or final
    positions already violate (the final positions of the initial angles: on a circle every
    formation has the same spacings, elsewhere the formation is the initial one), or a
    coupling other than the potential that has no solution near the initial guess; a driver
    calls it before starting workers (:func:`solve_formation` calls it too). With obstacles,
    a formation whose targets clear them must exist among the initial angles' family
    (:meth:`~ocpar.formation.FormationProblem.clear_start`: a rotation on a circle). With a
    final time other than ``fixed`` (:func:`~ocpar.formation.final_time.check_final_time`),
    the problem's own duration is only a start: its feasibility is not asked."""
    if problem.ode_agents:
        _check_ode_applicable(problem, options)
    check_final_time(problem, options)
    check_minimum_time(problem, options)
    if isinstance(problem.curve, Surface) and options.mode != "hierarchical":
        raise ValueError("surfaces apply to the hierarchical mode only")
    if isinstance(problem.curve, Slots) and options.mode != "hierarchical":
        raise ValueError("slots apply to the hierarchical mode only (the assignment is the "
                         "outer problem)")
    if isinstance(problem.curve, Slots) and options.ordering == "optimal":
        raise ValueError("ordering 'optimal' does nothing onto slots: their assignment is "
                         "always the optimal one over each agent's candidate slots "
                         "(--slot-candidates); use ordering 'keep'")
    if problem.obstacles and not isinstance(problem.curve, Slots):
        problem.clear_start(problem.initial_phi())
    if options.mode == "hierarchical" and options.outer == "offset":
        problem.require_circle("outer 'offset'")
    if options.ordering == "optimal" and not problem.on_circle \
            and problem.coupling != PotentialCoupling():
        raise ValueError(f"ordering 'optimal' off a circle searches the potential's isolated "
                         f"solution sets; the {problem.coupling.label} coupling is not "
                         "searched (use ordering 'keep')")
    if not isinstance(problem.curve, Slots) and problem.coupling != PotentialCoupling():
        phi0 = problem.initial_phi()
        residual = np.max(np.abs(problem.coupling.residual(phi0, problem.curve)))
        if not np.isfinite(residual):
            raise ValueError("coupling: g(phi) is not finite at the initial guess")
        if not residual <= PROJECTION_TOL:
            raise ValueError(f"coupling: no solution of g(phi) = 0 found from the initial "
                             f"guess (max |g| {residual:.3g} after the projection)")
    if given_start(problem, options) is not None and options.ordering == "optimal":
        raise ValueError("initial_angles/initial_rotation: ordering 'optimal' chooses its own "
                         "start (use ordering 'keep')")
    if problem.reach_sets() and options.final_time == "fixed":   # ValueError if none is
        feasible_start(problem, problem.initial_phi())
    if options.min_separation is not None:
        size = problem.common_shape.boundary_size   # p = (start, end, ...)
        final = problem.boundary_params_rows(np.arange(problem.agents),
                                             problem.initial_phi())[:, size:2 * size]
        check_separation_feasible(problem.positions(problem.starts), problem.positions(final),
                                  options.min_separation)


def _check_ode_applicable(problem: FormationProblem, options: FormationOptions) -> None:
    """What ODE agents (:class:`~ocpar.ocp.MsEndpointShape`) do not offer yet: ValueError
    naming the option."""
    if options.min_separation is not None and options.separation == "exact":
        raise ValueError("separation 'exact': not yet for ODE agents (MsEndpointShape); "
                         "use separation 'rounds'")
    if options.min_separation is not None \
            and len({(type(s), s.node_size, s.n_params) for s in set(problem.shapes)}) > 1:
        raise ValueError("min_separation: not yet for a fleet of agents of different kinds "
                         "or state sizes (DMOC and ODE agents, or ODE models of different nx)")


def obstacle_check(problem: FormationProblem, positions: np.ndarray, status: str,
                    message: str, durations: np.ndarray | None = None
                    ) -> tuple[str, str, dict]:
    """The returned paths' positions (n, P, p; :func:`~ocpar.formation.verify.checked_positions`:
    the nodes, or an ODE agent's re-integrated path) checked against ``problem``'s obstacles
    (:func:`~ocpar.formation.keep_out.obstacles.closest_obstacle`, independently of the
    inner planes): the status (``obstacles_not_cleared`` if a path of a run that reached its
    answer is inside one), the message and the result's obstacle fields (clearance, each
    agent's sides); unchanged and none without obstacles. ``durations`` (n,): each agent's
    horizon T where it chose its own (the closest point's time; default the shapes')."""
    if not problem.obstacles:
        return status, message, {}
    closest = closest_obstacle(positions, problem.obstacles, problem.common_shape.duration
                               if durations is None else durations)
    fields = {"obstacle_clearance": closest,
              "obstacle_sides": passing_sides(positions, problem.obstacles)}
    if not np.isfinite(closest.distance):
        return status, message, fields
    if cleared(closest, problem.obstacles):
        return status, message + f"; obstacles cleared (min clearance {closest.distance:.3g})", \
            fields
    words = (f"agent {closest.agent} comes {-closest.distance:.3g} inside obstacle "
             f"{closest.obstacle} at t = {closest.time:.6g}")
    if status in ("converged", "not_converged"):
        return "obstacles_not_cleared", f"obstacles not cleared: {words}", fields
    return status, message + f"; {words}", fields


#: The verification's checks a status already reports (its message says by how much).
KNOWN_FAILURES = {"separation_not_met": ("separation",), "obstacles_not_cleared": ("obstacles",)}


def _verified(verification: Verification, status: str, message: str
              ) -> tuple[Verification, str, str]:
    """The answer's ``verification`` (:mod:`ocpar.formation.verify`) and the status and
    message it leaves: ``converged`` becomes ``failed`` if it fails (the message then starts
    with the first failure), other statuses stay with the failures appended that they do not
    already report (:data:`KNOWN_FAILURES`); a near-collision is said in the message (the
    status stays)."""
    if not verification.passed:
        if status == "converged":
            words = verification.failure_words()
            return verification, "failed", (f"the returned formation fails verification: "
                                            f"{words}; the solve said: {message}")
        words = verification.failure_words(KNOWN_FAILURES.get(status, ()))
        if words:
            message += f"; the returned formation fails verification: {words}"
    elif verification.near_collision is not None:
        message += f"; {near_collision_words(verification.near_collision)}"
    return verification, status, message


def discrete_choice(problem: FormationProblem, choice: IsolatedChoice | SlotChoice | None,
                    phi0: np.ndarray | None) -> dict:
    """The result's fields on the outer problem's feasible set near the start ``phi0``:
    ``continuous`` where the coupling leaves free directions (a circle's common rotation,
    equal arc length's shift, a sphere's rotations); elsewhere ``discrete``: the coupling's
    isolated solutions. Off a circle the potential's critical sets are a discrete choice
    either way: ``critical_sets`` lists the candidates searched
    (:mod:`ocpar.formation.couplings.critical_sets`), None when none were; onto slots the
    assignments. The status line's words on it are in ``note``."""
    if isinstance(choice, SlotChoice):
        every = choice.candidates == problem.curve.count
        return {"feasible_set": "discrete", "note": (
            f"; {problem.agents} agents onto {problem.curve.count} slots, "
            + ("every slot a candidate: the optimal assignment" if every else
               f"the optimal assignment over each agent's {choice.candidates} nearest slots "
               f"to its start and to its place (no cheaper one with "
               f"{min(2 * choice.candidates, problem.curve.count)})"))}
    feasible_set = problem.coupling.feasible_set(phi0, problem.curve)
    if choice is not None:
        return {"feasible_set": feasible_set,
                "critical_sets": [s.to_dict() for s in choice.sets],
                "note": (f"; the best of {len(choice.sets)} critical set(s) found from "
                         f"{choice.starts} start(s)"
                         + (f" (the last {choice.saturation} found no new one)"
                            if choice.saturated else " (the search had not saturated)")
                         + ", each with its cheapest assignment"
                         + (" and rotation" if feasible_set == "continuous" else "")
                         + (f" ({choice.dropped} more dropped: their returned points are "
                            "not critical or not of the potential reported)"
                            if choice.dropped else ""))}
    potential = problem.coupling == PotentialCoupling()
    if feasible_set == "continuous" and (problem.on_circle or not potential):
        return {"feasible_set": "continuous", "note": ""}
    if not potential:
        return {"feasible_set": "discrete", "critical_sets": None, "note": (
            f"; the feasible set is discrete (the {problem.coupling.label} coupling's isolated "
            "solutions): this is the one the initial guess selects, others not searched")}
    if feasible_set == "continuous":   # a sphere: critical sets, each up to a rotation
        return {"feasible_set": "continuous", "critical_sets": None, "note": (
            "; the potential's critical sets are isolated up to the target's rotations: this "
            "is the set the initial guess selects, turned by the cost; other sets and "
            "assignments not searched (--ordering optimal finds the best)")}
    return {"feasible_set": "discrete", "critical_sets": None, "note": (
        "; the feasible set is discrete (the potential's isolated critical points): this is "
        "the formation the initial guess selects, other solution sets and assignments not "
        "searched (--ordering optimal finds the best)")}


def solve_formation(
    problem: FormationProblem,
    backend: Backend | None = None,
    options: FormationOptions | None = None,
    phi0: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    output: Path | None = None,
) -> FormationResult:
    """Solve ``problem`` from the angles ``phi0`` (default: the options' ``initial_angles``
    or ``initial_rotation``, else :meth:`FormationProblem.initial_phi` moved to the nearest
    feasible formation, :func:`~ocpar.formation.feasibility.feasible_start`; onto slots
    none: the assignment chooses them).

    ``backend`` runs the inner solves (default: serial, in this process); ``progress`` is
    called with one line per superstep. The backend is left open for the caller to close.
    ``output``: the directory the run's files go to, where a large run's workers write their
    agents' part of the array file themselves (:mod:`ocpar.formation.finish`; the result
    then holds no per-agent paths, controls or solver statuses, and names the parts); None:
    every agent's arrays come back into the result.
    """
    options = options or FormationOptions()
    backend = backend or SerialBackend()
    check_applicable(problem, options)
    if options.final_time == "minimum":
        return solve_minimum_time(problem, backend, options, solve_formation, progress, output)
    if options.final_time == "free_per_agent":
        return solve_per_agent_time(problem, backend, options, solve_formation, phi0, progress)
    if options.inner_solver is not None and any(
            shape.solver != options.inner_solver for shape in problem.shapes):
        problem = problem.with_shapes(
            lambda shape: dataclasses.replace(shape, solver=options.inner_solver))
    problem = with_solver_options(problem, options.solver_options)
    if options.final_time == "free":
        return solve_free_time(problem, backend, options, solve_formation,
                               given_start(problem, options) if phi0 is None else phi0,
                               progress, output)
    slots = isinstance(problem.curve, Slots)   # then the assignment chooses φ: no φ0
    if phi0 is None:
        phi0 = given_start(problem, options)
    if phi0 is None and not slots:
        phi0 = feasible_start(problem, problem.initial_phi())
    elif phi0 is not None:
        phi0 = np.asarray(phi0, float)
    if phi0 is not None and phi0.shape != problem.parameter_shape:
        raise ValueError(f"phi0 must have shape {problem.parameter_shape}, got {phi0.shape}")
    if phi0 is not None:
        phi0 = phi0.ravel()   # the outer solvers see a vector (on a surface agent i's at 2i, 2i+1)
    if phi0 is not None and problem.obstacles and not slots:
        phi0 = problem.clear_start(phi0)   # a target inside an obstacle: start elsewhere
    building = time.perf_counter()
    if options.mode == "hierarchical":   # the workers' inner solvers, apart from the solve
        prepare_workers(problem, backend)
    record = solver_record(problem, options)
    built = time.perf_counter() - building
    first_trace = len(backend.traces)
    start = time.perf_counter()
    common = {"problem": problem.name, "agents": problem.agents, "backend": backend.name,
              "workers": backend.workers, "mode": options.mode, "on_circle": problem.on_circle,
              "solver_options": record}
    ordering_solves, choice, chosen, ordered = 0, None, None, None
    try:
        if slots:
            choice = assign_slots(problem, backend, options.slot_candidates, progress)
            phi0, ordering_solves, chosen = choice.phi, choice.inner_solves, "slots assigned"
        elif options.ordering == "optimal" and problem.on_circle:
            ordered = optimal_ordering(problem, backend, tol=options.outer_tol,
                                       progress=progress, gap=options.ordering_gap,
                                       search_rounds=options.ordering_rounds)
            phi0, ordering_solves = ordered.phi, ordered.inner_solves
        elif options.ordering == "optimal":
            choice = best_isolated_formation(problem, backend, options.critical,
                                             options.critical_starts, progress,
                                             options.outer_tol, options.critical_saturation)
            phi0, ordering_solves, chosen = choice.phi, choice.inner_solves, "ordering optimal"
    except InnerSolveFailed as exc:   # no assignment with every agent feasible: no answer
        n, shape = problem.agents, problem.common_shape
        return FormationResult(
            **common, status="failed", message=f"ordering: {exc}", total_cost=math.nan,
            phi=np.full(problem.parameter_shape, np.nan), agent_costs=np.full(n, np.nan),
            trajectories=np.full((n, shape.intervals + 1, problem.node_width), np.nan),
            outer_iterations=None, inner_solves=0, failed_solves=0,
            wall_time_s=time.perf_counter() - start,
            separation=problem.closest_approach(np.full((n, 2, problem.node_width), np.nan)),
            trace=backend.traces[first_trace:],
            fleet=Fleet.of(problem, np.full(problem.parameter_shape, np.nan)))
    discrete = discrete_choice(problem, choice, phi0)
    note = discrete.pop("note") + ordering_note(ordered)
    if ordered is not None:
        discrete["ordering"] = ordering_fields(ordered)

    if options.mode == "monolithic":
        sol = solve_monolithic(problem, phi0, options.monolithic_tol, options.max_outer_iterations,
                               options.min_separation)
        feasible = sol.violation <= MONOLITHIC_VIOLATION_TOL
        status = ("converged" if sol.success and feasible
                  else "not_converged" if feasible else "failed")
        words = (f"{sol.status}; constraints met (max violation {sol.violation:.1e})"
                 if feasible else
                 f"{sol.status}; the returned point breaks the constraints by "
                 f"{sol.violation:.3g}: an infeasible iterate, no answer")
        wall_time_s = time.perf_counter() - start  # before the checks below (reporting)
        status, message, obstacle_fields = obstacle_check(
            problem, checked_positions(problem, sol.trajectories, sol.controls), status,
            words + note)
        verification, status, message = _verified(verify_formation(
            problem, sol.trajectories, sol.controls, sol.phi, options.min_separation, backend),
            status, message)
        status, message = ordering_status(ordered, status, message)
        checked = time.perf_counter() - start - wall_time_s
        return FormationResult(
            **common,
            status=status,
            message=message,
            total_cost=float(np.sum(sol.agent_costs)),
            phi=sol.phi,
            agent_costs=sol.agent_costs,
            trajectories=sol.trajectories,
            cost_parts=cost_parts(problem, control_squares(problem, sol.controls)),
            outer_iterations=sol.iterations,
            inner_solves=ordering_solves,
            failed_solves=0,
            wall_time_s=wall_time_s,
            timings={"build_s": built, "verification_s": checked},
            separation=verification.closest,
            trace=backend.traces[first_trace:],
            coupling_residual=verification.coupling_residual,
            controls=sol.controls,
            verification=verification,
            fleet=Fleet.of(problem, sol.phi),
            solver_status=[sol.status] * problem.agents,
            solver_iterations=np.full(problem.agents, sol.iterations),
            **discrete,
            **obstacle_fields,
        )

    objective = OuterObjective(problem, backend, progress)
    refusal = None   # phase 1's one line, where it refused the problem
    try:
        if chosen is None:
            phi, iterations, success, message = OUTER[options.outer](
                objective, phi0, options.outer_tol, options.max_outer_iterations
            )
        else:   # the feasible set is discrete and the choice was the outer solve
            phi, iterations, success, message = phi0, 0, True, chosen
        objective.reach(phi)
        status = "converged" if success else "not_converged"
        message += note
        if objective.phase_one is not None:
            message += (f"; the start was infeasible: phase 1 (elastic inner problems, "
                        f"{objective.phase_one.inner_solves} solves) found a feasible one")
    except InnerSolveFailed as exc:
        phi, iterations, status, message = objective.last_phi, None, "failed", str(exc)
        if isinstance(exc, NoFeasibleFormation):   # refused: the paths are no answer to check
            refusal = message
    inner_solves = ordering_solves + objective.inner_solves
    failed_solves, retries = objective.failed_solves, objective.retries
    extra: dict = {}
    distance = options.min_separation
    parts: list[str] = []
    if status == "failed" or distance is not None:   # the paths here, for the rounds
        sols = objective.last_solutions
        objective.close()  # the solutions are gathered: the workers need not keep them
        costs = np.asarray(sols.column("cost"), dtype=float)
        trajectories = padded_paths(sols.column("q"), problem.node_width)
        controls = np.asarray(sols.column("u"))
        statuses, solver_iterations = sols.column("status"), np.asarray(
            sols.column("iterations"))
        if distance is not None and status != "failed":
            exactly = options.separation == "exact" and not problem.obstacles
            rounds = separate(problem, backend, phi, sols, distance,
                              options.separation_rounds, progress, until_met=exactly)
            extra = {"required_separation": distance, "separation_rounds": rounds.rounds,
                     "unconstrained_cost": float(np.sum(costs))}
            costs, trajectories, controls = rounds.costs, rounds.q, rounds.u
            inner_solves += rounds.inner_solves
            failed_solves += rounds.failed_solves
            retries += rounds.retries
            status, message = _separation_words(rounds, distance, status, message)
            if options.separation == "exact" and status == "converged" and problem.obstacles:
                message += ("; the rounds' answer: the exact separation does not take "
                            "obstacles yet")
            elif options.separation == "exact" and status == "converged":
                exact = separate_exactly(problem, backend, phi, rounds, distance, progress)
                inner_solves += exact.inner_solves
                failed_solves += exact.failed_solves
                status, message = _exact_words(problem, exact, distance, message,
                                               extra["unconstrained_cost"])
                if status != "failed":
                    phi = np.reshape(exact.phi, np.shape(phi))
                    costs, trajectories, controls = exact.costs, exact.q, exact.u
        wall_time_s = time.perf_counter() - start
        positions = problem.positions(trajectories)
        durations = (np.asarray(sols.column("duration"), float) if distance is None
                     else None)   # the rounds' paths: at the shapes' T
        continuous = checked_positions(problem, trajectories, controls, durations=durations,
                                       separation=distance is not None)
        squares = control_squares(problem, controls)
        verification = verify_formation(problem, trajectories, controls, phi, distance,
                                        backend)
    else:   # finished where the paths are (ocpar.formation.finish)
        wall_time_s = time.perf_counter() - start
        checking = time.perf_counter()
        done = finish(problem, objective.agents, phi,
                      output if writes_parts(problem, backend, output) else None)
        objective.close()
        costs, trajectories, controls = done.costs, done.q, done.u
        statuses, solver_iterations = done.status, done.iterations
        positions, squares, parts = done.positions, done.squares, done.parts
        durations = done.durations
        continuous = checked_positions(problem, trajectories, controls, positions, durations)
        verification = verify_checked(problem, positions, done.ends, phi, done.checks,
                                      distance, backend,
                                      time.perf_counter() - checking - done.written_s,
                                      continuous)
        if parts:   # the workers wrote their agents' part of the array file
            extra["timings"] = {"files_s": done.written_s}
    checking = time.perf_counter()
    status, message, obstacle_fields = obstacle_check(problem, continuous, status, message,
                                                      durations)
    extra |= obstacle_fields
    if durations is not None and any(getattr(shape, "time_bounds", None) is not None
                                     for shape in problem.agents_by_shape()):
        extra["durations"] = durations   # each agent's own T_i, that of its returned path
    verification, status, message = _verified(verification, status, message)
    status, message = ordering_status(ordered, status, message)
    if refusal is not None:
        message = refusal
    checked = verification.time_s + time.perf_counter() - checking
    return FormationResult(
        **common,
        status=status,
        message=message,
        total_cost=float(np.sum(costs)),
        phi=np.reshape(phi, problem.parameter_shape),
        agent_costs=costs,
        trajectories=trajectories,
        cost_parts=cost_parts(problem, squares),
        outer_iterations=iterations,
        separation=verification.closest,
        inner_solves=inner_solves,
        failed_solves=failed_solves,
        retries=retries,
        wall_time_s=wall_time_s,
        timings={"build_s": built, "verification_s": checked} | extra.pop("timings", {}),
        trace=backend.traces[first_trace:],
        coupling_residual=verification.coupling_residual,
        controls=controls,
        verification=verification,
        fleet=Fleet.of(problem, phi),
        solver_status=statuses,
        solver_iterations=solver_iterations,
        positions=positions,
        parts=parts,
        **discrete,
        **extra,
    )


def with_solver_options(problem: FormationProblem, given: dict) -> FormationProblem:
    """``problem`` with the solver options ``given`` set over each shape's own (one new
    shape per distinct shape object, not one per agent)."""
    if not given:
        return problem
    changed: dict[int, DmocShape] = {}

    def change(shape: DmocShape) -> DmocShape:
        if id(shape) not in changed:
            changed[id(shape)] = dataclasses.replace(
                shape, solver_options=merged(shape.solver_options, given))
        return changed[id(shape)]

    return problem.with_shapes(change)


def solver_record(problem: FormationProblem, options: FormationOptions) -> dict:
    """result.json's ``solver_options``: the run's, and by inner problem's shape (``dmoc`` for
    DMOC agents, ``ms`` for ODE agents; ``dmoc[k]``, ``ms[k]`` for the k-th distinct shape of a
    fleet of several) the options its solvers are built with
    (:func:`ocpar.ocp.solver_options.used`), read from the shapes: no transcription is built."""
    shapes = list(problem.agents_by_shape())
    kinds = ["dmoc" if isinstance(s, DmocShape) else "ms" for s in shapes]
    settings = {kind if len(shapes) == 1 else f"{kind}[{k}]": s.solver_settings()
                for k, (kind, s) in enumerate(zip(kinds, shapes, strict=True))}
    return used(solver_options(options.solver_options), settings)


def ordering_note(ordered: OrderingResult | None) -> str:
    """The status line's words on the optimal ordering on a circle ("" without one)."""
    if ordered is None:
        return ""
    if ordered.bound is None:
        return ("; ordering optimal: the best assignment and rotation found, no bound "
                "claimed (the inner problems are not known to be convex in their end "
                "position, e.g. obstacles or a nonlinear model)")
    if ordered.proven:
        return (f"; ordering optimal: the global optimum over assignments and rotation, "
                f"proven to a gap of {ordered.gap:.1e} (lower bound {ordered.lower_bound:.12g})")
    return f"; ordering optimal: {ordered.search_message}"


def ordering_status(ordered: OrderingResult | None, status: str, message: str
                    ) -> tuple[str, str]:
    """``status`` and ``message`` unless the ordering's search claimed a bound and stopped
    short of its gap (its budget, or failed solves): then ``not_converged`` in place of
    ``converged``, the message first saying why."""
    if ordered is not None and ordered.bound is not None and not ordered.proven \
            and status == "converged":
        rest = message.replace(ordering_note(ordered), "")
        return "not_converged", f"ordering optimal {ordered.search_message}; {rest}"
    return status, message


def ordering_fields(ordered: OrderingResult) -> dict:
    """``result.json``'s ``ordering`` (:class:`~ocpar.formation.result.FormationResult`)."""
    def finite(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    return {"assignment": np.asarray(ordered.assignment).tolist(),
            "offset": float(ordered.offset), "bound": ordered.bound,
            "proven": bool(ordered.proven), "gap": finite(ordered.gap),
            "lower_bound": finite(ordered.lower_bound),
            "search_supersteps": int(ordered.search_supersteps),
            "search_inner_solves": int(ordered.search_solves),
            "inner_solves": int(ordered.inner_solves),
            "message": ordered.search_message or ordered.message}


def _separation_words(rounds: Separation, distance: float, status: str, message: str
                      ) -> tuple[str, str]:
    """The status and message after the separation ``rounds`` for the required ``distance``
    (length unit)."""
    if rounds.met and not rounds.rounds:
        return status, message + f"; separation {distance:g} met by the unconstrained paths"
    if rounds.met:
        return status, message + (f"; separation {distance:g} met after {rounds.rounds} "
                                  f"round(s) (last move {rounds.change:.1e})")
    return "separation_not_met", (
        f"separation {distance:g} not met after {rounds.rounds} round(s): agents "
        f"{rounds.closest.agents[0]} and {rounds.closest.agents[1]} come within "
        f"{rounds.closest.distance:.6g} (short by {distance - rounds.closest.distance:.3g}; "
        f"{rounds.dropped} half-space(s) dropped for want of slots over the rounds)")


def _exact_words(problem: FormationProblem, exact: ExactSeparation, distance: float,
                 message: str, unconstrained: float) -> tuple[str, str]:
    """The status and message after the exact separation ``exact``
    (:mod:`ocpar.formation.keep_out.exact`) for the required ``distance`` (length unit),
    appended to the rounds' ``message``: ``separation_not_met`` if the answer's closest
    approach (computed here) is below D (1 −
    :data:`~ocpar.formation.keep_out.rounds.SEPARATION_RTOL`), ``not_converged`` if its
    search over the rotation did not converge or the angles have free directions it does not
    search (a surface's rotations, a user's coupling without a shift family), ``failed`` if a
    cluster's solve failed (no answer), else ``converged``; where a cluster was too large
    for it, the rounds' answer, ``converged``, its cost's increase over the
    ``unconstrained`` total cost stated (the gap's bound where that optimum is global)."""
    if exact.too_large:
        increase = float(np.sum(exact.costs)) / unconstrained - 1
        return "converged", (f"{message}; exact separation {exact.message}: the rounds' "
                             f"answer, separated, its optimality not proven (cost "
                             f"{increase:.3g} relative above the unconstrained optimum, which "
                             "bounds the gap where that optimum is global)")
    if not exact.success and exact.message.startswith(("a cluster", "the inner solve")):
        return "failed", f"exact separation: {exact.message}"
    closest = problem.closest_approach(exact.q)
    words = (f"{message}; exact separation: {len(exact.pairs)} pair(s) with separating planes "
             f"(largest cluster {exact.largest} agent(s)), rotation {exact.rotation:+.6e} rad "
             f"in {exact.evaluations} superstep(s), closest {closest.distance:.10g}")
    if closest.distance < distance * (1 - SEPARATION_RTOL):
        return "separation_not_met", (
            f"separation {distance:g} not met by the exact separation: agents "
            f"{closest.agents[0]} and {closest.agents[1]} come within "
            f"{closest.distance:.6g} (short by {distance - closest.distance:.3g})")
    if not exact.success:
        return "not_converged", words + f"; {exact.message}"
    return "converged", words
