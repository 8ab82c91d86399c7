"""Direct multiple shooting (MS) for ẋ = f(x, u) over a fixed horizon.

N+1 state samples x_0..x_N at spacing h and N piecewise-constant controls u_0..u_{N-1}; the
continuity constraints x_{j+1} = Φ_h(x_j, u_j) use explicit Euler, Φ_h = x + h f(x, u) (the
local-pursuit paper's eq. 13/17), or classical RK4. The cost Σ_j c_h(x_j, u_j) integrates the
running cost g by the same step: with Euler the left rectangle c_h = h g(x_j, u_j) (first
order, as in the paper), with RK4 the cost as an augmented state ċ = g(x, u) integrated by the
same four stages (c_h = h/6 (g₁ + 2g₂ + 2g₃ + g₄) at the stage states): a fixed control's cost
is then fourth-order accurate like its path, and the optimal cost converges at the O(h²) that
piecewise-constant controls allow, where the left rectangle would hold it at O(h). The initial
state x_0 and the values of the terminal components x_N[i] (i in ``terminal``; the others are
free: a target set Q(x) = x[terminal] − target = 0) are NLP parameters, p = (x_0, target).
Decision variables w = (x_1..x_N, u_0..u_{N-1}); states and controls are bounded by the
model's bounds (controls only if the model has ``control_bounds``).
A guess is a w; the default holds x_0 with zero controls.

Free final time (optional, ``MsShape.final_time`` = (T_min, T_max)): the horizon T is one more
decision variable, the last entry of w, bounded by [T_min, T_max]; every step is h = T/N (the
grid is τ_j = j/N of the real time T: a time scaling, no extra state), and the cost gains
``time_weight`` · T (with a zero running cost and weight 1: minimum time). ``step`` is then
the nominal step, the default guess's T = N·step (clipped to the bounds). A fixed-time shape
(``final_time`` None) is the NLP above, unchanged.

Path constraints (optional, ``MsShape.path_constraints``, :mod:`ocpar.ocp.constraints`):
functions of ``x`` and ``u``. One that names ``u`` is imposed at (x_j, u_j), j = 0..N−1, the
sample where each control starts (x_0 is data); one of ``x`` alone at the free samples
x_1..x_N. Between samples they are not imposed: the continuous path of an RK4 step is not a
segment, so a constraint met at the samples can be broken in between by O(h²) (a state
constraint of an Euler path, linear between samples, holds on the whole path when it is
convex in x). They are inequalities: the Newton local solver takes equalities only, so a
shape with path constraints re-solves from a guess with ``sqpmethod`` (then IPOPT), and
IPOPT imposes them and the bounds exactly (no bound relaxation).

Re-solves from a nearby solution (a ``warm_start`` shape with a guess) first run a local
solver, IPOPT only if it fails: ``local_solver="newton"`` (default) takes full Newton steps on
the KKT system of the equality-constrained NLP (bounds only checked at the end), one compiled
CasADi function of two steps called through preallocated buffers; ``"sqp"`` runs CasADi's
``sqpmethod`` with ``qrqp``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property, lru_cache

import casadi as ca
import numpy as np

from ocpar.bsp.columns import Columns, to_columns
from ocpar.models.ode import OdeModel, control_bounds
from ocpar.ocp.batch import BufferedFunction, kkt_newton_function
from ocpar.ocp.constraints import (
    CompiledConstraint,
    ConstraintRows,
    PathConstraint,
    compile_constraints,
)
from ocpar.ocp.contract import InnerSolution, call_nlpsol, check_params, transcription
from ocpar.ocp.solver_options import (
    SolverOptions,
    ipopt,
    newton,
    solver_options,
    sqpmethod,
)

INTEGRATORS = ("euler", "rk4")
#: Local solvers for warm-started re-solves (see the module docstring). Measured on the
#: pursuit subproblems (orbit transfer, N_Δ = 60, 354 variables), one process: Newton
#: ~0.3-0.5 ms per solve, sqpmethod+qrqp ~1.8-2.3 ms, IPOPT ~3 ms; same optimum to ~1e-10.
LOCAL_SOLVERS = ("newton", "sqp")
#: Newton steps per call of the compiled Newton function; from the leader's plan two steps
#: reach the 1e-10 tolerance (one does not).
NEWTON_STEPS = 2
#: Calls of the Newton function (each of :data:`NEWTON_STEPS` steps) before giving up.
NEWTON_ROUNDS = 2
#: IPOPT options for re-solves from a guess near the solution of a well-scaled problem: small
#: initial barrier parameter, guess kept close to the bounds, no NLP or MUMPS scaling. On the
#: pursuit subproblems (N_Δ = 60): ~3.3 iterations and ~2.5 ms per solve instead of ~4 and
#: ~3.4 ms, same optimum to 9 digits.
WARM_START_OPTIONS = {"mu_init": 1e-6, "warm_start_init_point": "yes", "bound_push": 1e-9,
                      "bound_frac": 1e-9, "nlp_scaling_method": "none", "mumps_scaling": 0,
                      "mumps_permuting_scaling": 0}
#: CasADi sqpmethod options for warm-started re-solves (silent; a failed QP is a failed
#: solve, not an exception).
SQP_OPTIONS = {"qpsol": "qrqp", "max_iter": 50, "print_header": False,
               "print_iteration": False, "print_status": False, "print_time": False,
               "error_on_fail": False,
               "qpsol_options": {"print_iter": False, "print_header": False,
                                 "error_on_fail": False}}


@dataclass(frozen=True)
class MsShape:
    """Everything that fixes the structure of an MS NLP (the solver-cache key).

    ``intervals`` N (N+1 samples), ``step`` h in the model's time unit, ``terminal`` the
    indices of the state components fixed at the end. ``warm_start``: a solve from a guess
    first runs ``local_solver`` (one of :data:`LOCAL_SOLVERS`), then IPOPT tuned for guesses
    close to the solution of a well-scaled problem (:data:`WARM_START_OPTIONS`).
    ``path_constraints``: :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``x``
    and ``u`` (module docstring), compiled when the shape is built. ``final_time``
    (T_min, T_max), 0 < T_min ≤ T_max, frees the horizon T within them, and ``time_weight``
    (≥ 0, only with ``final_time``) adds weight · T to the cost (module docstring; None:
    fixed T = N·step). ``solver_options``: the
    inner solvers' own options (``ipopt.tol``, ``sqpmethod.tol_pr``, ``newton.kkt_tol``,
    ``newton.max_iter``, …; :mod:`ocpar.ocp.solver_options`) over these defaults (``tol``
    is IPOPT's, ``sqpmethod``'s and Newton's), checked when the shape is built.
    """

    model: OdeModel
    intervals: int
    step: float
    terminal: tuple[int, ...]
    integrator: str = "euler"
    tol: float = 1e-10
    max_iter: int = 1000
    warm_start: bool = False
    local_solver: str = "newton"
    path_constraints: tuple[PathConstraint | CompiledConstraint, ...] = ()
    final_time: tuple[float, float] | None = None
    time_weight: float = 0.0
    solver_options: SolverOptions = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", solver_options(self.solver_options))
        object.__setattr__(self, "path_constraints", compile_constraints(
            self.path_constraints, {"x": self.model.nx, "u": self.model.nu}))
        if self.final_time is not None:
            object.__setattr__(self, "final_time", check_final_time(self.final_time))
        if not (np.isfinite(self.time_weight) and self.time_weight >= 0):
            raise ValueError(f"time_weight must be a finite number >= 0, got {self.time_weight}")
        if self.time_weight and self.final_time is None:
            raise ValueError("time_weight applies only to a free final time (final_time)")
        if self.intervals < 1:
            raise ValueError(f"multiple shooting needs at least 1 interval, got {self.intervals}")
        if not self.step > 0:
            raise ValueError(f"step must be > 0, got {self.step}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.integrator!r}; choose one of {INTEGRATORS}")
        if self.local_solver not in LOCAL_SOLVERS:
            raise ValueError(f"unknown local solver {self.local_solver!r}; choose one of "
                             f"{LOCAL_SOLVERS}")
        if any(not 0 <= i < self.model.nx for i in self.terminal):
            raise ValueError(f"terminal indices {self.terminal} outside 0..{self.model.nx - 1}")

    @property
    def n_params(self) -> int:
        """Length of p = (x_0, target)."""
        return self.model.nx + len(self.terminal)

    @property
    def newton_first(self) -> bool:
        """Whether a re-solve from a guess starts with Newton steps (a ``warm_start`` shape
        whose local solver is ``newton``, without path constraints: Newton takes equalities
        only)."""
        return self.warm_start and self.local_solver == "newton" and not self.path_constraints

    def solver_settings(self) -> dict[str, dict]:
        """The options this shape's solvers are built with (defaults and the shape's
        ``solver_options``), by solver: ``ipopt`` (``nlpsol``'s), and for a ``warm_start``
        shape its local solver's: ``newton`` (``kkt_tol``; ``max_iter``, Newton steps at
        most, in calls of :data:`NEWTON_STEPS`) or ``sqpmethod``."""
        given = self.solver_options
        extra = WARM_START_OPTIONS if self.warm_start else {}
        # IPOPT relaxes bounds and inequalities by 1e-8 (relative) unless told not to: a
        # solution would break |u| <= 1 by 5e-9
        extra = extra | {"bound_relax_factor": 0.0}
        settings = {"ipopt": ipopt(given, self.tol, self.max_iter, **extra)}
        if self.newton_first:
            settings["newton"] = {
                "kkt_tol": newton(given, "kkt_tol", self.tol),
                "max_iter": newton(given, "max_iter", NEWTON_ROUNDS * NEWTON_STEPS)}
        elif self.warm_start:
            settings["sqpmethod"] = sqpmethod(given, SQP_OPTIONS | {"tol_pr": self.tol,
                                                                   "tol_du": self.tol})
        return settings

    def build(self) -> MsTranscription:
        """The transcription of this shape (see :func:`~ocpar.ocp.transcription`)."""
        return MsTranscription(self)


@dataclass
class MsSolution(InnerSolution):
    """Result of one MS solve: the common fields, and states ``x`` (N+1, nx) including x_0;
    controls ``u`` (N, nu); ``cost_gradient`` dJ*/dp (nx + len(terminal), from the NLP
    multipliers); ``constraint_violation`` = max |continuity or terminal residual| and the
    path rows' excess over their bounds; ``w`` and
    ``lam_g`` the NLP solution and constraint multipliers (to warm-start a similar solve);
    ``final_time`` the horizon T of x and u (N·step with a fixed final time; NaN on
    failure)."""

    x: np.ndarray
    u: np.ndarray
    cost_gradient: np.ndarray
    constraint_violation: float
    w: np.ndarray
    lam_g: np.ndarray
    final_time: float = float("nan")


def check_final_time(bounds: object) -> tuple[float, float]:
    """``bounds`` as (T_min, T_max) with 0 < T_min ≤ T_max finite, or one ValueError."""
    try:
        lower, upper = (float(b) for b in bounds)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"final_time: need (T_min, T_max), got {bounds!r}") from None
    if not (np.isfinite(upper) and 0 < lower <= upper):
        raise ValueError(f"final_time: need finite 0 < T_min <= T_max, got {(lower, upper)}")
    return lower, upper


def step_function(model: OdeModel, step: float, integrator: str) -> ca.Function:
    """(x, u) -> (Φ_h(x, u), c_h(x, u)/h): one step of the chosen integrator with u held
    constant, and the step's mean running cost, its integral by the same rule over h (module
    docstring; the cost is h Σ_j of it, Euler's exactly the paper's h Σ_j g(x_j, u_j))."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    nxt, rate = step_expressions(model, x, u, step, integrator)
    return ca.Function("Phi", [x, u], [nxt, rate], ["x", "u"], ["next", "mean_rate"])


