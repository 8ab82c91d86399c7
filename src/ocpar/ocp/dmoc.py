"""DMOC: Discrete Mechanics and Optimal Control (discrete Lagrange–d'Alembert principle).

A mechanical system with Lagrangian L(q, q̇) moves on [0, T] from (q_0, q̇_0) to (q_N, q̇_N)
under controls u, minimising ∫|u|² dt. The path is discretised at N+1 nodes q_k = q(kh),
h = T/N, with the midpoint discrete Lagrangian

    L_d(q_k, q_{k+1}) = h L((q_k + q_{k+1})/2, (q_{k+1} - q_k)/h)

and one control u_k per interval (the average of the paper's node forces, whose alternating
component (-1)^k a changes neither cost nor dynamics). The left and right discrete forces of
interval k are f⁻_k = f⁺_k = (h/2) F(q_{k+½}, u_k), F the model's generalised force. The
constraints are the discrete Euler–Lagrange equations with the boundary momenta:

    D2L(q_0, q̇_0) + D1L_d(q_0, q_1) + f⁻_0 = 0
    D2L_d(q_{k-1}, q_k) + D1L_d(q_k, q_{k+1}) + f⁺_{k-1} + f⁻_k = 0,   k = 1..N-1
    -D2L(q_N, q̇_N) + D2L_d(q_{N-1}, q_N) + f⁺_{N-1} = 0

and the cost is J_d = h Σ_k |u_k|², or with a general running cost C(q, q̇, u)
(``DmocShape.running_cost``) J_d = h Σ_k C(q_{k+½}, (q_{k+1} − q_k)/h, u_k), the same midpoint
rule as L_d (second order, like the dynamics). Boundary data p = (q_0, q̇_0, q_N, q̇_N) ∈
R^{4 nq} are NLP parameters; the decision variables are w = (q_1..q_{N-1}, u_0..u_{N-1}, λ_0..λ_N).

Keep-out half-spaces (optional, ``DmocShape.keep_out_slots`` K > 0): K slots per interval k,
each a normal n ∈ R^d and offsets b⁰, b¹ at the interval's two nodes on the position r(q)
(the d configuration entries ``keep_out_positions``, e.g. the model's ``position_indices``),
appended to p after the boundary data, slot by slot, interval by interval:
(n_{0,0}, b⁰_{0,0}, b¹_{0,0}, n_{0,1}, …, b¹_{N−1,K−1}). The half-space moves linearly in time
over the interval, n·r(t) ≥ b(t) with b linear from b⁰ at t_k to b¹ at t_{k+1}; the rows are
n·r(q_k) ≥ b⁰ and n·r(q_{k+1}) ≥ b¹ at the interval's free nodes (the boundary nodes are
data: whoever builds a half-space on the first or last interval must make it hold there).
The continuous path DMOC represents is linear between nodes, so n·r(t) − b(t) is linear in
t on the interval: both ends ≥ 0 put the whole interval in the moving half-space. An unused
slot is n = 0, b⁰ = b¹ = −1 (:data:`UNUSED_OFFSET`): 0 ≥ −1, never active. The keep-outs
are elastic, so that the NLP is feasible whatever the half-spaces: each slot has a slack
σ_{k,s} ≥ 0 (appended to w), n·r − b + σ ≥ 0, and the cost gains ρ Σ σ with the penalty ρ
the last entry of p (an exact penalty: σ = 0 whenever the half-spaces can be met and ρ
exceeds their multipliers; the returned ``cost`` is h Σ |u_k|² alone). Slots are
parameters, not structure, so one compiled solver serves every agent whatever its
constraints; inequalities need the ``sqpmethod`` or ``ipopt`` solver (``newton`` takes
equalities only).

Control bounds (optional, ``DmocShape.control_bounds``): lo_j ≤ u_k[j] ≤ hi_j on every
interval's control, as bounds on w. u_k is constant on its interval, so the bound holds at
all times of the continuous control. The ``newton`` solver ignores bounds and only checks
them: a task whose unconstrained optimum leaves them goes on to IPOPT, which imposes them
exactly (no bound relaxation); ``sqpmethod`` imposes them in its batch. ``auto``, for a
shape whose only inequalities are control bounds and path constraints, stays on the Newton
kernel: every task by ``newton`` without them first (:attr:`DmocTranscription.without_limits`),
kept where its path keeps every limit inactive; the others by Newton on a guessed active set
(:class:`~ocpar.ocp.active_set.ActiveSetNewton`), accepted where this NLP's KKT conditions
hold to ``kkt_tol``; only the rest by ``sqpmethod``, then IPOPT. ``end_hessian``
comes from the KKT system of the equations where no bound is active, and from that of the
active set where one is (a control within ``kkt_tol`` of its bound, as a path row below;
strict complementarity assumed, :mod:`ocpar.ocp.sensitivity` says what happens otherwise).

Path constraints (optional, ``DmocShape.path_constraints``, :mod:`ocpar.ocp.constraints`):
functions of ``q``, ``v`` and ``u``. One of ``q`` alone is imposed at the free nodes
q_1..q_{N−1} (the boundary nodes are data); one that names ``v`` or ``u`` on each interval
at the arguments of its discrete Lagrangian and force, (q_{k+½}, (q_{k+1} − q_k)/h, u_k).
The continuous path DMOC represents is linear between nodes with constant velocity and
control on each interval, so a constraint of ``v`` and ``u`` alone (a thrust limit |u| ≤
u_max, a speed limit) holds at all times, and one convex in ``q`` (a half-space, a ball or
an ellipsoid to stay *inside*, a corridor) holds on the whole path when it holds at the
nodes; a non-convex one (staying *outside* an obstacle) can be broken between nodes: that is
what ``obstacles`` (below) impose exactly, a separating plane per interval. They are
inequalities: the ``newton`` solver takes equalities only, so a shape with path constraints
needs ``sqpmethod`` or ``ipopt``; ``end_hessian`` comes from the active set where a row is
active (as at a control bound).

Obstacles (optional, ``DmocShape.obstacles``, :mod:`ocpar.ocp.obstacles`): ellipsoids
(spheres) and half-spaces the positions r(q) (the d entries ``obstacle_positions``) stay out
of at all times of the continuous path. Each interval gets one separating plane n ∈ R^d per
ellipsoid as decision variables (appended to w, interval by interval, ellipsoid by
ellipsoid), with the rows 1 − |n|² ≥ 0, n·A(r(q_k) − c) − 1 ≥ 0 and n·A(r(q_{k+1}) − c) − 1 ≥ 0
(exact: the segment is then at scaled distance ≥ 1 from the centre, and such a plane exists
whenever it is; on the first and last intervals the boundary node's row binds n); a
half-space n·r(q_k) ≥ b at the free nodes. The rows come after the path rows. Which side a
path passes an ellipsoid on is the guess's choice: from the default guess (a task without
one), where its path enters an ellipsoid, every side of it
(:func:`~ocpar.ocp.obstacles.side_guesses`) is solved and the cheapest solution kept (ties:
the first, the side of the path's point nearest the centre), in the same solve; a guess
without planes gets each interval's nearest-point direction
(:func:`~ocpar.ocp.obstacles.guess_planes`).
``end_hessian`` comes from the active set with the planes made canonical
(:func:`~ocpar.ocp.obstacles.canonical_planes`: unique where an obstacle binds; fixed, as at
a bound, where none does, their variables being free there). Inequalities: ``sqpmethod``
or ``ipopt``. A batch (``sqpmethod``, ``auto``'s choice) never hands the planes to a QP:
their variables have no curvature where no row binds them, which ``qrqp`` meets as a
singular QP (in 3-D the batch failed on most tasks that way). It solves the tasks without
the obstacles first (:attr:`DmocTranscription.without_obstacles`: ``newton`` for a shape
whose only inequalities were the obstacles) and keeps each solution that clears them; the
others, from each side of the obstacles their free path enters, by one mapped ``sqpmethod``
call on the same keep-out without planes (:func:`~ocpar.ocp.obstacles.segment_rows`: one row
per interval, |y*|² ≥ 1 at the segment's point y* nearest the centre), lifted to this NLP
(canonical planes, :func:`~ocpar.ocp.obstacles.plane_multipliers`) and accepted only where
this NLP's KKT conditions hold to ``kkt_tol``; what fails goes to IPOPT, one task at a time.

Elastic (phase-1) problem (optional, ``DmocShape.elastic``): the same equations and rows,
every condition a formation's outer problem can make infeasible given slack, the cost the
total slack (ℓ1) instead of J_d. The end configuration and velocity enter as
q_N + a⁺ − a⁻ and q̇_N + b⁺ − b⁻ (a±, b± ≥ 0, nq each), each control bound as
lo − σ ≤ u_k[j] ≤ hi + σ and each path row as lb − σ ≤ c ≤ ub + σ (one σ ≥ 0 per control
entry and interval, per row; the obstacle rows stay hard: the start is clear of them and the
end and controls are free, so they can always be met). With holonomic constraints the
slackened end stays on them: c(q_N + a⁺ − a⁻) = 0 is a hard row (the slack moves the end
along the manifold, never off it; a velocity's component normal to it is taken up by the
end node's reaction). The cost is the total slack, each measured against a characteristic
size so that one tolerance means the same for all:
s = Σ a± + T Σ b± + Σ σ_u / |u|_j + Σ σ_row / |row|, the end position's in its length unit,
the end velocity's times the duration T (a length), a control bound's and a path row's
relative to the bound (|u|_j = max(|lo_j|, |hi_j|) over the finite ones, |row| likewise of
the row's bounds; 1 where that is 0): 0 exactly where the hard NLP is feasible. The NLP is
feasible whatever p (zero controls and any path meet the equations with slack), and its
``cost_gradient`` −λ_p is ds*/dp (entries
2nq..3nq: ds*/dq_N, the end position's). No ``end_hessian`` (NaN), no keep-out slots; the
returned ``q`` ends at the data q_N, not at the slackened end.

Free duration (optional, ``DmocShape.free_duration``): T is the last entry of p instead of
the constant ``duration`` (h = T/N in every expression above), so one compiled solver serves
every horizon, and the solution's ``cost_gradient`` carries dJ*/dT (−λ_p of T, the
envelope theorem) and its ``end_hessian`` is the (nq + 1, nq + 1) block of d²J*/dp² over
(q_N, T): d²J*/dq_N², d²J*/dq_N dT and d²J*/dT² from the KKT system
(:mod:`ocpar.ocp.sensitivity`). ``duration`` is then unused by the NLP (the shape is built
once for all durations, :meth:`DmocShape.build`). No keep-out slots with it.

Free duration per task (optional, ``DmocShape.time_bounds`` (T_min, T_max) with
``time_weight`` w ≥ 0): T is a decision variable in [T_min, T_max] (in w after the slacks,
before the planes) and the cost J_d + w T; the solution's ``cost`` is that sum, its
``duration`` the T it chose, and its ``cost_gradient`` and ``end_hessian`` those of the
optimum over T as well (the KKT system has T among its variables: d²/dq_N² of
min_T (J + w T), the Schur complement of T's block). Bounds on T are inequalities
(``sqpmethod`` or ``ipopt``). Not with ``free_duration``, keep-out slots, ``elastic`` or a
time-dependent model.

A time-dependent Lagrangian gives each interval its own L_d (see
:class:`~ocpar.models.MechanicalSystem`). Holonomic constraints c(q) = 0 (e.g. a unit
quaternion) add the reaction ∇c(q_k)ᵀ λ_k to the equation of every node k = 0..N (boundary
nodes included: without it the boundary momenta would over-determine the path) and
c(q_k) = 0 at the inner nodes (the boundary nodes are data); λ is empty otherwise.
"""

from __future__ import annotations

import dataclasses
import itertools
import operator
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np

