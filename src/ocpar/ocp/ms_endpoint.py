"""Multiple shooting between two given states: an ODE agent whose end point an outer problem
chooses (a formation's agent of any dynamics, :mod:`ocpar.ocp.endpoint_agents`).

The model ẋ = f(x, u) with running cost g(x, u) (an :class:`~ocpar.models.OdeModel` that
names its ``position_indices``) moves on [0, T] from x_0 to an end state x_N. N intervals of
h = T/N, one control u_j per interval held constant; the continuity rows
x_{j+1} = Φ_h(x_j, u_j), Φ_h ``steps`` steps of h/``steps`` of the ``integrator`` (classical
RK4 by default, or explicit Euler), and the cost h Σ_j c_h(x_j, u_j), the running cost
integrated by the same stages (:func:`~ocpar.ocp.multiple_shooting.step_function`: RK4's
h/6 (g₁ + 2g₂ + 2g₃ + g₄) at the stage states), as :class:`~ocpar.ocp.MsShape` transcribes
it. Parameters p = (x_0, x̄_N) ∈ R^{2 nx}: the start state and the end state; the end rows
x_N[i] = x̄_N[i] for every entry i not in ``free_end`` (the others are free: their entries of
p are not read). Decision variables w = (x_1..x_N, u_0..u_{N−1}).

Control bounds (``control_bounds``, as bounds on w) and path constraints
(:mod:`ocpar.ocp.constraints`, functions of ``x`` and ``u``: one of ``u`` at (x_j, u_j),
j = 0..N−1; one of ``x`` alone at x_1..x_N) are inequalities, imposed at those points only
(between samples an RK4 path is no segment). A model's finite ``state_bounds`` are refused
(write them as path constraints of ``x``: the verification checks those).

Obstacles (``obstacles``, :mod:`ocpar.ocp.obstacles`: ellipsoids and half-spaces in the
position entries ``obstacle_positions``, by default the model's ``position_indices``): an RK4
path is no chain of segments, so the keep-out is imposed on the polyline through the
integrator's own states, x_j, the ``steps`` − 1 sub-step states of interval j, x_{j+1}: one
row |y*|² − 1 ≥ 0 per sub-step and ellipsoid (:func:`~ocpar.ocp.obstacles.segment_rows`,
y* the scaled chord's point nearest the centre: the polyline is clear exactly) and the
half-spaces at every point of it but x_0 and x_N (data). Between two sub-step states the
path is the integrator's continuous solution, not the chord: it bulges out of the chord by
about (h/``steps``)² |r̈| / 8, outwards where it bends round the obstacle, inwards where it
bends away; :mod:`ocpar.formation.verify` re-integrates each sub-step with
:data:`~ocpar.formation.verify.DENSE_SUBSTEPS` finer steps and checks the clearance there
(raise ``steps`` where it reports a path inside). A solve from the default guess tries each
side of the ellipsoids the straight-line guess enters (:meth:`MsEndpointTranscription.side_guesses`,
:func:`~ocpar.ocp.obstacles.side_guesses`: its free nodes inside pushed out on that side; at most
2^3 sides) and keeps the cheapest; a re-solve from a previous solution keeps its side.

Keep-out half-spaces (``keep_out_slots`` K > 0 on the state entries ``keep_out_positions``,
the separation rounds' :mod:`ocpar.formation.keep_out.rounds`): p gains DMOC's keep-out block
(:mod:`ocpar.ocp.dmoc`: per interval and slot a normal n and offsets b⁰, b¹ at the
interval's two nodes, then the penalty ρ), w one slack σ ≥ 0 per interval and slot, the cost
ρ Σ σ (the returned ``cost`` is without it). Like the obstacles, the rows are imposed on the
polyline through the sub-step states: n·r(y_j) − b(t_j) + σ ≥ 0 at the interval's sub-step
states y_j, j = 0..``steps`` (x_0 and x_N left out: data), b linear in time from b⁰ to b¹;
between two sub-step states the path bulges out of the chord as said above (the formation
checks the separation on the dense re-integration). Not with a free or bounded duration or
the elastic problem.

The contract of a formation's agent (:mod:`ocpar.ocp.endpoint_agents`): J*, dJ*/dp (CasADi's
−λ_p), and ``end_hessian`` d²J*/dx̄_N² (nx, nx) from the KKT system
(:mod:`ocpar.ocp.sensitivity`; of the active set where a bound or a path row is active), the
path ``q`` (N+1, nx: the states at the nodes) and controls ``u`` (N, nu). Batches: the
``newton`` solver (:class:`~ocpar.ocp.riccati.RiccatiNewton`, equalities only, its end
Hessians from its own factorisation) or ``sqpmethod`` (:class:`~ocpar.ocp.batch.MappedNlp`),
each column accepted by its KKT check; IPOPT one task at a time
(:meth:`MsEndpointTranscription.solve`) for the others.

Free duration (optional, as DMOC's: :mod:`ocpar.ocp.dmoc`), h = T/N inside every step
(:func:`~ocpar.ocp.multiple_shooting.timed_step_function`): ``free_duration``, T the last
entry of p (one compiled solver for every T), ``cost_gradient`` ending with dJ*/dT (−λ_p of
T) and ``end_hessian`` the (nx + 1, nx + 1) block of d²J*/dp² over (x̄_N, T), T last; or
``time_bounds`` (T_min, T_max) with ``time_weight`` w ≥ 0, T the last entry of w and the
cost J + w T (``duration`` the T it chose; its bounds are inequalities: ``sqpmethod`` or
``ipopt``). A solution's ``duration`` is the T it was solved at.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property, lru_cache

import casadi as ca
import numpy as np

from ocpar.bsp.columns import LISTED, SHARED, STACKED, VALUES, Columns
from ocpar.models.ode import OdeModel, check_ode_model
from ocpar.ocp.batch import (
    AUTO_SOLVER,
    SOLVERS,
    KktNewton,
    MappedNlp,
    kkt_met,
    kkt_residuals,
    sqp_options,
)
from ocpar.ocp.constraints import (
    CompiledConstraint,
    ConstraintRows,
    PathConstraint,
    bound_sizes,
    check_control_bounds,
    compile_constraints,
)
from ocpar.ocp.contract import InnerSolution, call_nlpsol, check_params
from ocpar.ocp.duration import build_at_unit_duration, check_time_fields, over_duration
from ocpar.ocp.multiple_shooting import INTEGRATORS, step_function, timed_step_function
from ocpar.ocp.obstacles import (
    Obstacle,
    check_obstacles,
    keep_out_rows,
    segment_rows,
    side_guesses,
)
from ocpar.ocp.riccati import RiccatiNewton, stage_function
from ocpar.ocp.sensitivity import cost_hessian_function
from ocpar.ocp.solver_options import SolverOptions, ipopt, newton, solver_options, sqpmethod

#: Newton rounds (one step each) a ``newton`` batch takes at most: a unicycle from the
#: straight-line guess needs 5–7, from its previous solution 2–4.
NEWTON_ROUNDS = 12

#: SQP iterations a ``sqpmethod`` batch takes at most (and the shape's ``max_iter``): a
#: unicycle from its first guess needs ~10; a task its bounds make infeasible (a slot out of
#: reach) ran to the 500 of IPOPT's limit, 16 s for the 8 × 8 slot table under |a| ≤ 1.
#: What fails goes to IPOPT, one task at a time.
SQP_MAX_ITER = 50

#: ``qrqp`` active-set iterations per QP of a ``sqpmethod`` batch with obstacles (DMOC's
#: ``SEGMENT_QP_MAX_ITER``): a unicycle past a disc that |a| ≤ 0.8 makes infeasible took
#: 5.3 s to fail without it (QPs of up to qrqp's 1000), 0.55 s with it, and phase 1 of four
#: such unicycles 118 s against 30 s (the same answer); what stops goes to IPOPT.
OBSTACLE_QP_MAX_ITER = 100

#: A bound or path row within this (relative to 1 + |bound|) of its bound counts as active
#: for the end Hessian: IPOPT's interior points stop ~1e-12..1e-10 from an active bound
#: (5e-12 on the tests' unicycle under |a| ≤ 0.9, whose inactive entries are ≥ 0.07 away).
ACTIVE_RTOL = 1e-8

#: Status of a batched solve, by the outcome of its KKT check.
BATCH_STATUS = {True: "Solve_Succeeded", False: "KKT_Check_Failed"}


@dataclass(frozen=True)
class MsEndpointShape:
    """Everything that fixes the structure of a multiple-shooting NLP between two states (the
    solver-cache key; module docstring).

    ``model`` an :class:`~ocpar.models.OdeModel` with ``position_indices`` (the state entries
    that are its position); ``intervals`` N; ``duration`` T (the model's time unit);
    ``steps`` integrator steps per interval; ``integrator`` ``rk4`` (default) or ``euler``;
    ``free_end`` the end-state entries left free (e.g. a heading); ``control_bounds`` one
    (lo, hi) per control entry (None: unbounded); ``path_constraints``
    :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``x`` and ``u``; ``solver``
    ``newton``, ``sqpmethod``, ``ipopt`` or ``auto`` (``newton`` without inequalities, else
    ``sqpmethod``); ``kkt_tol`` the batched solvers' acceptance test (1e-12: Newton's last
    step lands at rounding, so that the outer Newton's gradients, dJ*/dp at the returned
    points, carry no solver noise; at 1e-10 the 8-unicycle formation's outer search stopped
    at its noise after 17 supersteps instead of converging in 4); ``tol`` and
    ``max_iter`` IPOPT's; ``solver_options`` the inner solvers' own options (``ipopt.tol``,
    ``sqpmethod.max_iter``, ``newton.kkt_tol``, …; :mod:`ocpar.ocp.solver_options`) over
    these defaults, checked when the shape is built. ``free_duration``: T the last
    parameter (``duration`` then the caller's value of it, not part of the NLP);
    ``time_bounds`` (T_min, T_max) and ``time_weight`` w: T a decision variable of each task,
    the cost J + w T (module docstring; ``duration``, clipped to the bounds, its first
    guess). ``obstacles`` kept out of on the polyline through the integrator's sub-step
    states of the entries ``obstacle_positions`` (default: the model's ``position_indices``;
    module docstring); ``elastic`` the phase-1 problem of this shape instead (module
    docstring; not with ``time_bounds``); ``keep_out_slots`` K moving half-spaces per interval
    on the state entries ``keep_out_positions`` (module docstring)."""

    model: OdeModel
    intervals: int = 10
    duration: float = 1.0
    steps: int = 1
    integrator: str = "rk4"
    free_end: tuple[int, ...] = ()
    control_bounds: tuple[tuple[float, float], ...] | None = None
    path_constraints: tuple[PathConstraint | CompiledConstraint, ...] = ()
    solver: str = AUTO_SOLVER
    kkt_tol: float = 1e-12
    tol: float = 1e-12
    max_iter: int = 500
    solver_options: SolverOptions = ()
    free_duration: bool = False
    time_weight: float = 0.0
    time_bounds: tuple[float, float] | None = None
    obstacles: tuple[Obstacle, ...] = ()
    obstacle_positions: tuple[int, ...] = ()
    elastic: bool = False
    keep_out_slots: int = 0
    keep_out_positions: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        check_ode_model(self.model, "shape.model")
        object.__setattr__(self, "solver_options", solver_options(self.solver_options))
        nx, nu = self.model.nx, self.model.nu
        positions = getattr(self.model, "position_indices", None)
        if positions is None or not positions or len(set(positions)) != len(positions) \
                or not all(isinstance(i, int | np.integer) and 0 <= i < nx for i in positions):
            raise ValueError(f"shape.model: position_indices must name distinct entries of "
                             f"its {nx} state entries, got {positions!r}")
        lower, upper = self.model.state_bounds()
        if np.any(np.isfinite(lower)) or np.any(np.isfinite(upper)):
            raise ValueError("shape.model: its state_bounds are not imposed on a formation's "
                             "agents; give them as path constraints of x (path_constraints)")
        object.__setattr__(self, "free_end", tuple(int(i) for i in self.free_end))
        if any(not 0 <= i < nx or i in positions for i in self.free_end) \
                or len(set(self.free_end)) != len(self.free_end):
            raise ValueError(f"free_end: must be distinct state entries (0..{nx - 1}) outside "
                             f"the position entries {tuple(positions)}, got {self.free_end}")
        object.__setattr__(self, "path_constraints", compile_constraints(
            self.path_constraints, {"x": nx, "u": nu}))
        self._check_obstacles(tuple(positions))
        self._check_keep_outs()
        if self.control_bounds is not None:
            object.__setattr__(self, "control_bounds",
                               check_control_bounds(self.control_bounds, nu))
        for name, value in (("intervals", self.intervals), ("steps", self.steps)):
            if not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"{name}: must be an integer ≥ 1, got {value!r}")
        if not self.duration > 0:
            raise ValueError(f"duration: must be > 0, got {self.duration}")
        object.__setattr__(self, "time_bounds", check_time_fields(
            self.free_duration, self.time_bounds, self.time_weight))
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator: choose one of {INTEGRATORS}, got "
                             f"{self.integrator!r}")
        if self.solver not in (AUTO_SOLVER, *SOLVERS):
            raise ValueError(f"solver: choose one of {AUTO_SOLVER}, {', '.join(SOLVERS)}, got "
                             f"{self.solver!r}")
        if self.solver == "newton" and self.has_inequalities:
            raise ValueError("solver: control bounds, path constraints, time bounds, obstacles "
                             "and an elastic problem's slacks are inequalities and the newton "
                             "solver takes equalities only; choose sqpmethod, ipopt or auto (the "
                             "default)")
        if self.elastic and self.time_bounds is not None:
            raise ValueError("elastic: not with time_bounds (phase 1 at a fixed or parametric T)")

    def _check_obstacles(self, positions: tuple[int, ...]) -> None:
        """``obstacles`` (of one dimension d) on ``obstacle_positions`` (d distinct state
        entries; default ``positions``, the model's), or ValueError naming the field."""
        if not self.obstacles:
            if self.obstacle_positions:
                raise ValueError("obstacle_positions needs obstacles")
            return
        entries = tuple(int(i) for i in (self.obstacle_positions or positions))
        if len(set(entries)) != len(entries) \
                or not all(0 <= i < self.model.nx for i in entries):
            raise ValueError(f"obstacle_positions: must be distinct state entries "
                             f"(0..{self.model.nx - 1}), got {entries}")
        object.__setattr__(self, "obstacle_positions", entries)
        object.__setattr__(self, "obstacles", check_obstacles(self.obstacles, len(entries)))

    def _check_keep_outs(self) -> None:
        """``keep_out_slots`` K ≥ 0 on ``keep_out_positions`` (d distinct state entries), not
        with a free or bounded duration or the elastic problem, or ValueError naming the
        field."""
        if not isinstance(self.keep_out_slots, int | np.integer) or self.keep_out_slots < 0:
            raise ValueError(f"keep_out_slots must be an integer ≥ 0, got "
                             f"{self.keep_out_slots!r}")
        entries = tuple(int(i) for i in self.keep_out_positions)
        if not self.keep_out_slots:
            if entries:
                raise ValueError("keep_out_positions needs keep_out_slots > 0")
            return
        if not entries or len(set(entries)) != len(entries) \
                or not all(0 <= i < self.model.nx for i in entries):
            raise ValueError(f"keep_out_positions must be distinct state entries "
                             f"(0..{self.model.nx - 1}), got {self.keep_out_positions!r}")
        if self.free_duration or self.time_bounds is not None or self.elastic:
            raise ValueError("keep_out_slots: not with free_duration, time_bounds or elastic")
        object.__setattr__(self, "keep_out_positions", entries)

    @property
    def n_keep_out(self) -> int:
        """Entries of p the keep-outs take: N K (d + 2) slot data and the penalty ρ (0
        without keep-outs)."""
        if not self.keep_out_slots:
            return 0
        return self.intervals * self.keep_out_slots * (len(self.keep_out_positions) + 2) + 1

    @property
    def has_inequalities(self) -> bool:
        """Whether the NLP has inequalities (control bounds, path constraints, T's bounds,
        obstacles, keep-outs, an elastic problem's slacks)."""
        return (self.control_bounds is not None or bool(self.path_constraints)
                or self.time_bounds is not None or bool(self.obstacles) or self.elastic
                or self.keep_out_slots > 0)

    @property
    def chosen_solver(self) -> str:
        """``solver``, or for ``auto`` ``newton`` (equalities only), ``ipopt`` (T a
        variable: ``sqpmethod``'s exact Hessian is indefinite in T on a nonlinear model, and
        from the first guess it diverged on 1 of 4 unicycles, each of its 50 iterations'
        QPs running to their limit: 50–85 s for the four) or ``sqpmethod``."""
        if self.solver != AUTO_SOLVER:
            return self.solver
        if self.time_bounds is not None:
            return "ipopt"
        return "sqpmethod" if self.has_inequalities else "newton"

    @property
    def n_params(self) -> int:
        """Length of p = (x_0, x̄_N), then the keep-outs' data (:attr:`n_keep_out`), then T
        where the duration is free."""
        return 2 * self.model.nx + self.n_keep_out + int(self.free_duration)

    def solver_settings(self) -> dict[str, dict]:
        """The options this shape's solvers are built with (defaults and the shape's
        ``solver_options``), by solver: ``ipopt`` (``nlpsol``'s) and the batched solver's,
        ``newton`` (``kkt_tol``, ``max_iter``: Newton steps at most) or ``sqpmethod``."""
        given = self.solver_options
        settings = {"ipopt": ipopt(given, self.tol, self.max_iter, bound_relax_factor=0.0)}
        if self.chosen_solver == "newton":
            settings["newton"] = {
                # the recursion's stages have a fixed step: sparse QR where T is a parameter
                "kkt_solver": "qr" if self.free_duration
                else newton(given, "kkt_solver", "riccati"),
                "kkt_tol": newton(given, "kkt_tol", self.kkt_tol),
                "max_iter": newton(given, "max_iter", min(NEWTON_ROUNDS, self.max_iter))}
        elif self.chosen_solver == "sqpmethod":
            settings["sqpmethod"] = sqpmethod(given, sqp_options(
                self.kkt_tol, min(self.max_iter, SQP_MAX_ITER)))
        return settings

    def with_duration(self, duration: float) -> MsEndpointShape:
        """This shape over the horizon ``duration`` (the model's time unit)."""
        return over_duration(self, duration)

    # the agent-shape interface of :mod:`ocpar.ocp.endpoint_agents`

    @property
    def boundary_size(self) -> int:
        """Entries of each boundary state in p = (start, end): nx."""
        return self.model.nx

    @property
    def node_size(self) -> int:
        """Entries of a node of the returned path ``q``: the state's nx."""
        return self.model.nx

    @property
    def position_indices(self) -> tuple[int, ...]:
        """The state entries that are the agent's position (the model's)."""
        return tuple(int(i) for i in self.model.position_indices)  # type: ignore[attr-defined]

    def end_position_entries(self, d: int) -> np.ndarray:
        """The entries of the end state (and of ``end_hessian``'s rows) that are the d
        position entries a target fixes: the model's ``position_indices``."""
        if d != len(self.position_indices):
            raise ValueError(f"the target lies in {d}-D, the model's position has "
                             f"{len(self.position_indices)} entries")
        return np.asarray(self.position_indices)

    @property
    def resolves_from_previous(self) -> bool:
        """An agent re-solves from its previous solution (the default guess of a nonlinear
        model is far from the answer)."""
        return True

    def previous_guesses(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The guesses w (k, nw) that re-solve from paths q (k, N+1, nx) and controls
        u (k, N, nu)."""
        k = len(q)
        return np.hstack([q[:, 1:].reshape(k, -1), u.reshape(k, -1)])

    def build(self) -> MsEndpointTranscription:
        """The transcription of this shape (see :func:`~ocpar.ocp.transcription`); with a
        free duration the one of every duration (that of ``duration`` 1)."""
        return build_at_unit_duration(self, MsEndpointTranscription)


@dataclass
class MsEndpointSolution(InnerSolution):
    """Result of one solve: the common fields, ``cost_gradient`` dJ*/dp (2 nx,),
    ``end_hessian`` d²J*/dx̄_N² (nx, nx; rows and columns of a free entry zero; with a free
    duration (nx + 1, nx + 1) over (x̄_N, T)), ``q`` the states at the nodes (N+1, nx),
    ``u`` the interval controls (N, nu), ``duration`` T (the shape's, the parameter's, or
    the one the task chose: ``time_bounds``), ``multipliers`` the constraints' λ_g (ng,; NaN
    on failure): a re-solve from this solution starts from them (one Newton step fewer than
    from λ = 0, where the end moved a little)."""

    cost_gradient: np.ndarray
    end_hessian: np.ndarray
    q: np.ndarray
    u: np.ndarray
    duration: float
    multipliers: np.ndarray


class MsEndpointTranscription:
    """The NLP of one :class:`MsEndpointShape`, its IPOPT solver and its batched solver."""

    def __init__(self, shape: MsEndpointShape) -> None:
        self.shape = shape
        model, n = shape.model, shape.intervals
        nx, nu = model.nx, model.nu
        self.nx, self.nu, self.n = nx, nu, n
        timed = shape.time_bounds is not None
        t_var = ca.SX.sym("T", int(timed))
        #: T: a variable (time bounds), the last parameter (free duration) or the constant
        self.horizon = t_var[0] if timed else None
        p = ca.SX.sym("p", shape.n_params)
        if shape.free_duration:
            self.horizon = p[-1]
        #: rows and columns of ``end_hessian``: x̄_N's (and T's, where free) entries of p
        self.nh = nx + int(shape.free_duration)
        if self.horizon is None:
            h = shape.duration / n
            phi = step_function(model, h / shape.steps, shape.integrator)
        else:
            h = self.horizon / n
            timed_phi = timed_step_function(model, shape.integrator)

            def phi(state: ca.SX, control: ca.SX) -> list[ca.SX]:
                return timed_phi(state, control, h / shape.steps)
        x_free, u = ca.SX.sym("x", nx, n), ca.SX.sym("u", nu, n)
        x = ca.horzcat(p[:nx], x_free)
        gaps, rates, polyline = [], [], [x[:, 0]]
        for j in range(n):
            state = x[:, j]
            for _ in range(shape.steps):
                state, rate = phi(state, u[:, j])
                rates.append(rate)
                polyline.append(state)
            gaps.append(x[:, j + 1] - state)
            polyline[-1] = x[:, j + 1]   # the node itself: the same point where gap = 0
        fixed = [i for i in range(nx) if i not in shape.free_end]
        end_slack = ca.SX.sym("end_slack", 2 * len(fixed) if shape.elastic else 0)
        reached = p[nx:][fixed] + (end_slack[:len(fixed)] - end_slack[len(fixed):]
                                   if shape.elastic else 0)
        ends = [x[i, n] - reached[k] for k, i in enumerate(fixed)]
        cost = h / shape.steps * ca.sum1(ca.vertcat(*rates))
        if timed:
            cost += shape.time_weight * self.horizon
        path = ConstraintRows()
        for constraint in shape.path_constraints:
            path.add(constraint, [{"x": x[:, j], "u": u[:, j]} for j in range(n)]
                     if constraint.depends_on("u") else [{"x": x[:, j]} for j in range(1, n + 1)])
        equations = ca.vertcat(*gaps, *ends)
        keep_out_slack = ca.SX.sym("keep_out_slack", n * shape.keep_out_slots)
        keep_out = ca.vertcat(*segment_rows(shape.obstacles, [
            point[list(shape.obstacle_positions)] for point in polyline]),
            *self._keep_out_rows(p[2 * nx:], polyline, keep_out_slack))
        if shape.keep_out_slots:
            cost += p[2 * nx + shape.n_keep_out - 1] * ca.sum1(keep_out_slack)
        lo, hi = (np.array(b) for b in zip(*(shape.control_bounds or [(-np.inf, np.inf)] * nu),
                                           strict=True))
        clear = np.full(keep_out.numel(), np.inf)
        if shape.elastic:   # module docstring: the slacks after (x, u), the cost their sum
            elastic = _Elastic(end_slack, ca.vec(u), path, np.tile(lo, n), np.tile(hi, n),
                               shape.control_bounds is not None)
            slacks = elastic.slacks
            inequalities = ca.vertcat(elastic.rows, keep_out)
            row_lower = np.concatenate([elastic.lower, np.zeros(clear.size)])
            row_upper = np.concatenate([elastic.upper, clear])
            lo, hi, cost = np.full(nu, -np.inf), np.full(nu, np.inf), elastic.cost
        else:
            slacks = keep_out_slack   # (empty without keep-outs)
            inequalities = ca.vertcat(path.expr, keep_out)
            row_lower = np.concatenate([path.lower, np.zeros(clear.size)])
            row_upper = np.concatenate([path.upper, clear])
        w = ca.vertcat(ca.vec(x_free), ca.vec(u), t_var, slacks)
        #: T's entry of w (time bounds: after the controls; never with slacks), else None
        self.t_index = nx * n + nu * n if timed else None
        g = ca.vertcat(equations, inequalities)
        self._w, self._p, self._f, self._g = w, p, cost, g
        #: the NLP as functions of (w, p): its cost and its rows (bounds ``lbg``, ``ubg``),
        #: for an NLP that holds this one among others (the monolithic formation)
        self.cost = ca.Function("J", [w, p], [cost], ["w", "p"], ["J"])
        self.constraints = ca.Function("g", [w, p], [g], ["w", "p"], ["g"])
        self.nw, self.ng, self.n_eq, self.n_path = w.numel(), g.numel(), equations.numel(), \
            inequalities.numel()
        self.n_slack = slacks.numel()
        self.n_params = shape.n_params
        self.lbg = np.concatenate([np.zeros(self.n_eq), row_lower])
        self.ubg = np.concatenate([np.zeros(self.n_eq), row_upper])
        t_lower, t_upper = shape.time_bounds or (None, None)
        self.lbx = np.concatenate([np.full(nx * n, -np.inf), np.tile(lo, n),
                                   np.full(int(timed), t_lower or 0.0), np.zeros(self.n_slack)])
        self.ubx = np.concatenate([np.full(nx * n, np.inf), np.tile(hi, n),
                                   np.full(int(timed), t_upper or 0.0),
                                   np.full(self.n_slack, np.inf)])
        block = list(range(nx, 2 * nx)) + ([shape.n_params - 1] if shape.free_duration else [])
        #: d²J*/dx̄_N² of the equations (w, λ_g, p) → (nx, nx): where no inequality is active
        #: (None for the elastic problem: phase 1 reads no Hessian)
        self.end_hessian = None if shape.elastic else _on_rows(cost_hessian_function(
            "ms_end", w, p, cost, equations, block), self.ng)
        #: the same on the active set given by a mask (w, λ_g, p, a): where one is
        self.active_hessian = cost_hessian_function("ms_end", w, p, cost, g, block,
                                                    active_set=True) \
            if shape.has_inequalities and not shape.elastic else None
        self.path_rows = ca.Function("path", [w, p], [inequalities])

    def _keep_out_rows(self, data: ca.SX, polyline: list[ca.SX], slack: ca.SX
                       ) -> list[ca.SX]:
        """n·r(y) − b + σ at the sub-step states y of each interval k (its nodes and the
        ``steps`` − 1 states between, x_0 and x_N left out: data), slot s: b the slot's
        offset linear in time from b⁰ at x_k to b¹ at x_{k+1}, r the entries
        ``keep_out_positions``, from the keep-out block ``data`` of p (as
        :mod:`ocpar.ocp.dmoc`'s) and the slacks σ (N K,)."""
        shape = self.shape
        return keep_out_rows(data, polyline, shape.steps, self.n, shape.keep_out_slots,
                             list(shape.keep_out_positions), slack)

    def _without_penalty(self, f: np.ndarray, w: np.ndarray, params: np.ndarray
                         ) -> np.ndarray:
        """The costs (k,) of solutions w (k, nw) with ``params`` (k, n_params) whose NLP
        costs are ``f`` (k,): the keep-outs' penalty ρ Σ σ taken off (none without)."""
        f = np.asarray(f, float).ravel()
        if not self.shape.keep_out_slots:
            return f
        rho = np.asarray(params, float)[:, 2 * self.nx + self.shape.n_keep_out - 1]
        return f - rho * np.sum(np.asarray(w, float)[:, self.nw - self.n_slack:], axis=1)

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape (bounds and inequalities exact: no relaxation)."""
        nlp = {"x": self._w, "p": self._p, "f": self._f, "g": self._g}
        return ca.nlpsol("ms_endpoint", "ipopt", nlp, self.solver_settings["ipopt"])

    @cached_property
    def solver_settings(self) -> dict[str, dict]:
        """:meth:`MsEndpointShape.solver_settings`, once."""
        return self.shape.solver_settings()

    @cached_property
    def kkt_residuals(self) -> ca.Function:
        """(w, p, λ_g, λ_x) ↦ the KKT residuals (:func:`~ocpar.ocp.batch.kkt_residuals`)."""
        return kkt_residuals("ms_endpoint", self._w, self._p, self._f, self._g)

    @cached_property
    def batch_solver(self) -> RiccatiNewton | KktNewton | MappedNlp | None:
        """The batched solver (None for ``ipopt``): ``newton`` by the Riccati recursion
        (:mod:`ocpar.ocp.riccati`, its end Hessians from its factorisation) or, with
        ``newton.kkt_solver = qr``, by sparse QR; the others' end Hessians are evaluated
        after it, at the accepted columns only (:meth:`_hessians`: a failed column's KKT
        matrix may be singular)."""
        chosen, settings = self.shape.chosen_solver, self.solver_settings
        if chosen == "newton" and settings["newton"]["kkt_solver"] == "riccati":
            shape = self.shape
            step = shape.duration / self.n / shape.steps
            stage = stage_function(step_function(shape.model, step, shape.integrator),
                                   shape.steps, step)
            fixed = tuple(i for i in range(self.nx) if i not in shape.free_end)
            return RiccatiNewton(stage, self.n, fixed, settings["newton"]["kkt_tol"])
        if chosen == "newton":
            return KktNewton("ms_endpoint", self._w, self._p, self._f, self._g, 1,
                             self.solver_settings["newton"]["kkt_tol"])
        if chosen == "sqpmethod":
            return MappedNlp("ms_endpoint_sqp", self._w, self._p, self._f, self._g,
                             self.shape.kkt_tol, min(self.shape.max_iter, SQP_MAX_ITER),
                             self.shape.kkt_tol, options=self.shape.solver_options,
                             qp_max_iter=OBSTACLE_QP_MAX_ITER if self.shape.obstacles
                             else None)
        return None

    @property
    def has_inequalities(self) -> bool:
        """Whether the NLP has inequalities (:attr:`MsEndpointShape.has_inequalities`)."""
        return self.shape.has_inequalities

    def prepare(self, count: int) -> None:
        """Build the batched solver's mapped calls for ``count`` tasks at once."""
        if self.batch_solver is not None:
            self.batch_solver.prepare(count)

    # guesses

    def default_guess(self, params: np.ndarray) -> np.ndarray:
        """The model's ``guess(starts, ends, times)`` where it has one (states (k, N+1, nx)
        and controls (k, N, nu) from starts and ends (k, nx) at the node times); else the
        states on the straight line from x_0 to x̄_N (free end entries held at x_0's value),
        zero controls."""
        return self.default_guesses(np.asarray(params, float)[None])[0]

    def default_guesses(self, params: np.ndarray) -> np.ndarray:
        """:meth:`default_guess` of each row of ``params`` (k, n_params): (k, nw), the
        model's guess at each row's T (its first guess where T is a variable); with
        ellipsoid obstacles, each guess's free nodes inside one pushed out on the side of its
        point nearest the centre (:func:`~ocpar.ocp.obstacles.side_guesses`' first)."""
        if self.shape.obstacles:
            return np.stack([sides[0] for sides in self.side_guesses(params)])
        return self._completed(self._line_guesses(params))

    def side_guesses(self, params: np.ndarray) -> list[list[np.ndarray]]:
        """Per row of ``params`` (k, n_params) the guesses (nw,) of each side of the ellipsoids
        its straight-line guess enters (:func:`~ocpar.ocp.obstacles.side_guesses`: the free
        nodes inside pushed out on that side; the side of the nearest point first; one
        guess where it enters none)."""
        guesses = self._line_guesses(params)
        q, u = self.unpack_many(guesses, params)
        entries = list(self.shape.obstacle_positions)
        found = []
        for path, controls in zip(q, u, strict=True):
            sides = []
            for pushed, _ in side_guesses(self.shape.obstacles, path[:, entries]):
                moved = path.copy()
                moved[:, entries] = pushed
                sides.append(self._completed(self.shape.previous_guesses(
                    moved[None], controls[None])[0]))
            found.append(sides)
        return found

    def _line_guesses(self, params: np.ndarray) -> np.ndarray:
        """The guesses of :meth:`default_guesses` before the obstacles and the slacks
        (k, N (nx + nu))."""
        nx, n, k = self.nx, self.n, len(params)
        x0, xn = params[:, :nx], params[:, nx:2 * nx].copy()
        free = list(self.shape.free_end)
        xn[:, free] = x0[:, free]
        guess = getattr(self.shape.model, "guess", None)
        if guess is None:
            s = np.arange(1, n + 1)[None, :, None] / n
            states = x0[:, None] + s * (xn - x0)[:, None]
            return np.hstack([states.reshape(k, -1), np.zeros((k, self.nu * n))])
        durations = (params[:, -1] if self.shape.free_duration
                     else np.full(k, self.first_duration))
        guesses = np.empty((k, n * (nx + self.nu)))
        for duration in np.unique(durations).tolist():   # the model's guess per T
            rows = durations == duration
            states, controls = guess(x0[rows], xn[rows], np.linspace(0.0, duration, n + 1))
            guesses[rows] = np.hstack([np.asarray(states, float)[:, 1:].reshape(rows.sum(), -1),
                                       np.asarray(controls, float).reshape(rows.sum(), -1)])
        return guesses

    @property
    def first_duration(self) -> float:
        """The first guess of T where it is a variable: ``duration`` within the bounds."""
        low, high = self.shape.time_bounds or (-np.inf, np.inf)
        return float(np.clip(self.shape.duration, low, high))

    def _completed(self, guesses: np.ndarray) -> np.ndarray:
        """Guesses (..., ·) of the states and controls with what w holds after them appended
        where they have none: T's first guess (T a variable) or the elastic problem's slacks
        (0)."""
        extra = self.nw - self.n * (self.nx + self.nu)
        if not extra or guesses.shape[-1] == self.nw:
            return guesses
        fill = self.first_duration if self.t_index is not None else 0.0
        return np.concatenate([guesses, np.full((*guesses.shape[:-1], extra), fill)], axis=-1)

    def full_guess(self, guess: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``guess`` (the states and controls, or all of w) as a whole w (nw,): what w
        holds after them appended where it has none (:meth:`_completed`)."""
        return self._completed(np.asarray(guess, float))

    def durations(self, w: np.ndarray, params: np.ndarray) -> np.ndarray:
        """T of each solution w (k, nw) with ``params`` (k, n_params): (k,)."""
        if self.t_index is not None:
            return np.asarray(w, float)[:, self.t_index].copy()
        if self.shape.free_duration:
            return np.asarray(params, float)[:, -1].copy()
        return np.full(len(w), self.shape.duration)

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """:meth:`default_guess`: an agent re-solves from its previous path first
        (:attr:`MsEndpointShape.resolves_from_previous`), from this where that fails."""
        yield self.default_guess(params)

    def warm_start(self, solution: MsEndpointSolution) -> np.ndarray:
        """The guess that re-solves from ``solution`` (and its T, where T is a variable)."""
        guess = self.shape.previous_guesses(solution.q[None], solution.u[None])[0]
        return guess if self.t_index is None else np.append(guess, solution.duration)

    def unpack(self, w: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The states at the nodes (N+1, nx) and the interval controls (N, nu) of w (nw,)."""
        q, u = self.unpack_many(np.asarray(w, float)[None], np.asarray(params, float)[None])
        return q[0], u[0]

    def unpack_many(self, w: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States (k, N+1, nx) with x_0 from ``params`` and controls (k, N, nu) of w (k, nw)."""
        k, nx, n = len(w), self.nx, self.n
        q = np.concatenate([params[:, None, :nx], w[:, :nx * n].reshape(k, n, nx)], axis=1)
        return q, w[:, nx * n:(nx + self.nu) * n].reshape(k, n, self.nu)

    # solves

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> MsEndpointSolution:
        """A failed solve: NaN cost, gradient, Hessian and path, with ``status``."""
        nx, nu, n = self.nx, self.nu, self.n
        return MsEndpointSolution(
            cost=float("nan"), status=status, success=False, iterations=0, attempts=1,
            solve_time_s=elapsed, cost_gradient=np.full(self.n_params, np.nan),
            end_hessian=np.full((self.nh, self.nh), np.nan), q=np.full((n + 1, nx), np.nan),
            u=np.full((n, nu), np.nan), duration=float(
                params[-1] if self.shape.free_duration and len(params) == self.n_params
                else np.nan if self.t_index is not None else self.shape.duration),
            multipliers=np.full(self.ng, np.nan))

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> MsEndpointSolution:
        """Solve by IPOPT for p = (x_0, x̄_N) from ``guess`` (default :meth:`default_guess`)
        and multipliers (default 0); a failed solve is returned, not raised. A solve IPOPT
        stopped short of its tolerance (e.g. at rounding) counts where the returned point
        meets the KKT conditions to ``kkt_tol`` (:func:`~ocpar.ocp.batch.kkt_met`), a
        batch's own test."""
        params = check_params(params, self.n_params, "multiple shooting (endpoint)")
        if guess is None and self.shape.obstacles:   # each side, the cheapest kept
            tried = [self.solve(params, side, multipliers)
                     for side in self.side_guesses(params[None])[0]]
            best = min(tried, key=lambda t: (not t.success, t.cost if t.success else 0.0))
            best.solve_time_s = sum(t.solve_time_s for t in tried)
            return best
        x0 = self._completed(self.default_guess(params) if guess is None
                             else np.asarray(guess, float))
        extra = {} if multipliers is None else {"lam_g0": multipliers}
        call = call_nlpsol(self.solver, x0=x0, p=params, lbg=self.lbg, ubg=self.ubg,
                           lbx=self.lbx, ubx=self.ubx, **extra)
        if call.out is None:
            return self.failure(params, call.status, call.solve_time_s)
        w, lam_g, lam_x = (np.asarray(call.out[k]).ravel()[None] for k in ("x", "lam_g", "lam_x"))
        success, status = call.success, call.status
        if not success and self._met(w, params[None], lam_g, lam_x)[0]:
            success, status = True, status + " (KKT check met)"
        q, u = self.unpack_many(w, params[None])
        hessian = self._hessians(w, lam_g, params[None], np.array([success]))[0]
        return MsEndpointSolution(
            cost=float(self._without_penalty(np.asarray(call.out["f"]), w, params[None])[0]),
            status=status, success=success,
            iterations=call.iterations, attempts=1, solve_time_s=call.solve_time_s,
            cost_gradient=call.cost_gradient, end_hessian=hessian, q=q[0], u=u[0],
            duration=float(self.durations(w, params[None])[0]), multipliers=lam_g[0])

    def _met(self, w: np.ndarray, params: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray
             ) -> np.ndarray:
        """Whether each solution meets the KKT conditions to ``kkt_tol`` (k,)."""
        k = len(w)
        g, stationarity, gradient = (np.asarray(r) for r in self.kkt_residuals.map(k)(
            w.T, params.T, lam_g.T, lam_x.T))
        return kkt_met(w, params, lam_g, lam_x, g.T, stationarity.ravel(), gradient.ravel(),
                       (self.lbg, self.ubg, self.lbx, self.ubx),
                       self.solver_settings.get("newton", {}).get("kkt_tol", self.shape.kkt_tol))

    def solve_batch(self, params: np.ndarray, guesses: np.ndarray | list[np.ndarray | None],
                    multipliers: np.ndarray | list[np.ndarray | None]) -> Columns | None:
        """Solve k tasks in one call of the batched solver: ``params`` (k, 2 nx), one guess
        and one multiplier vector per task (None: the default guess, zeros). ``success`` from
        the KKT check; ``iterations`` the Newton steps (``newton``) or −1; the call's time
        shared equally. None for ``ipopt`` or where CasADi raised (then one by one)."""
        if self.batch_solver is None:
            return None
        params = np.asarray(params, float)
        k = len(params)
        if isinstance(guesses, np.ndarray) and guesses.ndim == 2 and len(guesses) == k:
            guesses = self._completed(guesses.astype(float))
        x0 = (guesses if isinstance(guesses, np.ndarray) and guesses.shape == (k, self.nw)
              else self.default_guesses(params))
        if not isinstance(guesses, np.ndarray):
            for i, guess in enumerate(guesses):
                if guess is not None:
                    x0[i] = self._completed(np.asarray(guess, float))
        lam0 = np.zeros((k, self.ng))
        if isinstance(multipliers, np.ndarray) and multipliers.shape == (k, self.ng):
            lam0 = multipliers.astype(float)
        else:
            for i, lam in enumerate(multipliers):
                if lam is not None:
                    lam0[i] = lam
        first = self._batch_call(x0, params, lam0)
        cold = (np.zeros(0, np.intp) if isinstance(guesses, np.ndarray)
                else np.flatnonzero([guess is None for guess in guesses]))
        if first is None or not self.shape.obstacles or not len(cold):
            return first
        return self._other_sides(first, params[cold], cold, lam0[cold])

    def _other_sides(self, first: Columns, params: np.ndarray, cold: np.ndarray,
                     lam0: np.ndarray) -> Columns:
        """``first`` (k solutions) with each column of ``cold`` (its default guess, whose
        p are ``params``) re-solved from the guess of each other side
        (:meth:`side_guesses`), one batched call per side, the cheapest success kept (ties:
        the earlier side); each column's ``solve_time_s`` that of the call it keeps."""
        sides = self.side_guesses(params)
        parts, positions = [first], [np.arange(first.length)]
        chosen = np.zeros(first.length, np.intp)   # the part each column takes
        best = np.where(first.column("success"), first.column("cost"), np.inf)
        for j in range(1, max(len(g) for g in sides)):
            rows = np.flatnonzero([len(g) > j for g in sides])
            if not len(rows):
                continue
            found = self._batch_call(np.stack([sides[r][j] for r in rows]), params[rows],
                                     lam0[rows])
            if found is None:
                continue
            cost = np.where(found.column("success"), found.column("cost"), np.inf)
            better = cost < best[cold[rows]]
            best[cold[rows[better]]] = cost[better]
            chosen[cold[rows[better]]] = len(parts)
            parts.append(found)
            positions.append(cold[rows])
        pick = [parts[part].take([int(np.flatnonzero(positions[part] == i)[0])])
                for i, part in enumerate(chosen.tolist())]
        return Columns.concat(pick) if np.any(chosen) else first

    def _batch_call(self, x0: np.ndarray, params: np.ndarray, lam0: np.ndarray
                    ) -> Columns | None:
        """One call of the batched solver from guesses ``x0`` (k, nw) and multipliers
        ``lam0`` (k, ng) for ``params`` (k, 2 nx): the solutions, or None where CasADi
        raised."""
        k = len(params)
        try:
            if not isinstance(self.batch_solver, MappedNlp):
                batch = self.batch_solver.solve(x0, params, lam0, self.lbx, self.ubx,
                                                self.solver_settings["newton"]["max_iter"])
            else:
                batch = self.batch_solver.solve(x0, params, lam0, self.lbg, self.ubg,
                                                self.lbx, self.ubx)
        except RuntimeError:
            return None
        success = np.asarray(batch.success, bool)
        hessians = (batch.extra.reshape(k, self.nh, self.nh)
                    if isinstance(self.batch_solver, RiccatiNewton)
                    else self._hessians(batch.x, batch.lam_g, params, success))
        q, u = self.unpack_many(batch.x, params)
        statuses = [BATCH_STATUS[ok] for ok in success.tolist()]
        return Columns(cls=MsEndpointSolution, length=k, fields={
            "cost": (VALUES, self._without_penalty(batch.f, batch.x, params)),
            "status": ((SHARED, statuses[0]) if len(set(statuses)) == 1
                       else (LISTED, statuses)),
            "success": (VALUES, success),
            "iterations": (VALUES, np.asarray(np.full(k, -1) if batch.iterations is None
                                              else batch.iterations, np.int64)),
            "attempts": (VALUES, np.ones(k, np.int64)),
            "solve_time_s": (VALUES, np.full(k, batch.solve_time_s / k)),
            "cost_gradient": (STACKED, -batch.lam_p),
            "end_hessian": (STACKED, hessians),
            "q": (STACKED, q), "u": (STACKED, u), "multipliers": (STACKED, batch.lam_g),
            "duration": ((SHARED, self.shape.duration) if self.horizon is None
                         else (VALUES, self.durations(batch.x, params)))})

    def _hessians(self, w: np.ndarray, lam_g: np.ndarray, params: np.ndarray,
                  solved: np.ndarray) -> np.ndarray:
        """``end_hessian`` (k, nh, nh) of solutions w (k, nw) with multipliers ``lam_g``
        (k, ng) where ``solved`` (k,), NaN elsewhere: that of the equations (one mapped call)
        where no inequality is within :data:`ACTIVE_RTOL` of its bound, else that of the
        active set; NaN where a KKT matrix is singular."""
        k, nx = len(w), self.nh
        hessians = np.full((k, nx, nx), np.nan)
        if self.end_hessian is None:   # the elastic problem: none
            return hessians
        rows = np.flatnonzero(solved & np.all(np.isfinite(w), axis=1)
                              & np.all(np.isfinite(lam_g), axis=1))
        if not len(rows):
            return hessians
        mask = np.zeros((len(rows), self.ng + self.nw))
        mask[:, :self.n_eq] = 1.0
        if self.active_hessian is not None:
            if self.n_path:
                path = np.asarray(self.path_rows.map(len(rows))(w[rows].T, params[rows].T))
                mask[:, self.n_eq:self.ng] = _near(path.reshape(self.n_path, -1).T,
                                                   self.lbg[self.n_eq:], self.ubg[self.n_eq:],
                                                   ACTIVE_RTOL)
            mask[:, self.ng:] = _near(w[rows], self.lbx, self.ubx, ACTIVE_RTOL)
        active = mask[:, self.n_eq:].any(axis=1)
        plain = rows[~active]
        if len(plain):
            try:
                value = np.asarray(self._mapped_hessian(len(plain))(
                    w[plain].T, lam_g[plain].T, params[plain].T))   # (nx, m nx)
                hessians[plain] = value.reshape(nx, len(plain), nx).transpose(1, 0, 2)
            except RuntimeError:   # a singular one among them: each on its own
                for i in plain.tolist():
                    hessians[i] = self._one_hessian(self.end_hessian, w[i], lam_g[i],
                                                    params[i])
        for i, row in zip(rows[active].tolist(), mask[active], strict=True):
            hessians[i] = self._one_hessian(self.active_hessian, w[i], lam_g[i], params[i],
                                            row)
        return hessians

    @lru_cache(maxsize=16)  # noqa: B019 (one transcription per shape per process)
    def _mapped_hessian(self, k: int) -> ca.Function:
        """:attr:`end_hessian` mapped over k columns (each as alone)."""
        return self.end_hessian.map(k, "serial")

    def _one_hessian(self, function: ca.Function | None, *args: np.ndarray) -> np.ndarray:
        """``function`` at ``args`` as (nh, nh); NaN where its KKT matrix is singular."""
        try:
            return np.asarray(function(*args)).reshape(self.nh, self.nh)  # type: ignore[misc]
        except RuntimeError:
            return np.full((self.nh, self.nh), np.nan)


class _Elastic:
    """The elastic problem's slacks, rows and cost (module docstring): the end slacks a±
    ``end_slack`` (2 × the fixed entries), then one σ per control entry and interval where
    ``bounded`` (controls ``u``, N nu; bounds ``lo``, ``hi`` (N nu,)), then one per path row
    of ``path``. ``rows`` (c + σ ≥ lb, c − σ ≤ ub, u + σ ≥ lo, u − σ ≤ hi) with their
    ``lower`` and ``upper`` bounds, ``cost`` the weighted total slack."""

    def __init__(self, end_slack: ca.SX, u: ca.SX, path: ConstraintRows, lo: np.ndarray,
                 hi: np.ndarray, bounded: bool) -> None:
        row_slack = ca.SX.sym("row_slack", path.count)
        u_slack = ca.SX.sym("u_slack", u.numel() if bounded else 0)
        self.slacks = ca.vertcat(end_slack, u_slack, row_slack)
        none, free = np.full(path.count, -np.inf), np.full(path.count, np.inf)
        self.rows = ca.vertcat(path.expr + row_slack, path.expr - row_slack,
                               *([u + u_slack, u - u_slack] if bounded else []))
        self.lower = np.concatenate([path.lower, none, *([lo, np.full(lo.size, -np.inf)]
                                                         if bounded else [])])
        self.upper = np.concatenate([free, path.upper, *([np.full(hi.size, np.inf), hi]
                                                         if bounded else [])])
        weights = np.concatenate([np.ones(end_slack.numel()),
                                  1 / bound_sizes(lo, hi) if bounded else [],
                                  1 / bound_sizes(path.lower, path.upper)])
        self.cost = ca.dot(ca.DM(weights), self.slacks)


def _near(values: np.ndarray, lower: np.ndarray, upper: np.ndarray, tol: float) -> np.ndarray:
    """Where ``values`` lie within ``tol`` (relative) of a finite ``lower`` or ``upper``."""
    with np.errstate(invalid="ignore"):
        return ((np.isfinite(lower) & (values - lower <= tol * (1 + np.abs(lower))))
                | (np.isfinite(upper) & (upper - values <= tol * (1 + np.abs(upper)))))


def _on_rows(hessian: ca.Function, ng: int) -> ca.Function:
    """``hessian`` (w, λ_eq, p) of the equations (the first rows of g) as a function of the
    multipliers of all ``ng`` rows (w, λ_g, p), its output dense (a free end entry's rows are
    structural zeros)."""
    w, lam, p = (ca.MX.sym(name, hessian.nnz_in(i) if i != 1 else ng)
                 for i, name in enumerate(("w", "lam_g", "p")))
    dense = ca.densify(hessian(w, lam[:hessian.nnz_in(1)], p))
    return ca.Function(hessian.name(), [w, lam, p], [dense])