def timed_step_function(model: OdeModel, integrator: str) -> ca.Function:
    """(x, u, h) -> (Φ_h(x, u), c_h(x, u)/h): :func:`step_function` with the step h an input
    (a free final time's h = T/N)."""
    x, u, h = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu), ca.SX.sym("h")
    nxt, rate = step_expressions(model, x, u, h, integrator)
    return ca.Function("Phi_h", [x, u, h], [nxt, rate], ["x", "u", "h"], ["next", "mean_rate"])


def step_expressions(model: OdeModel, x: ca.SX, u: ca.SX, step: float | ca.SX,
                     integrator: str) -> tuple[ca.SX, ca.SX]:
    """Φ_h(x, u) and the step's mean running cost (:func:`step_function`), as expressions."""
    if integrator == "euler":
        nxt = x + step * model.rhs(x, u)
        rate = model.running_cost(x, u)
    else:
        k1 = model.rhs(x, u)
        x2 = x + step / 2 * k1
        k2 = model.rhs(x2, u)
        x3 = x + step / 2 * k2
        k3 = model.rhs(x3, u)
        x4 = x + step * k3
        k4 = model.rhs(x4, u)
        nxt = x + step / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        g = [model.running_cost(stage, u) for stage in (x, x2, x3, x4)]
        rate = (g[0] + 2 * g[1] + 2 * g[2] + g[3]) / 6
    return nxt, rate