from ocpar.bsp.columns import LISTED, SHARED, STACKED, VALUES, Columns, to_columns
from ocpar.models.mechanical import MechanicalSystem
from ocpar.ocp.active_set import ActiveSetNewton
from ocpar.ocp.batch import (
    AUTO_SOLVER,
    SOLVERS,
    BatchSolve,
    KktNewton,
    MappedNlp,
    kkt_met,
    kkt_residuals,
    sqp_options,
)
from ocpar.ocp.constraints import (
    CompiledConstraint,
    CompiledFunction,
    ConstraintRows,
    PathConstraint,
    bound_sizes,
    check_control_bounds,
    compile_constraints,
    compile_function,
)
from ocpar.ocp.contract import (
    InnerSolution,
    NlpCall,
    call_nlpsol,
    check_params,
    transcription,
)
from ocpar.ocp.convex_qp import ConvexQp
from ocpar.ocp.duration import build_at_unit_duration, check_time_fields, over_duration
from ocpar.ocp.obstacles import (
    SIDE_OBSTACLES,
    Obstacle,
    canonical_planes,
    check_obstacles,
    ellipsoids,
    entered,
    guess_planes,
    keep_out_rows,
    obstacle_rows,
    on_near_side,
    plane_multipliers,
    segment_rows,
    side_guesses,
)
from ocpar.ocp.sensitivity import cost_hessian_function, shared_cost_hessian_function
from ocpar.ocp.solver_options import (
    SolverOptions,
    ipopt,
    newton,
    solver_options,
    sqpmethod,
)

#: Newton steps the ``newton`` solver takes on a batch at most (one per call: a QP such as
#: a point mass's needs one; a rigid spacecraft's from the default guess four), and at most
#: the shape's ``max_iter``.
NEWTON_ROUNDS = 8

#: SQP iterations (at most; and the shape's ``max_iter``) and ``qrqp`` active-set iterations
#: per QP of a solve with the obstacles' segment rows (``DmocTranscription.segment_nlp``):
#: from the side nearest the unconstrained path it takes 3–5 (the mixed fleet in 3-D), from
#: the far side up to ~35, each QP's active-set search up to hundreds (0.8 s for one solve
#: of the box-limited fleet without these limits, 78 ms with them); a candidate stopped by
#: them fails (its other sides, or IPOPT, answer).
SEGMENT_MAX_ITER = 50
SEGMENT_QP_MAX_ITER = 100
#: The segment rows' ``sqpmethod`` stops at ``kkt_tol`` times this (its answers are still
#: accepted by the KKT check at ``kkt_tol``): started from an agent's previous solution
#: (:meth:`DmocTranscription.start_guesses`) it would stop at its first iterate within
#: ``kkt_tol``, ~1e-10 off, where a cold start's last step lands at rounding; the outer
#: Newton's test (1e-12 on the summed gradient) then took two more supersteps on the 2-D
#: fleet. Below rounding, it stops when its steps vanish: ~5–10 % more time per warm solve.
SEGMENT_TOL_FACTOR = 1e-5

#: Offset b of an unused keep-out slot (with normal 0: the row 0 ≥ b is never active).
UNUSED_OFFSET = -1.0

#: IPOPT statuses of a solve that stopped where rounding stops progress: a success if the
#: returned point meets the KKT check (:meth:`DmocTranscription._checked`).
ROUNDING_STOPS = ("Search_Direction_Becomes_Too_Small", "Solved_To_Acceptable_Level")

#: Status of a batched solve, by the outcome of its KKT check.
BATCH_STATUS = {True: "Solve_Succeeded", False: "KKT_Check_Failed"}