class MsTranscription:
    """The MS NLP of one shape and its IPOPT solver."""

    def __init__(self, shape: MsShape) -> None:
        self.shape = shape
        model, n = shape.model, shape.intervals
        nx, nu = model.nx, model.nu
        self.nx, self.nu, self.n = nx, nu, n
        p = ca.SX.sym("p", nx + len(shape.terminal))
        x_free = ca.SX.sym("x", nx, n)
        u = ca.SX.sym("u", nu, n)
        x = ca.horzcat(p[:nx], x_free)
        # a free final time: the horizon T, w's last entry, every step T/N
        horizon = [] if shape.final_time is None else [ca.SX.sym("T")]
        if horizon:
            phi, step = timed_step_function(model, shape.integrator), horizon[0] / n
            steps = [phi(x[:, j], u[:, j], step) for j in range(n)]
        else:
            phi, step = step_function(model, shape.step, shape.integrator), shape.step
            steps = [phi(x[:, j], u[:, j]) for j in range(n)]
        gaps = [x[:, j + 1] - nxt for j, (nxt, _) in enumerate(steps)]
        terminal = [x[i, n] - p[nx + k] for k, i in enumerate(shape.terminal)]
        cost = step * ca.sum1(ca.vertcat(*[rate for _, rate in steps]))
        if horizon:
            cost += shape.time_weight * horizon[0]

        self.w = ca.vertcat(ca.vec(x_free), ca.vec(u), *horizon)
        self.p = p
        self.n_params = shape.n_params
        self.nw = self.w.numel()
        self.cost = cost
        path = ConstraintRows()
        for constraint in shape.path_constraints:
            path.add(constraint, [{"x": x[:, j], "u": u[:, j]} for j in range(n)]
                     if constraint.depends_on("u") else [{"x": x[:, j]} for j in range(1, n + 1)])
        self.n_path = path.count
        self.g = ca.vertcat(*gaps, *terminal, path.expr)
        self.ng = self.g.numel()
        #: Constraint bounds: continuity and terminal rows = 0, then the path rows'.
        self.lbg = np.concatenate([np.zeros(self.ng - path.count), path.lower])
        self.ubg = np.concatenate([np.zeros(self.ng - path.count), path.upper])
        lower, upper = model.state_bounds()
        u_lower, u_upper = control_bounds(model)
        lbw = [np.tile(lower, n), np.tile(u_lower, n)]
        ubw = [np.tile(upper, n), np.tile(u_upper, n)]
        if shape.final_time is not None:
            lbw.append([shape.final_time[0]])
            ubw.append([shape.final_time[1]])
        self.lbw, self.ubw = np.concatenate(lbw), np.concatenate(ubw)

    @cached_property
    def solver_settings(self) -> dict[str, dict]:
        """:meth:`MsShape.solver_settings`, once."""
        return self.shape.solver_settings()

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape, built on first use and then reused."""
        nlp = {"x": self.w, "p": self.p, "f": self.cost, "g": self.g}
        return ca.nlpsol("ms", "ipopt", nlp, self.solver_settings["ipopt"])

    @cached_property
    def resolver(self) -> ca.Function:
        """CasADi's SQP (exact Hessian, qrqp QP solver) for warm-started re-solves: from a
        guess near the solution it needs no barrier iterations; on the pursuit subproblems
        ~1.5 ms instead of IPOPT's ~3 ms, same optimum to ~1e-13."""
        nlp = {"x": self.w, "p": self.p, "f": self.cost, "g": self.g}
        return ca.nlpsol("ms_sqp", "sqpmethod", nlp, self.solver_settings["sqpmethod"])

    @cached_property
    def newton(self) -> BufferedFunction:
        """(w, λ_g, p) -> (w, λ_g, J, g, ‖∇_w L‖∞, ∇_p L) after :data:`NEWTON_STEPS` full
        Newton steps on the KKT system of L = J + λ_gᵀ g (sparse QR; bounds ignored). At a
        KKT point ∇_p L is dJ*/dp."""
        return BufferedFunction(self._newton_function)

    @lru_cache(maxsize=16)  # noqa: B019 (one transcription per shape per process)
    def newton_batch(self, k: int) -> BufferedFunction:
        """:attr:`newton` mapped over k columns (inputs and outputs stacked column after
        column); each column's result is bitwise the one-by-one call's."""
        return BufferedFunction(self._newton_function.map(k, "serial"))

    @cached_property
    def _newton_function(self) -> ca.Function:
        return kkt_newton_function("ms", self.w, self.p, self.cost, self.g, NEWTON_STEPS)

    def pack(self, x: np.ndarray, u: np.ndarray, final_time: float | None = None) -> np.ndarray:
        """w from states x (N+1, nx) (x_0 is dropped) and controls u (N, nu), and with a free
        final time the horizon T (default N·step)."""
        parts = [np.asarray(x)[1:].ravel(), np.asarray(u).ravel()]
        if self.shape.final_time is not None:
            nominal = self.n * self.shape.step if final_time is None else final_time
            parts.append([nominal])
        return np.concatenate(parts)

    def unpack(self, w: np.ndarray, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States (N+1, nx) including x0, and controls (N, nu), from w."""
        n, nx = self.n, self.nx
        x = np.vstack([x0, np.asarray(w[: nx * n]).reshape(n, nx)])
        return x, np.asarray(w[nx * n : (nx + self.nu) * n]).reshape(n, self.nu)

    def final_time(self, w: np.ndarray) -> float:
        """The horizon T of w: its last entry with a free final time, else N·step."""
        return float(w[-1]) if self.shape.final_time is not None else self.n * self.shape.step

    def default_guess(self, params: np.ndarray) -> np.ndarray:
        """x_0 held at every sample, zero controls (and T = N·step clipped to its bounds)."""
        x0 = np.asarray(params, float)[: self.nx]
        nominal = self.n * self.shape.step
        if self.shape.final_time is not None:
            nominal = float(np.clip(nominal, *self.shape.final_time))
        return self.pack(np.tile(x0, (self.n + 1, 1)), np.zeros((self.n, self.nu)), nominal)

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """None: a scheme brings its own fallback (e.g. the leader's trajectory)."""
        return iter(())

    def warm_start(self, solution: MsSolution) -> np.ndarray:
        """The guess that re-solves from ``solution``: its w."""
        return solution.w

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> MsSolution:
        """Solve for p = (x_0, target) from ``guess`` (default :meth:`default_guess`) and
        constraint multipliers λ_g0 (default 0). With a ``warm_start`` shape and a guess, the
        shape's local solver runs first and IPOPT only if it fails. A failed solve is returned,
        not raised."""
        params = check_params(params, self.n_params, "multiple shooting")
        return self._solve(params, guess, multipliers)

    def solve_batch(self, params: np.ndarray,
                    guesses: np.ndarray | list[np.ndarray | None],
                    multipliers: np.ndarray | list[np.ndarray | None] | None = None
                    ) -> Columns:
        """:meth:`solve` for each row of ``params`` (k, n_params) from the row of ``guesses``
        (k, nw; a None row: :meth:`default_guess`) and of ``multipliers`` (k, ng; None or a
        None row: zeros), all finite (the batched kernel :func:`~ocpar.ocp.solve_tasks`
        calls it). With a ``warm_start`` Newton shape the first Newton call is one call of
        :meth:`newton_batch` (~5-10 % less CPU per solve than one by one on the pursuit
        subproblems); a row that has not converged goes on alone. Every solution is bitwise
        the one-by-one :meth:`solve`'s."""
        params = np.atleast_2d(np.asarray(params, float))
        k = len(params)
        if len(guesses) == k:
            guesses = np.atleast_2d(np.array(
                [self.default_guess(p) if g is None else np.asarray(g, float)
                 for p, g in zip(params, guesses, strict=True)]))
        if params.shape != (k, self.n_params) or np.shape(guesses) != (k, self.nw):
            raise ValueError(f"multiple shooting batch: params must be (k, {self.n_params}) and "
                             f"guesses (k, {self.nw}), got {params.shape} and {guesses.shape}")
        lams = np.zeros((k, self.ng))
        for i, lam in enumerate([] if multipliers is None else multipliers):
            if lam is not None:
                if np.shape(lam) != (self.ng,):
                    raise ValueError(f"multiple shooting batch: multipliers must be "
                                     f"(k, {self.ng}), got a row of shape {np.shape(lam)}")
                lams[i] = lam
        if not self._newton_first:
            return to_columns([self.solve(*row)  # type: ignore[return-value]
                               for row in zip(params, guesses, lams, strict=True)])
        start = time.perf_counter()
        try:
            outputs = self.newton_batch(k)(guesses.ravel(), lams.ravel(), params.ravel())
        except RuntimeError:   # a singular KKT matrix in a column: each on its own
            return to_columns([self.solve(*row)  # type: ignore[return-value]
                               for row in zip(params, guesses, lams, strict=True)])
        share = (time.perf_counter() - start) / k
        columns = [output.reshape(k, -1) for output in outputs]
        return to_columns([  # type: ignore[return-value]
            self._solve(params[i], guesses[i], lams[i], ([c[i] for c in columns], share))
            for i in range(k)])

    def _solve(self, params: np.ndarray, guess: np.ndarray | None,
               multipliers: np.ndarray | None,
               first_round: tuple[list[np.ndarray], float] | None = None) -> MsSolution:
        if self.shape.warm_start and guess is not None:
            if self._newton_first:
                first = self._solve_newton(params, guess, multipliers, first_round)
            else:
                first = self._solve_with(self.resolver, params, guess, multipliers)
            if first.success:
                return first
        if guess is None:
            guess = self.default_guess(params)
        return self._solve_with(self.solver, params, guess, multipliers)

    @property
    def _newton_first(self) -> bool:
        """:attr:`MsShape.newton_first`."""
        return self.shape.newton_first

    def _solve_newton(self, params: np.ndarray, guess: np.ndarray,
                      multipliers: np.ndarray | None,
                      first_round: tuple[list[np.ndarray], float] | None) -> MsSolution:
        """Up to :data:`NEWTON_ROUNDS` calls of :attr:`newton` (or the shape's
        ``newton.max_iter`` steps, rounded up to whole calls; the first call's outputs and
        time per solve possibly given: ``first_round``); success when the KKT residuals
        (‖∇_w L‖∞, max |g|) are within ``tol`` (or ``newton.kkt_tol``) and w within its
        bounds."""
        start = time.perf_counter()
        w, lam = guess, np.zeros(self.ng) if multipliers is None else multipliers
        status, steps = "Newton_Not_Converged", 0
        settings = self.solver_settings["newton"]
        tol = settings["kkt_tol"]
        for _ in range(-(-settings["max_iter"] // NEWTON_STEPS)):
            steps += NEWTON_STEPS
            if first_round is not None and steps == NEWTON_STEPS:
                w, lam, cost, g, dual, cost_gradient = first_round[0]
            else:
                try:
                    w, lam, cost, g, dual, cost_gradient = self.newton(w, lam, params)
                except RuntimeError:   # a singular KKT matrix
                    status = "Newton_Failed"
                    break
            violation = float(np.max(np.abs(g)))
            if not (np.all(np.isfinite(w)) and np.all(np.isfinite(lam))):
                status = "Newton_Diverged"
                break
            if dual[0] <= tol and violation <= tol:
                inside = np.all(w >= self.lbw) and np.all(w <= self.ubw)
                status = "Solve_Succeeded" if inside else "Newton_Out_Of_Bounds"
                break
        elapsed = time.perf_counter() - start + (0.0 if first_round is None else first_round[1])
        if status != "Solve_Succeeded":
            return self.failure(params, status, elapsed)
        x, u = self.unpack(w, params[: self.nx])
        return MsSolution(cost=float(cost[0]), status=status, success=True,
                          iterations=steps, attempts=1, solve_time_s=elapsed,
                          x=x, u=u, cost_gradient=cost_gradient,
                          constraint_violation=violation, w=w, lam_g=lam,
                          final_time=self.final_time(w))

    def _solve_with(self, solver: ca.Function, params: np.ndarray, guess: np.ndarray,
                    multipliers: np.ndarray | None) -> MsSolution:
        call = call_nlpsol(solver, x0=guess, p=params, lbg=self.lbg, ubg=self.ubg, lbx=self.lbw,
                           ubx=self.ubw, lam_g0=0 if multipliers is None else multipliers)
        if call.out is None:
            return self.failure(params, call.status, call.solve_time_s)
        out = call.out
        w = np.asarray(out["x"]).ravel()
        x, u = self.unpack(w, params[: self.nx])
        g = np.asarray(out["g"]).ravel()
        return MsSolution(
            **call.common, x=x, u=u, cost_gradient=call.cost_gradient,
            constraint_violation=self._violation(g),
            w=w, lam_g=np.asarray(out["lam_g"]).ravel(), final_time=self.final_time(w))

    def _violation(self, g: np.ndarray) -> float:
        """max |continuity or terminal residual| and the path rows' excess over their
        bounds, of constraint values ``g`` (ng,)."""
        n_eq = self.ng - self.n_path
        path = g[n_eq:]
        excess = np.max(np.maximum(self.lbg[n_eq:] - path, path - self.ubg[n_eq:]), initial=0.0)
        return float(max(np.max(np.abs(g[:n_eq])), excess))

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> MsSolution:
        """A failed solve for p: NaN cost, path, gradient and multipliers, with ``status``."""
        params = np.asarray(params, float)
        w = np.full(self.nw, np.nan)
        x, u = self.unpack(w, params[: self.nx])
        return MsSolution(cost=float("nan"), status=status, success=False, iterations=0,
                          attempts=1, solve_time_s=elapsed, x=x, u=u,
                          cost_gradient=np.full(params.shape, np.nan),
                          constraint_violation=float("inf"), w=w, lam_g=np.full(self.ng, np.nan),
                          final_time=float("nan"))


def ms_problem(shape: MsShape) -> MsTranscription:
    """The process-wide MS transcription of ``shape`` (:func:`~ocpar.ocp.transcription`)."""
    return transcription(shape)