@dataclass(frozen=True)
class DmocShape:
    """Everything that fixes the structure of a DMOC NLP (the solver-cache key).

    ``duration`` is T in the model's time unit; ``intervals`` is N. ``solver`` (see
    :mod:`ocpar.ocp.batch`): ``newton`` (a chunk of tasks in one compiled call of Newton
    steps on the KKT system, ~0.012 ms per point-mass solve and ~0.8 ms per rigid
    spacecraft; equalities only), ``sqpmethod`` (one mapped ``sqpmethod``/``qrqp`` call,
    ~0.05 / 1.7 ms), both with IPOPT for the tasks whose KKT check fails, or ``ipopt`` (one
    IPOPT call per task, ~0.5 / 1.5 ms); ``auto`` (the default) is :attr:`chosen_solver`:
    ``newton`` (the fastest, by measurement) for a shape of equalities only, ``sqpmethod``
    for one with inequalities (control bounds, path constraints, keep-out slots, obstacles:
    ``newton`` only checks bounds afterwards, and a task with an active bound went to IPOPT,
    ~10 ms), its batch trying ``newton`` first where control bounds and path constraints
    are its only inequalities (module docstring). ``kkt_tol`` is
    the batched solvers' stopping tolerance on the (unscaled) primal and dual residuals and
    their acceptance test;
    ``tol`` is IPOPT's (scaled). With 1e-10 a point-mass QP takes one sqpmethod iteration
    instead of two (at 1e-12 the second only meets rounding), and its cost agrees with
    IPOPT's to ~1e-13. ``keep_out_slots`` K and ``keep_out_positions`` (d configuration
    entries): K keep-out half-spaces per interval on those entries (module docstring; K = 0:
    none, the NLP of old). ``control_bounds``: one (lo, hi) per control entry, the model's
    force unit (module docstring; None: unbounded, the NLP of old). ``path_constraints``:
    :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``q``, ``v`` and ``u`` (module
    docstring), compiled when the shape is built. ``running_cost``: C(q, v, u) ≥ 0, a scalar
    function whose parameter names (among ``q``, ``v``, ``u``) pick its arguments (module
    docstring; None: |u|², the NLP of old). ``obstacles``:
    :class:`~ocpar.ocp.obstacles.Ellipsoid` and :class:`~ocpar.ocp.obstacles.HalfSpace`
    obstacles in position space, kept
    clear exactly on the continuous path (module docstring; none: the NLP of old), on the
    configuration entries ``obstacle_positions`` (default: the first d, d the obstacles'
    dimension). ``elastic``: the phase-1 NLP of this shape instead (module docstring; its
    ``cost`` the total slack s ≥ 0, 0 where the shape's NLP is feasible). ``free_duration``:
    T is the last parameter (module docstring; ``duration`` is then the caller's value of
    it, not part of the NLP). ``time_bounds`` (T_min, T_max) and ``time_weight`` w: T a
    decision variable of each task, the cost J + w T (module docstring; ``duration``, clipped
    to the bounds, is then the first guess of T).
    ``solver_options``: the inner solvers' own options (``ipopt.tol``, ``sqpmethod.max_iter``,
    ``newton.kkt_tol``, …; :mod:`ocpar.ocp.solver_options`) over the defaults above, checked
    when the shape is built and stored as sorted (name, value) pairs.
    """

    model: MechanicalSystem
    intervals: int = 10
    duration: float = 1.0
    tol: float = 1e-12
    max_iter: int = 500
    solver: str = AUTO_SOLVER
    kkt_tol: float = 1e-10
    keep_out_slots: int = 0
    keep_out_positions: tuple[int, ...] = ()
    control_bounds: tuple[tuple[float, float], ...] | None = None
    path_constraints: tuple[PathConstraint | CompiledConstraint, ...] = ()
    running_cost: Callable[..., Any] | CompiledFunction | None = None
    obstacles: tuple[Obstacle, ...] = ()
    obstacle_positions: tuple[int, ...] = ()
    elastic: bool = False
    free_duration: bool = False
    time_weight: float = 0.0
    time_bounds: tuple[float, float] | None = None
    solver_options: SolverOptions = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", solver_options(self.solver_options))
        nq, nu = self.model.nq, self.model.nu
        sizes = {"q": nq, "v": nq, "u": nu}
        object.__setattr__(self, "path_constraints", compile_constraints(
            self.path_constraints, sizes))
        if self.running_cost is not None:
            object.__setattr__(self, "running_cost", compile_function(
                self.running_cost, sizes, "running_cost", "running_cost", scalar=True))
        if self.control_bounds is not None:
            object.__setattr__(self, "control_bounds",
                               check_control_bounds(self.control_bounds, self.model.nu))
        if self.intervals < 1:
            raise ValueError(f"DMOC needs at least 1 interval, got {self.intervals}")
        if not self.duration > 0:
            raise ValueError(f"DMOC duration must be > 0, got {self.duration}")
        if self.solver not in (AUTO_SOLVER, *SOLVERS):
            raise ValueError(f"unknown DMOC solver {self.solver!r}; choose one of "
                             f"{AUTO_SOLVER}, {', '.join(SOLVERS)}")
        if self.keep_out_slots < 0:
            raise ValueError(f"keep_out_slots must be ≥ 0, got {self.keep_out_slots}")
        positions = self.keep_out_positions
        if self.keep_out_slots and not (
                positions and len(set(positions)) == len(positions)
                and all(0 <= i < self.model.nq for i in positions)):
            raise ValueError(f"keep_out_positions must be distinct entries of the "
                             f"{self.model.nq} configuration entries, got {positions}")
        if not self.keep_out_slots and positions:
            raise ValueError("keep_out_positions needs keep_out_slots > 0")
        if self.keep_out_slots and self.solver == "newton":
            raise ValueError("keep-out half-spaces are inequalities: the newton solver takes "
                             "equalities only; choose sqpmethod, ipopt or auto (the default)")
        if self.path_constraints and self.solver == "newton":
            raise ValueError("solver: path constraints are inequalities and the newton solver "
                             "takes equalities only; choose sqpmethod, ipopt or auto (the default)")
        self._check_obstacles()
        if self.free_duration and self.keep_out_slots:
            raise ValueError("free_duration: not with keep-out slots (their penalty is the "
                             "last parameter)")
        self._check_time()
        if self.free_duration and getattr(self.model, "time_dependent", False):
            raise ValueError("free_duration: the model is time dependent (tabulated on its "
                             "intervals of one T)")
        if self.elastic and (self.keep_out_slots or self.solver == "newton"):
            raise ValueError("elastic: needs a shape without keep-out slots, solved by "
                             "sqpmethod, ipopt or auto (slacks are inequalities)")
        model_intervals = getattr(self.model, "intervals", None)
        if model_intervals is not None and model_intervals != self.intervals:
            raise ValueError(f"the model is tabulated on {model_intervals} intervals, the "
                             f"DMOC shape has {self.intervals}")

    def _check_time(self) -> None:
        """``time_bounds`` and ``time_weight`` (:func:`~ocpar.ocp.duration.check_time_fields`)
        and what T as a variable does not go with, or ValueError naming the field."""
        bounds = check_time_fields(self.free_duration, self.time_bounds, self.time_weight)
        object.__setattr__(self, "time_bounds", bounds)
        if bounds is not None and (self.keep_out_slots or self.elastic
                                   or self.solver == "newton"
                                   or getattr(self.model, "time_dependent", False)):
            raise ValueError("time_bounds: not with free_duration, keep-out slots, elastic, "
                             "the newton solver (T's bounds are inequalities) or a "
                             "time-dependent model")

    def _check_obstacles(self) -> None:
        """``obstacles`` (a tuple of obstacles of one dimension d ≤ nq) and
        ``obstacle_positions`` (d distinct configuration entries, default the first d), or
        ValueError naming the field."""
        if not self.obstacles:
            if self.obstacle_positions:
                raise ValueError("obstacle_positions needs obstacles")
            return
        first = self.obstacles[0] if isinstance(self.obstacles, tuple | list) else None
        dim = getattr(first, "dim", 0)
        object.__setattr__(self, "obstacles", check_obstacles(self.obstacles, dim))
        positions = tuple(self.obstacle_positions) or tuple(range(dim))
        if not (len(positions) == dim <= self.model.nq and len(set(positions)) == dim
                and all(isinstance(i, int | np.integer) and 0 <= i < self.model.nq
                        for i in positions)):
            raise ValueError(f"obstacle_positions: must be {dim} distinct entries of the "
                             f"{self.model.nq} configuration entries, got {positions}")
        object.__setattr__(self, "obstacle_positions", tuple(int(i) for i in positions))
        if self.solver == "newton":
            raise ValueError("solver: obstacles are inequalities and the newton solver takes "
                             "equalities only; choose sqpmethod, ipopt or auto (the default)")

    @property
    def chosen_solver(self) -> str:
        """The solver this shape's NLPs are solved with: ``solver``, or for ``auto``
        ``newton`` where the NLP has equalities only and ``sqpmethod`` where it has
        inequalities (control bounds, path constraints, obstacles); ``ipopt`` with keep-out
        slots, their tasks batched by :class:`~ocpar.ocp.convex_qp.ConvexQp` first where
        the NLP is a convex QP (``DmocTranscription.keep_out_qp``)."""
        if self.solver != AUTO_SOLVER:
            return self.solver
        if self.keep_out_slots:
            return "ipopt"
        return "sqpmethod" if self.has_inequalities else "newton"

    @property
    def has_inequalities(self) -> bool:
        """Whether the NLP has inequalities (control bounds, path constraints, keep-out
        slots, obstacles, T's bounds, an elastic problem's slacks)."""
        return bool(self.control_bounds is not None or self.path_constraints
                    or self.keep_out_slots or self.obstacles or self.elastic
                    or self.time_bounds is not None)

    def solver_settings(self) -> dict[str, dict]:
        """The options this shape's solvers are built with (defaults and the shape's
        ``solver_options``), by solver: ``ipopt`` (``nlpsol``'s) and the batched solver's,
        ``newton`` (``kkt_tol``, ``max_iter``: Newton steps at most) or ``sqpmethod``."""
        given = self.solver_options
        # IPOPT relaxes inequalities by 1e-8 (relative) unless told not to: a keep-out and a
        # control bound are exact
        exact = {"bound_relax_factor": 0.0} if self.has_inequalities else {}
        settings = {"ipopt": ipopt(given, self.tol, self.max_iter, **exact)}
        if self.chosen_solver == "newton":
            settings["newton"] = {
                "kkt_tol": newton(given, "kkt_tol", self.kkt_tol),
                "max_iter": newton(given, "max_iter", min(NEWTON_ROUNDS, self.max_iter))}
        elif self.chosen_solver == "sqpmethod":
            settings["sqpmethod"] = sqpmethod(given, sqp_options(self.kkt_tol, self.max_iter))
        return settings

    @property
    def resolves_from_previous(self) -> bool:
        """Whether an agent that re-solves this shape (a later superstep, its end moved)
        starts from its previous solution (:func:`~ocpar.ocp.endpoint_agents.solve_agents`):
        with ellipsoid obstacles, whose side a cold start finds by solving from each side
        (:meth:`DmocTranscription.start_guesses`). Otherwise from the default guess, as
        of old."""
        return bool(ellipsoids(self.obstacles))

    @property
    def n_keep_out(self) -> int:
        """Length of the keep-out block of p: N K (d + 2), then ρ (module docstring)."""
        if not self.keep_out_slots:
            return 0
        return self.intervals * self.keep_out_slots * (len(self.keep_out_positions) + 2) + 1

    @property
    def n_params(self) -> int:
        """Length of p: the boundary data (q_0, q̇_0, q_N, q̇_N), then the keep-out block,
        then T where the duration is free."""
        return 4 * self.model.nq + self.n_keep_out + int(self.free_duration)

    def with_duration(self, duration: float) -> DmocShape:
        """This shape over the horizon ``duration`` (the model's time unit)."""
        return over_duration(self, duration)

    # the agent-shape interface of :mod:`ocpar.ocp.endpoint_agents`

    @property
    def boundary_size(self) -> int:
        """Entries of each boundary state in p = (start, end, …): (q, q̇), 2 nq."""
        return 2 * self.model.nq

    @property
    def node_size(self) -> int:
        """Entries of a node of the returned path ``q``: the configuration's nq."""
        return self.model.nq

    def end_position_entries(self, d: int) -> np.ndarray:
        """The entries of the end state (and of ``end_hessian``'s rows) a d-dimensional
        target fixes: the first d of q_N."""
        return np.arange(d)

    def previous_guesses(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The guesses (k, inner nodes and controls) that re-solve from node paths
        q (k, N+1, nq) and controls u (k, N, nu)."""
        k, nodes, nq = q.shape
        inner = (nodes - 2) * nq
        guesses = np.empty((k, inner + int(np.prod(u.shape[1:]))))
        guesses[:, :inner].reshape(k, nodes - 2, nq)[:] = q[:, 1:-1]  # a view: no copy first
        guesses[:, inner:] = u.reshape(k, guesses.shape[1] - inner)
        return guesses

    def build(self) -> DmocTranscription:
        """The transcription of this shape (see :func:`~ocpar.ocp.transcription`); with a
        free duration the one of every duration (that of ``duration`` 1)."""
        return build_at_unit_duration(self, DmocTranscription)


@dataclass
class DmocSolution(InnerSolution):
    """Result of one DMOC solve: the common fields, and ``cost_gradient`` dJ*/dp (n_params,
    from the NLP multipliers); ``end_hessian`` d²J*/dq_N² (nq, nq, from the KKT system,
    :mod:`ocpar.ocp.sensitivity`; NaN for a shape with keep-out slots; with a free duration
    (nq + 1, nq + 1) over (q_N, T)); ``duration`` T (the shape's, the parameter's, or the
    one the task chose: ``time_bounds``); ``q`` the node path
    (N+1, nq); ``u`` the interval controls (N, nu)."""

    cost_gradient: np.ndarray
    end_hessian: np.ndarray
    q: np.ndarray
    u: np.ndarray
    duration: float


class DmocTranscription:
    """The DMOC NLP of one shape, as CasADi functions of (w, p), plus its solvers (IPOPT one
    task at a time, :class:`~ocpar.ocp.batch.MappedNlp` for batches).

    A guess is w = (q_1..q_{N−1}, u_0..u_{N−1}, λ_0..λ_N) or w without its λ block (then
    λ = 0), e.g. a previous solution's inner nodes and controls."""

    def __init__(self, shape: DmocShape) -> None:
        self.shape = shape
        self._maps: dict[tuple[str, int], ca.Function] = {}
        model, n = shape.model, shape.intervals
        nq, nu = model.nq, model.nu
        p = ca.SX.sym("p", shape.n_params)
        timed = shape.time_bounds is not None
        t_var = ca.SX.sym("T", int(timed))
        #: T: a variable (time bounds), the last parameter (free duration) or the constant
        self.horizon = t_var[0] if timed else p[-1] if shape.free_duration else shape.duration
        h = self.horizon / n
        self.nq, self.nu, self.n = nq, nu, n
        #: rows and columns of ``end_hessian``: q_N's (and T's, where free) entries of p
        self.nh = nq + int(shape.free_duration)

        a, b = ca.SX.sym("a", nq), ca.SX.sym("b", nq)
        q, v, u = ca.SX.sym("q", nq), ca.SX.sym("v", nq), ca.SX.sym("u", nu)
        # one discrete Lagrangian per interval for time-dependent systems, else one for all
        intervals = range(n) if getattr(model, "time_dependent", False) else [0]
        d1ld, d2ld = {}, {}
        step = ca.SX.sym("h")   # the step, an input: a parameter where T is free
        for k in intervals:
            ld = step * ca.substitute(model.lagrangian(q, v, k), ca.vertcat(q, v),
                                      ca.vertcat((a + b) / 2, (b - a) / step))
            d1ld[k] = ca.Function(f"D1Ld_{k}", [a, b, step], [ca.gradient(ld, a)])
            d2ld[k] = ca.Function(f"D2Ld_{k}", [a, b, step], [ca.gradient(ld, b)])
        d1 = [_at_step(d1ld.get(k, d1ld[0]), h) for k in range(n)]
        d2 = [_at_step(d2ld.get(k, d2ld[0]), h) for k in range(n)]
        start_momentum = ca.Function("D2L_0", [q, v], [ca.gradient(model.lagrangian(q, v, 0), v)])
        end_momentum = ca.Function(
            "D2L_N", [q, v], [ca.gradient(model.lagrangian(q, v, max(intervals)), v)])
        force = ca.Function("F", [q, u], [model.generalized_force(q, u)])
        nc = getattr(model, "n_constraints", 0)
        self.nc = nc

        q0, v0, qn, vn = (p[i * nq : (i + 1) * nq] for i in range(4))
        # the elastic problem's end slacks (a⁺, a⁻, b⁺, b⁻): the end it reaches
        end_slack = ca.SX.sym("end_slack", 4 * nq if shape.elastic else 0)
        if shape.elastic:
            qn = qn + end_slack[:nq] - end_slack[nq:2 * nq]
            vn = vn + end_slack[2 * nq:3 * nq] - end_slack[3 * nq:]
        q_inner = ca.SX.sym("q_inner", nq * (n - 1))
        u_all = ca.SX.sym("u", nu * n)
        lam = ca.SX.sym("lambda", nc * (n + 1))
        qs = [q0] + [q_inner[k * nq : (k + 1) * nq] for k in range(n - 1)] + [qn]
        us = [u_all[k * nu : (k + 1) * nu] for k in range(n)]
        f_half = [0.5 * h * force((qs[k] + qs[k + 1]) / 2, us[k]) for k in range(n)]
        if nc:
            c = ca.Function("c", [q], [model.constraints(q)])
            grad_c = ca.Function("Gt", [q], [ca.jacobian(model.constraints(q), q).T])
            react = [grad_c(qs[k]) @ lam[k * nc : (k + 1) * nc] for k in range(n + 1)]
        else:
            react = [ca.SX.zeros(nq)] * (n + 1)

        eqs = [start_momentum(q0, v0) + d1[0](qs[0], qs[1]) + f_half[0] + react[0]]
        eqs += [
            d2[k - 1](qs[k - 1], qs[k]) + d1[k](qs[k], qs[k + 1]) + f_half[k - 1] + f_half[k]
            + react[k]
            for k in range(1, n)
        ]
        eqs.append(-end_momentum(qn, vn) + d2[n - 1](qs[n - 1], qs[n]) + f_half[n - 1] + react[n])
        if nc:
            eqs += [c(qs[k]) for k in range(1, n)]
        if nc and shape.elastic:   # the slackened end stays on c(q) = 0 (module docstring)
            eqs.append(c(qs[n]))
        slack = ca.SX.sym("slack", n * shape.keep_out_slots)
        keep_out = self._keep_out_rows(p[4 * nq:], qs, slack)
        # each interval's midpoint configuration, discrete velocity and control (built only
        # for a running cost or path constraints: ~7 ms of a point mass's build otherwise)
        midpoints = ([{"q": (qs[k] + qs[k + 1]) / 2, "v": (qs[k + 1] - qs[k]) / h, "u": us[k]}
                      for k in range(n)]
                     if shape.running_cost is not None or shape.path_constraints else [])
        path = ConstraintRows()
        for constraint in shape.path_constraints:
            path.add(constraint, midpoints if constraint.depends_on("v", "u")
                     else [{"q": qs[k]} for k in range(1, n)])
        control_cost = (h * ca.sumsqr(u_all) if shape.running_cost is None else
                        h * ca.sum1(ca.vertcat(*[shape.running_cost(m) for m in midpoints])))
        #: J_d without the keep-out penalty, of the path and controls (q_1..q_{N−1}, u) and p
        # (and T where it is a variable: a shape with time bounds has no keep-outs to use it)
        self.control_cost = ca.Function("Jd", [ca.vertcat(q_inner, u_all, t_var), p],
                                        [control_cost])
        penalty = p[-1] * ca.sum1(slack) if shape.keep_out_slots else 0

        #: The obstacles' planes (N m_e d: interval by interval, ellipsoid by ellipsoid).
        balls = ellipsoids(shape.obstacles)
        planes = ca.SX.sym("planes", n * len(balls) * len(shape.obstacle_positions))
        obstacle = obstacle_rows(shape.obstacles, [q[list(shape.obstacle_positions)]
                                                   for q in qs], planes)
        rows = ca.vertcat(path.expr, *obstacle)
        row_lower = np.concatenate([path.lower, np.zeros(len(obstacle))])
        row_upper = np.concatenate([path.upper, np.full(len(obstacle), np.inf)])
        self.u_lower, self.u_upper = (np.array(bound) for bound in zip(
            *(shape.control_bounds or [(-np.inf, np.inf)] * nu), strict=True))
        if shape.elastic:   # the path rows and control bounds elastic (module docstring)
            bounded = shape.control_bounds is not None
            row_slack = ca.SX.sym("row_slack", path.count)
            u_slack = ca.SX.sym("u_slack", nu * n if bounded else 0)
            elastic = ca.vertcat(end_slack, u_slack, row_slack)
            none, free = np.full(path.count, -np.inf), np.full(path.count, np.inf)
            rows = ca.vertcat(path.expr + row_slack, path.expr - row_slack, *obstacle,
                              *([u_all + u_slack, u_all - u_slack] if bounded else []))
            u_lower, u_upper = np.tile(self.u_lower, n), np.tile(self.u_upper, n)
            row_lower = np.concatenate([path.lower, none, np.zeros(len(obstacle)),
                                        *([u_lower, np.full(n * nu, -np.inf)] if bounded
                                          else [])])
            row_upper = np.concatenate([free, path.upper, np.full(len(obstacle), np.inf),
                                        *([np.full(n * nu, np.inf), u_upper] if bounded
                                          else [])])
            objective = ca.dot(self._slack_weights(path), elastic)
        else:
            elastic = ca.SX.sym("elastic", 0)
            objective = control_cost + penalty + (shape.time_weight * self.horizon if timed
                                                  else 0)
        w = ca.vertcat(q_inner, u_all, lam, slack, elastic, t_var, planes)
        #: T's entry of w (time bounds), else None
        self.t_index = w.numel() - planes.numel() - 1 if timed else None
        self.nw = w.numel()
        self.n_params = shape.n_params
        n_eq = nq * (n + 1) + nc * (n - 1 + bool(shape.elastic))
        self.n_path = path.count
        #: Inequality rows after the equations and keep-outs: the path rows, the obstacles'
        #: (elastic: each with its slack, as lower and upper rows, then the control bounds').
        self.n_rows = rows.numel()
        self.n_planes = planes.numel()
        self.ng = n_eq + len(keep_out) + self.n_rows
        #: Constraint bounds: the equations = 0, the keep-out rows ≥ 0, the path rows',
        #: the obstacle rows ≥ 0.
        self.lbg = np.concatenate([np.zeros(n_eq + len(keep_out)), row_lower])
        self.ubg = np.concatenate([np.zeros(n_eq), np.full(len(keep_out), np.inf), row_upper])
        #: Variable bounds: the controls within ``control_bounds`` (elastic: free), the
        #: slacks ≥ 0, the rest free.
        n_path = q_inner.numel()
        u_lower, u_upper = ((np.full(n * nu, -np.inf), np.full(n * nu, np.inf))
                            if shape.elastic else
                            (np.tile(self.u_lower, n), np.tile(self.u_upper, n)))
        t_lower, t_upper = shape.time_bounds or (None, None)
        self.lbx = np.concatenate([np.full(n_path, -np.inf), u_lower,
                                   np.full(lam.numel(), -np.inf),
                                   np.zeros(slack.numel() + elastic.numel()),
                                   np.full(t_var.numel(), t_lower or 0.0),
                                   np.full(planes.numel(), -np.inf)])
        self.ubx = np.concatenate([np.full(n_path, np.inf), u_upper,
                                   np.full(lam.numel() + slack.numel() + elastic.numel(),
                                           np.inf),
                                   np.full(t_var.numel(), t_upper or 0.0),
                                   np.full(planes.numel(), np.inf)])
        self.cost = ca.Function("J", [w, p], [objective], ["w", "p"], ["J"])
        self.constraints = ca.Function("g", [w, p], [ca.vertcat(*eqs, *keep_out, rows)],
                                       ["w", "p"], ["g"])
        self._w, self._p = w, p
        # d²J*/dq_N² from the KKT system holds for equalities only: none with keep-outs; with
        # path constraints that of the equations, valid while no path row is active
        # (the equations through a Function call, as the rows of g: the evaluation graph of
        # old, ~25 % faster to evaluate than the bare expressions)
        # (the planes' variables are free where no row binds them: that of the equations is
        # singular there, every solve's comes from the active set, NaN until then)
        equations = self._equations = ca.Function("g_eq", [w, p], [ca.vertcat(*eqs)])
        self.end_hessian = None if shape.keep_out_slots or shape.elastic else ca.Function(
            "dmoc_no_hessian", [w, ca.SX.sym("lam_g", self.ng), p],
            [ca.DM(np.full((self.nh, self.nh), np.nan))]) if self.n_planes else \
            _on_equations(cost_hessian_function(
                "dmoc", w, p, self.cost(w, p), equations(w, p), self.hessian_block), self.ng)
        # with control bounds or path rows, that of the active set where one is active
        self.active_hessian = None if (shape.keep_out_slots or shape.elastic
                                       or not self.has_inequalities) else \
            cost_hessian_function("dmoc", w, p, self.cost(w, p), self.constraints(w, p),
                                  self.hessian_block, active_set=True)
        self.path_rows = ca.Function("path", [w, p], [path.expr], ["w", "p"], ["c"])
        self.obstacle_rows = ca.Function("obstacle", [w, p], [ca.vertcat(*obstacle)],
                                         ["w", "p"], ["c"])

    @property
    def hessian_block(self) -> list[int]:
        """The entries of p ``end_hessian`` covers: q_N's, then T's where it is free."""
        nq = self.nq
        return list(range(2 * nq, 3 * nq)) + ([self.n_params - 1] if self.shape.free_duration
                                              else [])

    def _slack_weights(self, path: ConstraintRows) -> ca.SX:
        """The elastic cost's weight of each slack (module docstring): 1 per length unit of
        the end position (a±), T per velocity unit of the end velocity (b±), 1 / (the
        bound's size) per unit of a control bound's and a path row's slack (the size
        max(|lo|, |hi|) over its finite bounds, 1 where that is 0)."""
        nq, n = self.nq, self.n
        parts = [ca.DM.ones(2 * nq), self.horizon * ca.DM.ones(2 * nq)]
        if self.shape.control_bounds is not None:
            parts.append(ca.DM(np.tile(1 / bound_sizes(self.u_lower, self.u_upper), n)))
        parts.append(ca.DM(1 / bound_sizes(path.lower, path.upper)))
        return ca.vertcat(*parts)

    def _keep_out_rows(self, data: ca.SX, qs: list[ca.SX], slack: ca.SX) -> list[ca.SX]:
        """n·r(q) − b + σ at the free nodes q of each interval k, slot s (b the slot's offset
        at that node), from the keep-out block ``data`` of p and the slacks (module
        docstring)."""
        shape = self.shape
        return keep_out_rows(data, qs, 1, self.n, shape.keep_out_slots,
                             list(shape.keep_out_positions), slack)

    @property
    def first_duration(self) -> float:
        """The first guess of T where it is a variable: ``duration`` within the bounds."""
        low, high = self.shape.time_bounds or (-np.inf, np.inf)
        return float(np.clip(self.shape.duration, low, high))

    def durations(self, w: np.ndarray, params: np.ndarray) -> np.ndarray:
        """T of each solution w (k, nw) with ``params`` (k, n_params): (k,)."""
        if self.t_index is not None:
            return np.asarray(w, float)[:, self.t_index]
        if self.shape.free_duration:
            return np.asarray(params, float)[:, -1].copy()
        return np.full(len(w), self.shape.duration)

    def steps(self, params: np.ndarray) -> np.ndarray | float:
        """The step h = T/N of each row of ``params`` (k, n_params): (k,) with a free
        duration, else the shape's constant."""
        if self.shape.free_duration:
            return np.asarray(params, float)[:, -1] / self.n
        return self.shape.duration / self.n

    def _costs(self, w: np.ndarray, params: np.ndarray, u: np.ndarray) -> np.ndarray:
        """J_d without the keep-out penalty of each solution w (k, nw) with ``params``
        (k, n_params) and its controls u (k, N, nu): (k,)."""
        if self.shape.running_cost is None:
            return self.steps(params) * np.sum(u**2, axis=(1, 2))
        n_free = self.nq * (self.n - 1) + self.nu * self.n
        return np.asarray(self.control_cost.map(len(w))(w[:, :n_free].T, params.T)).ravel()

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape, built on first use and then reused."""
        w, p = self._w, self._p
        nlp = {"x": w, "p": p, "f": self.cost(w, p), "g": self.constraints(w, p)}
        return ca.nlpsol("dmoc", "ipopt", nlp, self.solver_settings["ipopt"])

    @cached_property
    def solver_settings(self) -> dict[str, dict]:
        """:meth:`DmocShape.solver_settings`, once."""
        return self.shape.solver_settings()

    @cached_property
    def kkt_residuals(self) -> ca.Function:
        """(w, p, λ_g, λ_x) ↦ the KKT residuals (:func:`~ocpar.ocp.batch.kkt_residuals`)."""
        w, p = self._w, self._p
        return kkt_residuals("dmoc", w, p, self.cost(w, p), self.constraints(w, p))

    def _checked(self, call: NlpCall, params: np.ndarray) -> NlpCall:
        """``call`` (an IPOPT solve at ``params``), counted a success where IPOPT stopped at
        rounding (:data:`ROUNDING_STOPS`: its scaled tolerance out of reach, e.g. costs of
        1e5 at ``tol`` 1e-12) and the returned point meets the KKT conditions to ``kkt_tol``,
        the batched solvers' own test (:func:`~ocpar.ocp.batch.kkt_met`)."""
        if call.success or call.out is None or call.status not in ROUNDING_STOPS:
            return call
        w, lam_g, lam_x = (np.asarray(call.out[k]).ravel() for k in ("x", "lam_g", "lam_x"))
        g, stationarity, gradient = (np.asarray(r).ravel()
                                     for r in self.kkt_residuals(w, params, lam_g, lam_x))
        bounds = (self.lbg, self.ubg, *((self.lbx, self.ubx) if self.has_inequalities
                                       else (-np.inf, np.inf)))
        if kkt_met(w[None], params[None], lam_g[None], lam_x[None], g[None], stationarity,
                   gradient, bounds, self.shape.kkt_tol)[0]:
            call.success = True
            call.status += " (KKT check met)"
        return call

    @property
    def has_inequalities(self) -> bool:
        """Whether the NLP has inequalities (:attr:`DmocShape.has_inequalities`)."""
        return self.shape.has_inequalities

    def _activity(self, w: np.ndarray, params: np.ndarray, lam_g: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The activity mask (k, ng + nw) of solutions w (k, nw) with ``params``
        (k, n_params) and multipliers ``lam_g`` (k, ng): 1 for the equations, for path and
        obstacle rows and controls at a bound (to within ``kkt_tol`` relative; an ellipsoid's
        rows also where they carry a multiplier above ``kkt_tol`` of the largest) and for the
        planes no obstacle row binds (frozen), 0 elsewhere (:mod:`ocpar.ocp.sensitivity`);
        and w with its planes made canonical (:func:`~ocpar.ocp.obstacles.canonical_planes`),
        where the mask holds."""
        k, n_eq, tol = len(w), self.ng - self.n_rows, self.shape.kkt_tol
        mask = np.zeros((k, self.ng + self.nw))
        mask[:, :n_eq] = 1.0
        if self.n_path:
            rows = np.asarray(self.path_rows.map(k)(w.T, params.T)).reshape(self.n_path, k).T
            end = n_eq + self.n_path
            mask[:, n_eq:end] = _near(rows, self.lbg[n_eq:end], self.ubg[n_eq:end], tol)
        if self.shape.control_bounds is not None or self.t_index is not None:
            mask[:, self.ng:] = _near(w, self.lbx, self.ubx, tol)
        if self.n_rows > self.n_path:
            w = w.copy()
            q, _ = self.unpack_many(w, params)
            start = n_eq + self.n_path
            ellipsoid_rows = lam_g[:, start:start + 3 * self.n_planes
                                   // len(self.shape.obstacle_positions)]
            loaded = np.abs(ellipsoid_rows) > tol * (1 + np.max(np.abs(lam_g), axis=1,
                                                                  keepdims=True))
            planes, binding, frozen = canonical_planes(
                self.shape.obstacles, q[..., list(self.shape.obstacle_positions)], tol, loaded)
            w[:, self.nw - self.n_planes:] = planes
            rows = np.asarray(self.obstacle_rows.map(k)(w.T, params.T)).reshape(-1, k).T
            mask[:, start:self.ng] = _near(rows, 0.0, np.inf, tol)
            mask[:, start:start + binding.shape[1]] = binding
            mask[:, self.ng + self.nw - self.n_planes:] = frozen
        return mask, w

    def _hessians(self, w: np.ndarray, lam_g: np.ndarray, params: np.ndarray,
                  equality: np.ndarray) -> np.ndarray:
        """``end_hessian`` of solutions w (k, nw) with multipliers ``lam_g`` (k, ng): that of
        the equations, ``equality`` (k, nh, nh), where no inequality is active, else that
        of the active set (:mod:`ocpar.ocp.sensitivity`)."""
        if self.active_hessian is None:
            return equality
        mask, w = self._activity(w, params, lam_g)
        finite = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(lam_g), axis=1)
        # with planes every solve's: their variables are free where no row binds them
        active = np.flatnonzero((mask[:, self.ng - self.n_rows:].any(axis=1)
                                 | bool(self.n_planes)) & finite)
        hessians = equality.copy()
        hessians[~finite] = np.nan
        if not len(active):
            return hessians
        try:   # one mapped call, each column computed as alone
            value = np.asarray(self._mapped("active_hessian", len(active))(
                w[active].T, lam_g[active].T, params[active].T, mask[active].T))
            hessians[active] = value.reshape(self.nh, len(active), self.nh).transpose(1, 0, 2)
            return hessians
        except RuntimeError:
            pass
        for k in active:  # one call each: a singular active set fails alone (NaN)
            try:
                hessians[k] = np.asarray(self.active_hessian(w[k], lam_g[k], params[k], mask[k]))
            except RuntimeError:
                hessians[k] = np.nan
        return hessians

    def _mapped(self, name: str, columns: int) -> ca.Function:
        """This transcription's Function attribute ``name`` mapped over ``columns`` columns
        (serially), built once per (name, columns)."""
        key = (name, columns)
        if key not in self._maps:
            self._maps[key] = getattr(self, name).map(columns, "serial")
        return self._maps[key]

    @property
    def batches(self) -> bool:
        """Whether :meth:`solve_batch` solves (its ``solver`` is not ``ipopt``, or it has
        :attr:`keep_out_qp`)."""
        return self.shape.chosen_solver != "ipopt" or self.keep_out_qp is not None

    @cached_property
    def keep_out_qp(self) -> ConvexQp | None:
        """The batched interior-point solver of a keep-out shape's NLP under the ``auto``
        solver where it is a convex QP (e.g. a point mass; None otherwise: IPOPT)."""
        shape = self.shape
        if shape.solver != AUTO_SOLVER or not shape.keep_out_slots or self.n_planes:
            return None
        w, p = self._w, self._p
        return ConvexQp.of("dmoc_qp", w, p, self.cost(w, p), self.constraints(w, p),
                           (self.lbg, self.ubg, self.lbx, self.ubx), shape.tol, shape.kkt_tol)

    @cached_property
    def batch_solver(self) -> KktNewton | MappedNlp | ConvexQp | None:
        """The batched solver of this shape's NLP (:attr:`keep_out_qp` where there is one;
        None when its ``solver`` is ``ipopt``, or with planes: their tasks are solved by
        :attr:`without_obstacles` and :attr:`segment_nlp`)."""
        if self.keep_out_qp is not None:
            return self.keep_out_qp
        w, p = self._w, self._p
        if self.shape.chosen_solver == "newton":  # DmocShape refuses it with keep-out slots
            return KktNewton("dmoc", w, p, self.cost(w, p), self.constraints(w, p), 1,
                             self.solver_settings["newton"]["kkt_tol"], post=self.end_hessian,
                             shared_post=self._shared_end_hessian)
        if self.shape.chosen_solver != "sqpmethod" or self.n_planes:
            return None
        return MappedNlp("dmoc_sqp", w, p, self.cost(w, p), self.constraints(w, p),
                         self.shape.kkt_tol, self.shape.max_iter, self.shape.kkt_tol,
                         post=self.end_hessian, options=self.shape.solver_options)

    def _shared_end_hessian(self, columns: int) -> ca.Function:
        """:attr:`end_hessian` of ``columns`` solutions at once whose KKT matrix is the same
        (:func:`~ocpar.ocp.sensitivity.shared_cost_hessian_function`; the Newton kernel's
        columns of a common T, :class:`~ocpar.ocp.batch.KktNewton`)."""
        w, p = self._w, self._p
        return _on_equations(shared_cost_hessian_function(
            "dmoc", w, p, self.cost(w, p), self._equations(w, p), self.hessian_block, columns),
            self.ng, columns)

    def default_guess(self, params: np.ndarray) -> np.ndarray:
        """Cubic Hermite path through the boundary data (projected onto the constraints, if
        any), zero controls and multipliers (the double integrator's minimum-energy path for a
        point mass)."""
        return self.default_guesses(np.asarray(params, float)[None])[0]

    def default_guesses(self, params: np.ndarray) -> np.ndarray:
        """:meth:`default_guess` of each row of ``params`` (k, 4 nq): (k, nw)."""
        nq, n, k = self.nq, self.n, len(params)
        # agents along the last axis: (node, entry, agent), each product contiguous
        q0, v0, qn, vn = np.ascontiguousarray(params[:, :4 * nq].T).reshape(4, 1, nq, k)
        s = np.arange(1, n)[:, None, None] / n
        t = params[:, -1] if self.shape.free_duration else self.first_duration
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        path = h00 * q0 + h10 * t * v0 + h01 * qn + h11 * t * vn   # (N−1, nq, k)
        guesses = np.zeros((k, self.nw))
        inner = (n - 1) * nq
        guesses[:, :inner] = path.reshape(inner, k).T
        if self.nc:
            guesses[:, :inner] = self.shape.model.project(
                guesses[:, :inner].reshape(-1, nq)).reshape(k, inner)
        if self.t_index is not None:
            guesses[:, self.t_index] = self.first_duration
        return self._with_planes(guesses, params)

    def _with_planes(self, guesses: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``guesses`` (k, nw) with each interval's planes the nearest-point directions of
        their paths (:func:`~ocpar.ocp.obstacles.guess_planes`; none without ellipsoids)."""
        if self.n_planes:
            q, _ = self.unpack_many(guesses, params)
            guesses[:, self.nw - self.n_planes:] = guess_planes(
                self.shape.obstacles, q[..., list(self.shape.obstacle_positions)])
        return guesses

    def side_guesses(self, guess: np.ndarray, params: np.ndarray) -> np.ndarray:
        """The guesses (m, nw) of each side of the ellipsoids the path of ``guess`` (nw,)
        enters, with ``params`` (n_params,) (:func:`~ocpar.ocp.obstacles.side_guesses`; the
        guess alone if it enters none or the shape has no planes)."""
        if not self.n_planes:
            return guess[None]
        q, _ = self.unpack(guess, params)
        positions = list(self.shape.obstacle_positions)
        rows = []
        for path, planes in side_guesses(self.shape.obstacles, q[:, positions]):
            row = guess.copy()
            inner = q[1:-1].copy()
            inner[:, positions] = path[1:-1]
            row[:inner.size] = inner.ravel()
            row[self.nw - self.n_planes:] = planes
            rows.append(row)
        return np.array(rows)

    def start_guesses(self, guess: np.ndarray | None, base: Callable[[], np.ndarray],
                      params: np.ndarray) -> np.ndarray:
        """The guesses (m, nw) a solve with ``params`` (n_params,) starts from. Without
        ``guess``: each side of the ellipsoids the path of ``base()`` (nw,) enters
        (:meth:`side_guesses`). With one (e.g. the agent's previous solution): the guess
        (:meth:`full_guess`) alone where it passes every ellipsoid the path of ``base()``
        enters on the side of that path's nearest point
        (:func:`~ocpar.ocp.obstacles.on_near_side`), else the guess and then each side of
        ``base()`` (the far side only where the guess is not on the near one). A batch
        solves the far ones only where they can be cheaper (:meth:`_in_two_rounds`); IPOPT
        (:meth:`solve`) all of them."""
        return self._candidates(guess, base, params)[0]

    def _candidates(self, guess: np.ndarray | None, base: Callable[[], np.ndarray],
                    params: np.ndarray) -> tuple[np.ndarray, list[tuple[tuple[int, np.ndarray],
                                                                        ...]]]:
        """:meth:`start_guesses` and, for each, the ellipsoids it passes on the far side of
        the path of ``base()``: (index among the ellipsoids, the unit direction (d,) in the
        scaled space of that path's point nearest the centre) pairs, () on the near side."""
        if guess is not None:
            warm = self.full_guess(guess, params)
            if not self.n_planes:
                return warm[None], [()]
        reference = base()
        if not self.n_planes:
            return self.side_guesses(reference, params), [()]
        positions = list(self.shape.obstacle_positions)
        q_base, _ = self.unpack(reference, params)
        hits = entered(self.shape.obstacles, q_base[:, positions])
        signs = list(itertools.product((1.0, -1.0), repeat=min(len(hits), SIDE_OBSTACLES)))
        far = [tuple(hit for hit, sign in zip(hits, row, strict=False) if sign < 0)
               for row in signs] if hits else [()]
        if guess is None:
            return self.side_guesses(reference, params), far
        q_warm, _ = self.unpack(warm, params)
        if on_near_side(self.shape.obstacles, q_base[:, positions], q_warm[:, positions]):
            return warm[None], [()]
        balls = ellipsoids(self.shape.obstacles)
        warm_far = tuple((e, d) for e, d in hits if not on_near_side(
            (balls[e],), q_base[:, positions], q_warm[:, positions]))
        return (np.vstack([warm[None], self.side_guesses(reference, params)]),
                [warm_far, *far])

    @cached_property
    def _quadratic_core(self) -> tuple[DmocTranscription, np.ndarray] | None:
        """Where this shape's NLP without obstacles, control bounds and path constraints is
        a QP with constant Hessian H and constraint Jacobian A in w (linear dynamics and a
        quadratic cost: point masses): its transcription and the blocks (N−1, d, d) of
        M = the w block of [[H, Aᵀ], [A, 0]]⁻¹ at each inner node's obstacle positions. On
        that NLP's feasible set J(w) = J* + ½ (w − w*)ᵀ H (w − w*), so the least cost with
        a linear row aᵀw ≤ aᵀw* − γ (γ > 0) is J* + γ² / (2 aᵀ M a), and the limits and the
        obstacles only add constraints (:meth:`_far_bounds`). None otherwise (also elastic
        or keep-out shapes)."""
        shape = self.shape
        if not self.n_planes or shape.elastic or shape.keep_out_slots:
            return None
        core = transcription(dataclasses.replace(
            shape, obstacles=(), obstacle_positions=(), control_bounds=None,
            path_constraints=(), solver=AUTO_SOLVER))
        w, p = core._w, core._p   # type: ignore[attr-defined]
        cost, rows = core.cost(w, p), core.constraints(w, p)  # type: ignore[attr-defined]
        try:
            if not (ca.is_quadratic(cost, w) and ca.is_linear(rows, w)):
                return None
        except RuntimeError:
            return None
        hessian, jacobian = ca.hessian(cost, w)[0], ca.jacobian(rows, w)
        if ca.depends_on(hessian, p) or ca.depends_on(jacobian, p):
            return None
        matrices = ca.Function("qp", [w, p], [hessian, jacobian])(np.zeros(w.numel()),
                                                                 np.zeros(p.numel()))
        h, a = (np.asarray(m, float) for m in matrices)
        nw, ng = h.shape[0], a.shape[0]
        try:
            inverse = np.linalg.inv(np.block([[h, a.T], [a, np.zeros((ng, ng))]]))[:nw, :nw]
        except np.linalg.LinAlgError:
            return None
        index = [[k * self.nq + i for i in shape.obstacle_positions] for k in range(self.n - 1)]
        return core, np.stack([inverse[np.ix_(rows_k, rows_k)] for rows_k in index])  # type: ignore[return-value]

    def _far_bounds(self, params: np.ndarray,
                    far: list[tuple[tuple[int, np.ndarray], ...]]) -> np.ndarray:
        """Lower bounds (m,) on the cost of every path (limits and obstacles included) that
        reaches, at a node, the far half-space {y : d·y ≤ −1} (scaled) of one of the
        ellipsoids ``far[j]`` names (pairs (e, d) of :meth:`_candidates`), with ``params``
        (m, n_params): the largest over those ellipsoids of J* + min_k max(γ_k, 0)² /
        (2 bᵀ M_k b), γ_k = 1 + d·y(q*_k) at the optimum q* of :attr:`_quadratic_core`
        (boundary nodes fixed: a boundary node there gives J*), b = Aᵀ_e d. −inf where the
        shape has no such core or it fails."""
        bounds = np.full(len(params), -np.inf)
        core = self._quadratic_core
        if core is None or not len(params):
            return bounds
        nlp, blocks = core
        solved = nlp.solve_batch(params, [None] * len(params), [None] * len(params))
        if solved is None:
            return bounds
        ok = np.asarray(solved.column("success"), bool)
        costs, q = np.asarray(solved.column("cost"), float), np.asarray(solved.column("q"))
        positions = q[..., list(self.shape.obstacle_positions)]
        balls = ellipsoids(self.shape.obstacles)
        for j, hits in enumerate(far):
            if not ok[j] or not hits:
                continue
            best = -np.inf
            for e, d in hits:
                ball = balls[e]
                gap = 1.0 + ball.scaled(positions[j]) @ d    # (N+1,)
                if np.any(gap[[0, -1]] <= 0):
                    best = max(best, costs[j])
                    continue
                b = ball.matrix.T @ d
                spread = np.einsum("i,kij,j->k", b, blocks, b)
                inner = np.maximum(gap[1:-1], 0.0)
                best = max(best, costs[j] + float(np.min(inner**2 / (2 * spread))))
            bounds[j] = best
        return bounds

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """The straight line from q_0 to q_N (projected onto the constraints, if any), zero
        controls and multipliers."""
        params = np.asarray(params, float)
        q0, _, qn, _ = params[:4 * self.nq].reshape(4, self.nq)
        path = q0 + np.arange(1, self.n)[:, None] / self.n * (qn - q0)
        if self.nc:
            path = self.shape.model.project(path)
        yield self.full_guess(np.concatenate([path.ravel(), np.zeros(self.nu * self.n)]),
                              params)

    def warm_start(self, solution: DmocSolution) -> np.ndarray:
        """The guess (inner nodes, controls; λ = 0) that re-solves from ``solution``."""
        return np.concatenate([solution.q[1:-1].ravel(), solution.u.ravel()])

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> DmocSolution:
        """A failed solve: NaN cost, gradient and path, with ``status``."""
        params = np.asarray(params, float)
        nan_q, nan_u = self.unpack(np.full(self.nw, np.nan), params)
        return DmocSolution(cost=float("nan"), status=status, success=False, iterations=0,
                            attempts=1, solve_time_s=elapsed,
                            cost_gradient=np.full(params.shape, np.nan),
                            end_hessian=self._no_hessian(), q=nan_q, u=nan_u,
                            duration=float("nan"))

    def _no_hessian(self) -> np.ndarray:
        """The (nh, nh) NaN ``end_hessian`` of a failed solve or of a shape with keep-outs."""
        return np.full((self.nh, self.nh), np.nan)

    def nodes(self, w: ca.SX, params: ca.SX) -> list[ca.SX]:
        """The node configurations q_0 … q_N (nq each) of ``w`` and ``params`` as
        expressions: :meth:`unpack`'s paths for symbolic w and p."""
        nq = self.nq
        inner = [w[k * nq:(k + 1) * nq] for k in range(self.n - 1)]
        return [params[:nq], *inner, params[2 * nq:3 * nq]]

    def unpack(self, w: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Split w into the node path q (N+1, nq) and the interval controls u (N, nu)."""
        q, u = self.unpack_many(np.asarray(w, float)[None], np.asarray(params, float)[None])
        return q[0], u[0]

    def unpack_many(self, w: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`unpack` of each row of w (k, nw) with ``params`` (k, 4 nq): paths
        (k, N+1, nq) and controls (k, N, nu)."""
        nq, n, k = self.nq, self.n, len(w)
        q = np.empty((k, n + 1, nq))
        q[:, 0], q[:, -1] = params[:, :nq], params[:, 2 * nq:3 * nq]
        q[:, 1:-1] = w[:, : nq * (n - 1)].reshape(k, n - 1, nq)
        u = w[:, nq * (n - 1) : nq * (n - 1) + self.nu * n].reshape(k, n, self.nu)
        return q, u

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> DmocSolution:
        """Solve for boundary data ``params`` from ``guess`` (default :meth:`default_guess`;
        with obstacles :meth:`start_guesses`, the cheapest kept) and constraint multipliers
        (default 0); a failed solve is returned, not raised."""
        params = check_params(params, self.n_params, "DMOC")
        x0 = self.start_guesses(guess, lambda: self.default_guess(params), params)
        extra = {} if multipliers is None else {"lam_g0": multipliers}
        bounds = {"lbx": self.lbx, "ubx": self.ubx} if self.has_inequalities else {}
        calls = [self._checked(call_nlpsol(self.solver, x0=x, p=params, lbg=self.lbg,
                                           ubg=self.ubg, **bounds, **extra), params)
                 for x in x0]
        call = calls[_cheapest([c.out is not None and c.success for c in calls],
                               [float(c.out["f"]) if c.out is not None else np.nan
                                for c in calls])]
        call.solve_time_s = sum(c.solve_time_s for c in calls)
        if call.out is None:
            return self.failure(params, call.status, call.solve_time_s)
        w, lam_g = (np.asarray(call.out[k]).ravel() for k in ("x", "lam_g"))
        q, u = self.unpack(w, params)
        duration = float(self.durations(w[None], params[None])[0])
        if self.shape.elastic:   # the cost is the total slack
            return DmocSolution(**call.common, cost_gradient=call.cost_gradient,
                                end_hessian=self._no_hessian(), q=q, u=u, duration=duration)
        if self.end_hessian is None:  # keep-outs: the control cost without the penalty
            common = {**call.common, "cost": float(self._costs(w[None], params[None], u[None])[0])}
            return DmocSolution(**common, cost_gradient=call.cost_gradient,
                                end_hessian=self._no_hessian(), q=q, u=u, duration=duration)
        hessian = self._hessians(w[None], lam_g[None], params[None],
                                 np.asarray(self.end_hessian(w, lam_g, params))[None])[0]
        return DmocSolution(**call.common, cost_gradient=call.cost_gradient,
                            end_hessian=hessian, q=q, u=u, duration=duration)

    def full_guess(self, guess: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``guess`` with λ = 0, slacks σ = 0 and the planes of its path
        (:meth:`_with_planes`) appended if it has none (p = ``params``)."""
        x0 = np.asarray(guess, float)
        if x0.size == self.nq * (self.n - 1) + self.nu * self.n:
            x0 = np.concatenate([x0, np.zeros(self.nw - x0.size)])
            if self.t_index is not None:
                x0[self.t_index] = self.first_duration
            x0 = self._with_planes(x0[None], np.asarray(params, float)[None])[0]
        return x0

    def prepare(self, count: int) -> None:
        """Build what solving ``count`` tasks in one :meth:`solve_batch` takes (the batched
        solver's mapped calls; with planes or limits, those of :attr:`without_obstacles` or
        :attr:`without_limits`), so that the first superstep does not."""
        screen = self.without_obstacles or self.without_limits
        if screen is not None:
            screen.prepare(count)
        elif self.batch_solver is not None:
            self.batch_solver.prepare(count)

    @cached_property
    def without_obstacles(self) -> DmocTranscription | None:
        """The transcription of this shape without its obstacles (same solver, ``newton``
        where ``auto`` chooses it then), whose batch :meth:`solve_batch` tries first; None
        without planes or without a batched solver."""
        if not self.n_planes or not self.batches:
            return None
        free = dataclasses.replace(self.shape, obstacles=(), obstacle_positions=())
        return transcription(free)   # type: ignore[return-value]

    def clear_of_obstacles(self, q: np.ndarray) -> np.ndarray:
        """Whether each path with nodes q (k, N+1, nq) keeps every segment more than
        ``kkt_tol`` · (the obstacle's scale) outside every obstacle (exact segment distances,
        :meth:`~ocpar.ocp.obstacles.Ellipsoid.clearance`): (k,) bool, False where not finite."""
        positions = q[..., list(self.shape.obstacle_positions)]
        clear = np.all(np.isfinite(positions), axis=(1, 2))
        for obstacle in self.shape.obstacles:
            gap, _ = obstacle.clearance(positions[:, :-1], positions[:, 1:])
            with np.errstate(invalid="ignore"):
                clear &= np.all(gap > self.shape.kkt_tol * obstacle.scale, axis=1)
        return clear

    def solve_batch(self, params: np.ndarray, guesses: np.ndarray | list[np.ndarray | None],
                    multipliers: np.ndarray | list[np.ndarray | None]) -> Columns | None:
        """Solve k tasks in one mapped call (:class:`~ocpar.ocp.batch.MappedNlp`): boundary
        data ``params`` (k, 4 nq), guesses and constraint multipliers per task (None: the
        default guess, zero multipliers). ``success`` comes from the KKT check; ``iterations``
        counts Newton steps (``newton``) or is −1 (``sqpmethod``: a mapped call reports none);
        ``solve_time_s`` is the call's time shared equally. None if this shape's solver is
        ``ipopt`` or CasADi raised (the caller then solves one by one).

        With obstacles, the tasks are first solved without them (:attr:`without_obstacles`,
        one batch); a task whose solution there succeeds and clears every obstacle
        (:meth:`clear_of_obstacles`) keeps it: it is a KKT point of the NLP with the
        obstacles, their rows inactive (with the canonical planes; ``end_hessian`` and
        ``cost_gradient`` the same, no obstacle row carrying a multiplier). Only the others
        are solved with the planes. Likewise with control bounds or path constraints alone
        (:attr:`without_limits`): every task by ``newton`` first, and only those whose path
        breaks or touches a limit (:meth:`_within_limits`) by :meth:`_solve_limited` (Newton
        on a guessed active set, then ``sqpmethod`` for what that misses)."""
        params = np.asarray(params, float)
        if self.without_obstacles is not None:
            return self._screened(params, guesses, multipliers, self.without_obstacles,
                                  self._clears, self._solve_segments)
        if self.without_limits is not None:
            return self._screened(params, guesses, multipliers, self.without_limits,
                                  self._within_limits, self._solve_limited)
        if self.batch_solver is None:
            return None
        return self._solve_batch(params, guesses, multipliers)

    @cached_property
    def without_limits(self) -> DmocTranscription | None:
        """The transcription of this shape without its control bounds and path constraints
        where ``auto`` chose ``sqpmethod`` for them alone (``newton`` solves it: no
        obstacles, keep-out slots, elastic slacks or time bounds), whose batch
        :meth:`solve_batch` tries first; None otherwise."""
        shape = self.shape
        if (shape.solver != AUTO_SOLVER or shape.obstacles
                or (shape.control_bounds is None and not shape.path_constraints)):
            return None
        free = dataclasses.replace(shape, control_bounds=None, path_constraints=())
        return transcription(free) if free.chosen_solver == "newton" else None  # type: ignore[return-value]

    def _clears(self, free: Columns, params: np.ndarray) -> np.ndarray:
        """Whether each solution ``free`` of :attr:`without_obstacles` succeeded and clears
        the obstacles (:meth:`clear_of_obstacles`): (k,) bool."""
        return (np.asarray(free.column("success"), bool)
                & self.clear_of_obstacles(np.asarray(free.column("q"))))

    def _within_limits(self, free: Columns, params: np.ndarray) -> np.ndarray:
        """Whether each solution ``free`` of :attr:`without_limits` succeeded and keeps every
        control and path row farther than ``kkt_tol`` (relative, :func:`_near`) inside its
        bounds: a KKT point of this NLP with no limit active (their multipliers 0, the same
        cost, gradient and ``end_hessian``): (k,) bool."""
        w = self._points(free, params)
        inside = np.asarray(free.column("success"), bool) & np.all(np.isfinite(w), axis=1)
        tol = self.shape.kkt_tol
        if self.shape.control_bounds is not None:
            inside &= ~np.any(_near(w, self.lbx, self.ubx, tol), axis=1)
        if self.n_path:
            k, n_eq = len(w), self.ng - self.n_rows
            rows = np.asarray(self._mapped("path_rows", k)(w.T, params.T)).reshape(self.n_path, k).T
            end = n_eq + self.n_path
            inside &= ~np.any(_near(rows, self.lbg[n_eq:end], self.ubg[n_eq:end], tol), axis=1)
        return inside

    def _points(self, solved: Columns, params: np.ndarray) -> np.ndarray:
        """The points w (k, nw) of solutions ``solved`` (their inner nodes and controls, the
        rest of w 0)."""
        q, u = np.asarray(solved.column("q")), np.asarray(solved.column("u"))
        inner = self.shape.previous_guesses(q, u)
        return np.hstack([inner, np.zeros((len(inner), self.nw - inner.shape[1]))])

    @cached_property
    def limit_newton(self) -> tuple[ActiveSetNewton, np.ndarray]:
        """This NLP by guessed active sets on the KKT Newton kernel
        (:class:`~ocpar.ocp.active_set.ActiveSetNewton`: the equations, and as limit rows the
        path rows, then the bounded entries of w), and those entries' indices."""
        w, p = self._w, self._p
        n_eq = self.ng - self.n_rows
        bounded = np.flatnonzero(np.isfinite(self.lbx) | np.isfinite(self.ubx))
        rows = ca.vertcat(self.path_rows(w, p), w[bounded.tolist()])
        lower = np.concatenate([self.lbg[n_eq:], self.lbx[bounded]])
        upper = np.concatenate([self.ubg[n_eq:], self.ubx[bounded]])
        return ActiveSetNewton("dmoc_limits", w, p, self.cost(w, p), self._equations(w, p),
                               rows, lower, upper, self.shape.kkt_tol), bounded

    def _solve_limited(self, params: np.ndarray, guesses: list[np.ndarray | None],
                       multipliers: list[np.ndarray | None], free: Columns) -> Columns | None:
        """The tasks ``params`` (k, n_params) whose solutions without limits ``free`` break
        or touch one: by :attr:`limit_newton` from those solutions (the default guess where
        one failed), each accepted where this NLP's KKT conditions hold to ``kkt_tol``
        (:func:`~ocpar.ocp.batch.kkt_met`; its ``end_hessian`` from the active set); the
        others by :attr:`batch_solver` (``sqpmethod``) from their own guesses (a column that
        fails there goes on to IPOPT, :func:`~ocpar.ocp.solve_tasks`). None if CasADi
        raised."""
        start = time.perf_counter()
        k, n_eq = len(params), self.ng - self.n_rows
        solver, bounded = self.limit_newton
        x0 = self._points(free, params)
        failed = ~np.asarray(free.column("success"), bool)
        if failed.any():
            x0[failed] = self.default_guesses(params[failed])
        rounds = newton(self.shape.solver_options, "max_iter",
                        min(NEWTON_ROUNDS, self.shape.max_iter))
        try:
            solved = solver.solve(x0, params, np.zeros((k, n_eq)), rounds)
        except RuntimeError:
            return None
        w, lam_g = solved.x, np.hstack([solved.lam_g, solved.lam_c[:, :self.n_path]])
        lam_x = np.zeros((k, self.nw))
        lam_x[:, bounded] = solved.lam_c[:, self.n_path:]
        g, stationarity, gradient = (np.asarray(r) for r in self._mapped("kkt_residuals", k)(
            w.T, params.T, lam_g.T, lam_x.T))
        accepted = solved.done & kkt_met(w, params, lam_g, lam_x, g.T, stationarity.ravel(),
                                         gradient.ravel(), (self.lbg, self.ubg, self.lbx,
                                                            self.ubx), self.shape.kkt_tol)
        ok, others = np.flatnonzero(accepted), np.flatnonzero(~accepted)
        parts, positions = [], []
        if len(ok):
            q, u = self.unpack_many(w[ok], params[ok])
            assert self.end_hessian is not None   # no keep-outs, not elastic
            equality = np.asarray(self._mapped("end_hessian", len(ok))(w[ok].T, lam_g[ok].T,
                                                                    params[ok].T))
            equality = equality.reshape(self.nh, len(ok), self.nh).transpose(1, 0, 2)
            hessians = self._hessians(w[ok], lam_g[ok], params[ok], equality)
            elapsed = np.full(len(ok), (time.perf_counter() - start) / k)
            parts.append(_solution_columns(solved.f[ok], np.ones(len(ok), bool),
                                           solved.iterations[ok], elapsed,
                                           -solved.lam_p[ok], hessians, q, u,
                                           self.durations(w[ok], params[ok])))
            positions.append(ok)
        if len(others):
            rest = self._solve_batch(params[others], [guesses[i] for i in others],
                                     [multipliers[i] for i in others])
            if rest is None:
                return None
            parts.append(rest)
            positions.append(others)
        return _in_order(parts, positions)

    def _screened(self, params: np.ndarray, guesses: np.ndarray | list[np.ndarray | None],
                  multipliers: np.ndarray | list[np.ndarray | None],
                  free_nlp: DmocTranscription,
                  keep: Callable[[Columns, np.ndarray], np.ndarray],
                  rest: Callable[[np.ndarray, list[np.ndarray | None],
                                  list[np.ndarray | None], Columns], Columns | None]
                  ) -> Columns | None:
        """:meth:`solve_batch` of a shape with obstacles or limits: every task first by
        ``free_nlp`` (the shape without them, fewer variables and rows), then ``rest``
        (params, guesses, multipliers, the free solutions) of the tasks whose free solution
        ``keep`` (free solutions, params) rejects; None if CasADi raised in either (the
        caller then solves one by one)."""
        k = len(params)
        guess_rows = list(guesses) if len(guesses) == k else [None] * k
        lam_rows = list(multipliers) if len(multipliers) == k else [None] * k
        n_free = free_nlp.nw
        free_guesses = [None if g is None else
                        (np.asarray(g, float)[:n_free] if np.size(g) == self.nw else g)
                        for g in guess_rows]
        free_lams = [None if m is None else np.asarray(m, float)[:free_nlp.ng]
                     for m in lam_rows]
        start = time.perf_counter()
        free = free_nlp.solve_batch(params, free_guesses, free_lams)
        free_time = time.perf_counter() - start
        if free is None:   # CasADi raised: the caller solves one by one
            return None
        kept = keep(free, params)
        if kept.all():
            return free
        redo = np.flatnonzero(~kept)
        solved = rest(params[redo], [guess_rows[i] for i in redo],
                      [lam_rows[i] for i in redo], free.take(redo))
        if solved is None:
            return None
        done = np.flatnonzero(kept)
        joined = _in_order([free.take(done), solved], [done, redo]) if len(done) else solved
        # the first batch's time is shared by all, the second's by the tasks it solved
        times = np.full(k, free_time / k)
        times[redo] += np.asarray(solved.column("solve_time_s"))
        joined.fields["solve_time_s"] = (VALUES, times)
        return joined

    @cached_property
    def segment_nlp(self) -> tuple[MappedNlp, np.ndarray, np.ndarray]:
        """The NLP of :attr:`without_obstacles` with the obstacles' rows of
        :func:`~ocpar.ocp.obstacles.segment_rows` (no planes) appended, as a
        :class:`~ocpar.ocp.batch.MappedNlp`, and its row bounds (lbg, ubg)."""
        free = self.without_obstacles
        assert free is not None
        w, p = free._w, free._p
        positions = list(self.shape.obstacle_positions)
        rows = segment_rows(self.shape.obstacles, [q[positions] for q in free.nodes(w, p)])
        g = ca.vertcat(free.constraints(w, p), *rows)
        solver = MappedNlp("dmoc_segments", w, p, free.cost(w, p), g,
                           self.shape.kkt_tol * SEGMENT_TOL_FACTOR,
                           min(self.shape.max_iter, SEGMENT_MAX_ITER), self.shape.kkt_tol,
                           qp_max_iter=SEGMENT_QP_MAX_ITER, options=self.shape.solver_options)
        return (solver, np.concatenate([free.lbg, np.zeros(len(rows))]),
                np.concatenate([free.ubg, np.full(len(rows), np.inf)]))

    def _solve_segments(self, params: np.ndarray, guesses: list[np.ndarray | None],
                        multipliers: list[np.ndarray | None], free: Columns) -> Columns:
        """The tasks ``params`` (k, n_params) whose solutions without obstacles ``free`` do
        not clear them: from :meth:`start_guesses` (the free path, or the default guess where
        the free solve failed, as the base: each side of the obstacles it enters, or the
        task's guess and, where that passes on the far side, both sides), solved together by
        :attr:`segment_nlp`, each task's cheapest kept, lifted to this NLP (the planes
        :func:`~ocpar.ocp.obstacles.canonical_planes`, the multipliers
        :func:`~ocpar.ocp.obstacles.plane_multipliers`) and accepted where it meets this
        NLP's KKT conditions to ``kkt_tol`` (:func:`~ocpar.ocp.batch.kkt_met`); the others
        one by one by IPOPT (:meth:`solve`)."""
        start = time.perf_counter()
        free_nlp = self.without_obstacles
        assert free_nlp is not None
        lbg = self.segment_nlp[1]
        n_free, ng_free, k = free_nlp.nw, free_nlp.ng, len(params)
        q_free, u_free = np.asarray(free.column("q")), np.asarray(free.column("u"))
        solved = np.asarray(free.column("success"), bool)
        rows, owner, lams, far = [], [], [], []
        for i in range(k):
            def base(i: int = i) -> np.ndarray:
                return self.default_guess(params[i]) if not solved[i] else self.full_guess(
                    np.concatenate([q_free[i, 1:-1].ravel(), u_free[i].ravel()]), params[i])
            sides, far_of = self._candidates(guesses[i], base, params[i])
            rows.append(sides[:, :n_free])
            owner += [i] * len(sides)
            far += far_of
            lam = np.zeros(len(lbg))
            if multipliers[i] is not None:
                lam[:ng_free] = np.asarray(multipliers[i], float)[:ng_free]
            lams += [lam] * len(sides)
        owner_index = np.asarray(owner)
        batch = self._in_two_rounds(np.concatenate(rows), params, owner_index,
                                    np.array(lams), far)
        accepted = np.zeros(k, bool)
        if batch is not None:
            starts = np.searchsorted(owner_index, np.arange(k + 1))
            pick = np.array([a + _cheapest(batch.success[a:b], batch.f[a:b])
                             for a, b in itertools.pairwise(starts.tolist())])
            x, lam_red, lam_x = batch.x[pick], batch.lam_g[pick], batch.lam_x[pick]
            w, lam_g, lam_xw = self._lifted(x, lam_red, lam_x, params, ng_free)
            g, stationarity, gradient = (np.asarray(r) for r in self.kkt_residuals.map(k)(
                w.T, params.T, lam_g.T, lam_xw.T))
            accepted = batch.success[pick] & kkt_met(
                w, params, lam_g, lam_xw, g.T, stationarity.ravel(), gradient.ravel(),
                (self.lbg, self.ubg, self.lbx, self.ubx), self.shape.kkt_tol)
        parts, positions = [], []
        if accepted.any():
            ok = np.flatnonzero(accepted)
            q, u = self.unpack_many(w[ok], params[ok])
            costs = (self._costs(w[ok], params[ok], u) if self.end_hessian is None
                     else batch.f[pick][ok])
            hessians = np.full((len(ok), self.nh, self.nh), np.nan)
            if self.end_hessian is not None:
                hessians = self._hessians(w[ok], lam_g[ok], params[ok], hessians)
            elapsed = (time.perf_counter() - start) / k
            parts.append(_solution_columns(costs, np.ones(len(ok), bool), np.full(len(ok), -1),
                                           np.full(len(ok), elapsed), -batch.lam_p[pick][ok],
                                           hessians, q, u, self.durations(w[ok], params[ok])))
            positions.append(ok)
        others = np.flatnonzero(~accepted)
        if len(others):
            again = [self.solve(params[i], guesses[i], multipliers[i])
                     for i in others.tolist()]
            for solution in again:   # the batch's attempt failed: IPOPT's is the second
                solution.attempts += 1
            again = to_columns(again)
            assert isinstance(again, Columns)
            parts.append(again)
            positions.append(others)
        return _in_order(parts, positions)

    def _in_two_rounds(self, x0: np.ndarray, params: np.ndarray, owner: np.ndarray,
                       lam0: np.ndarray, far: list[tuple[tuple[int, np.ndarray], ...]]
                       ) -> BatchSolve | None:
        """The candidates x0 (m, nw without planes) of the tasks ``owner`` (m,) with
        ``params`` (k, n_params) solved by :attr:`segment_nlp`: first those on the near
        side of every ellipsoid (``far`` (m,) empty), then each far one only where it can be
        cheaper: its task's near candidates all failed, or the lower bound of
        :meth:`_far_bounds` on every path reaching its far half-space is below their best
        cost. Candidates not solved are failed rows (NaN). None if CasADi raised."""
        solver, lbg, ubg = self.segment_nlp
        free_nlp = self.without_obstacles
        assert free_nlp is not None
        near = np.array([not f for f in far], bool)
        first = np.flatnonzero(near)
        try:
            part = solver.solve(x0[first], params[owner[first]], lam0[first], lbg, ubg,
                                free_nlp.lbx, free_nlp.ubx)
        except RuntimeError:
            return None
        full = _rows_of(part, len(x0), first)
        best = np.full(len(params), np.inf)
        np.minimum.at(best, owner[first], np.where(part.success, part.f, np.inf))
        later = np.flatnonzero(~near)
        if len(later):
            bounds = self._far_bounds(params[owner[later]], [far[j] for j in later])
            later = later[~(bounds >= best[owner[later]])]
        if len(later):
            try:
                part = solver.solve(x0[later], params[owner[later]], lam0[later], lbg, ubg,
                                    free_nlp.lbx, free_nlp.ubx)
            except RuntimeError:
                return None
            for name in ("x", "f", "lam_g", "lam_p", "success", "lam_x"):
                getattr(full, name)[later] = getattr(part, name)
        return full

    def _lifted(self, x: np.ndarray, lam_red: np.ndarray, lam_x: np.ndarray,
                params: np.ndarray, ng_free: int) -> tuple[np.ndarray, ...]:
        """Solutions of :attr:`segment_nlp` (x (k, nw_free), its row and bound multipliers)
        as points of this NLP: w with the canonical planes, λ_g and λ_x (module docstring of
        :mod:`ocpar.ocp.obstacles`)."""
        q, _ = self.unpack_many(x, params)
        positions = q[..., list(self.shape.obstacle_positions)]
        n_balls = len(ellipsoids(self.shape.obstacles))
        count = (self.n * n_balls)
        obstacle = lam_red[:, ng_free:]
        tol = self.shape.kkt_tol
        loaded = np.abs(obstacle[:, :count]) > tol * (
            1 + np.max(np.abs(lam_red), axis=1, keepdims=True))
        planes, _, _ = canonical_planes(self.shape.obstacles, positions, tol,
                                        np.repeat(loaded, 3, axis=1))
        w = np.hstack([x, planes])
        lam_g = np.hstack([lam_red[:, :ng_free],
                           plane_multipliers(self.shape.obstacles, positions, obstacle)])
        return w, lam_g, np.hstack([lam_x, np.zeros((len(x), self.n_planes))])

    def _solve_batch(self, params: np.ndarray, guesses: np.ndarray | list[np.ndarray | None],
                     multipliers: np.ndarray | list[np.ndarray | None]) -> Columns | None:
        """:meth:`solve_batch` by :attr:`batch_solver` (a shape without planes)."""
        if isinstance(multipliers, np.ndarray) and multipliers.shape == (len(params), self.ng):
            lam0 = multipliers.astype(float)
        else:
            lam0 = np.zeros((len(params), self.ng))
            for k in _given(multipliers):
                lam0[k] = multipliers[k]
        if isinstance(guesses, np.ndarray) and guesses.shape == (len(params), self.nw):
            x0 = guesses.astype(float)
        else:
            x0 = self.default_guesses(params)
            for k in _given(guesses):
                x0[k] = self.full_guess(guesses[k], params[k])
        try:
            if isinstance(self.batch_solver, ConvexQp):   # starts from its own point
                batch = self.batch_solver.solve(params)
            elif isinstance(self.batch_solver, KktNewton):
                rounds = self.solver_settings["newton"]["max_iter"]
                batch = self.batch_solver.solve(x0, params, lam0, self.lbx, self.ubx, rounds)
            else:
                assert self.batch_solver is not None
                batch = self.batch_solver.solve(x0, params, lam0, self.lbg, self.ubg, self.lbx,
                                                self.ubx)
        except RuntimeError:
            return None
        k = len(params)
        q, u = self.unpack_many(batch.x, params)
        iterations = np.full(k, -1) if batch.iterations is None else batch.iterations
        if self.shape.elastic:   # the cost is the total slack
            costs, hessians = batch.f, np.full((k, self.nh, self.nh), np.nan)
        elif self.end_hessian is None:  # keep-outs: the control cost without the penalty
            costs = self._costs(batch.x, params, u)
            hessians = np.full((k, self.nh, self.nh), np.nan)
        else:
            costs = batch.f
            hessians = batch.extra.reshape(k, self.nh, self.nh).transpose(0, 2, 1)
            hessians = self._hessians(batch.x, batch.lam_g, params, hessians)
        return _solution_columns(costs, np.asarray(batch.success, bool), iterations,
                                 np.full(k, batch.solve_time_s / k), -batch.lam_p, hessians,
                                 q, u, self.durations(batch.x, params))


def _in_order(parts: list[Columns], positions: list[np.ndarray]) -> Columns:
    """``parts`` joined, row r of part j going to position ``positions[j][r]``."""
    if len(parts) == 1:
        return parts[0]
    order = np.empty(sum(len(i) for i in positions), np.intp)
    order[np.concatenate(positions)] = np.arange(len(order))
    return Columns.concat(parts).take(order)


def _given(rows: np.ndarray | list[np.ndarray | None]) -> list[int]:
    """The indices of the entries of ``rows`` that are not None (compared in C: a
    superstep's tasks mostly have none)."""
    if not any(map(operator.is_not, rows, itertools.repeat(None))):
        return []
    return list(itertools.compress(range(len(rows)),
                                   map(operator.is_not, rows, itertools.repeat(None))))


def _solution_columns(costs: np.ndarray, success: np.ndarray, iterations: np.ndarray,
                      times: np.ndarray, gradients: np.ndarray, hessians: np.ndarray,
                      q: np.ndarray, u: np.ndarray, durations: np.ndarray) -> Columns:
    """k batched solutions as columns of :class:`DmocSolution` (one attempt each, the status
    from ``success``)."""
    k = len(costs)
    alike = k > 0 and bool(np.all(success == success[0]))
    return Columns(cls=DmocSolution, length=k, fields={
        "cost": (VALUES, np.asarray(costs, float)),
        "status": ((SHARED, BATCH_STATUS[bool(success[0])]) if alike
                   else (LISTED, [BATCH_STATUS[ok] for ok in success.tolist()])),
        "success": (VALUES, success),
        "iterations": (VALUES, np.asarray(iterations, np.int64)),
        "attempts": (VALUES, np.ones(k, np.int64)),
        "solve_time_s": (VALUES, np.asarray(times, float)),
        "cost_gradient": (STACKED, gradients),
        "end_hessian": (STACKED, hessians),
        "q": (STACKED, q),
        "u": (STACKED, u),
        "duration": (VALUES, np.asarray(durations, float)),
    })


def _rows_of(part: BatchSolve, m: int, rows: np.ndarray) -> BatchSolve:
    """``part``, the solves of ``rows`` of m candidates, as m rows (the others failed, NaN)."""
    def spread(values: np.ndarray, fill: float | bool) -> np.ndarray:
        out = np.full((m, *values.shape[1:]), fill, dtype=values.dtype)
        out[rows] = values
        return out
    assert part.lam_x is not None
    return BatchSolve(spread(part.x, np.nan), spread(part.f, np.nan),
                      spread(part.lam_g, np.nan), spread(part.lam_p, np.nan),
                      spread(np.asarray(part.success, bool), False),
                      spread(part.extra, np.nan), part.solve_time_s,
                      lam_x=spread(part.lam_x, np.nan))


def _cheapest(success: Sequence[bool] | np.ndarray, costs: Sequence[float] | np.ndarray
              ) -> int:
    """The index of the cheapest successful solve among candidates with ``success`` and
    ``costs`` (the first of equal costs; 0 if none succeeded)."""
    ok = np.flatnonzero(np.asarray(success, bool))
    return int(ok[np.argmin(np.asarray(costs, float)[ok])]) if len(ok) else 0


def _near(values: np.ndarray, lower: np.ndarray, upper: np.ndarray, tol: float) -> np.ndarray:
    """Where ``values`` lie within ``tol`` (relative) of a finite ``lower`` or ``upper``
    (broadcast along the last axis)."""
    with np.errstate(invalid="ignore"):
        return ((np.isfinite(lower) & (values - lower <= tol * (1 + np.abs(lower))))
                | (np.isfinite(upper) & (upper - values <= tol * (1 + np.abs(upper)))))


def _at_step(function: ca.Function, h: ca.SX | float) -> Callable[[ca.SX, ca.SX], ca.SX]:
    """(a, b) ↦ ``function``(a, b, h): a discrete Lagrangian's derivative at the step h."""
    return lambda a, b: function(a, b, h)


def _on_equations(hessian: ca.Function, ng: int, columns: int = 1) -> ca.Function:
    """``hessian`` (w, λ_eq, p) of the equations (the first rows of g) as a function of the
    multipliers of all ``ng`` rows (w, λ_g, p), each input ``columns`` columns wide; the
    same function when there are no others."""
    rows = hessian.size1_in(1)
    if rows == ng:
        return hessian
    w, lam, p = (ca.MX.sym(name, hessian.size1_in(i) if i != 1 else ng, columns)
                 for i, name in enumerate(("w", "lam_g", "p")))
    return ca.Function(hessian.name(), [w, lam, p], [hessian(w, lam[:rows, :], p)])


def dmoc_problem(shape: DmocShape) -> DmocTranscription:
    """The process-wide DMOC transcription of ``shape`` (:func:`~ocpar.ocp.transcription`)."""
    return transcription(shape)
