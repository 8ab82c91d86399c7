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

The contract of a formation's agent (:mod:`ocpar.ocp.endpoint_agents`): J*, dJ*/dp (CasADi's
−λ_p), and ``end_hessian`` d²J*/dx̄_N² (nx, nx) from the KKT system
(:mod:`ocpar.ocp.sensitivity`; of the active set where a bound or a path row is active), the
path ``q`` (N+1, nx: the states at the nodes) and controls ``u`` (N, nu). Batches: the
``newton`` solver (:class:`~ocpar.ocp.riccati.RiccatiNewton`, equalities only, its end
Hessians from its own factorisation) or ``sqpmethod`` (:class:`~ocpar.ocp.batch.MappedNlp`),
each column accepted by its KKT check; IPOPT one task at a time
(:meth:`MsEndpointTranscription.solve`) for the others.
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
    compile_constraints,
)
from ocpar.ocp.contract import InnerSolution, call_nlpsol, check_params
from ocpar.ocp.multiple_shooting import INTEGRATORS, step_function
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
    these defaults, checked when the shape is built."""

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
        if self.control_bounds is not None:
            object.__setattr__(self, "control_bounds", _pairs(self.control_bounds, nu))
        for name, value in (("intervals", self.intervals), ("steps", self.steps)):
            if not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"{name}: must be an integer ≥ 1, got {value!r}")
        if not self.duration > 0:
            raise ValueError(f"duration: must be > 0, got {self.duration}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator: choose one of {INTEGRATORS}, got "
                             f"{self.integrator!r}")
        if self.solver not in (AUTO_SOLVER, *SOLVERS):
            raise ValueError(f"solver: choose one of {AUTO_SOLVER}, {', '.join(SOLVERS)}, got "
                             f"{self.solver!r}")
        if self.solver == "newton" and self.has_inequalities:
            raise ValueError("solver: control bounds and path constraints are inequalities "
                             "and the newton solver takes equalities only; choose sqpmethod, "
                             "ipopt or auto (the default)")

    @property
    def has_inequalities(self) -> bool:
        """Whether the NLP has inequalities (control bounds, path constraints)."""
        return self.control_bounds is not None or bool(self.path_constraints)

    @property
    def chosen_solver(self) -> str:
        """``solver``, or for ``auto`` ``newton`` (equalities only) or ``sqpmethod``."""
        if self.solver != AUTO_SOLVER:
            return self.solver
        return "sqpmethod" if self.has_inequalities else "newton"

    @property
    def n_params(self) -> int:
        """Length of p = (x_0, x̄_N)."""
        return 2 * self.model.nx

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
        """The transcription of this shape (see :func:`~ocpar.ocp.transcription`)."""
        return MsEndpointTranscription(self)


def _pairs(bounds: object, nu: int) -> tuple[tuple[float, float], ...]:
    """``bounds`` as ``nu`` pairs (lo, hi), lo ≤ hi, or ValueError naming the field."""
    try:
        pairs = tuple((float(lo), float(hi)) for lo, hi in bounds)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError(f"control_bounds: must be {nu} pairs (lo, hi) of numbers") from None
    if len(pairs) != nu or not all(lo <= hi for lo, hi in pairs):
        raise ValueError(f"control_bounds: must be {nu} pairs (lo, hi) with lo <= hi, got "
                         f"{pairs}")
    return pairs


@dataclass
class MsEndpointSolution(InnerSolution):
    """Result of one solve: the common fields, ``cost_gradient`` dJ*/dp (2 nx,),
    ``end_hessian`` d²J*/dx̄_N² (nx, nx; rows and columns of a free entry zero), ``q`` the
    states at the nodes (N+1, nx), ``u`` the interval controls (N, nu), ``duration`` T (the
    shape's: an ODE agent's horizon is fixed)."""

    cost_gradient: np.ndarray
    end_hessian: np.ndarray
    q: np.ndarray
    u: np.ndarray
    duration: float


class MsEndpointTranscription:
    """The NLP of one :class:`MsEndpointShape`, its IPOPT solver and its batched solver."""

    def __init__(self, shape: MsEndpointShape) -> None:
        self.shape = shape
        model, n = shape.model, shape.intervals
        nx, nu = model.nx, model.nu
        self.nx, self.nu, self.n = nx, nu, n
        h = shape.duration / n
        phi = step_function(model, h / shape.steps, shape.integrator)
        p = ca.SX.sym("p", 2 * nx)
        x_free, u = ca.SX.sym("x", nx, n), ca.SX.sym("u", nu, n)
        x = ca.horzcat(p[:nx], x_free)
        gaps, rates = [], []
        for j in range(n):
            state = x[:, j]
            for _ in range(shape.steps):
                state, rate = phi(state, u[:, j])
                rates.append(rate)
            gaps.append(x[:, j + 1] - state)
        fixed = [i for i in range(nx) if i not in shape.free_end]
        ends = [x[i, n] - p[nx + i] for i in fixed]
        cost = h / shape.steps * ca.sum1(ca.vertcat(*rates))
        path = ConstraintRows()
        for constraint in shape.path_constraints:
            path.add(constraint, [{"x": x[:, j], "u": u[:, j]} for j in range(n)]
                     if constraint.depends_on("u") else [{"x": x[:, j]} for j in range(1, n + 1)])
        equations = ca.vertcat(*gaps, *ends)
        w = ca.vertcat(ca.vec(x_free), ca.vec(u))
        g = ca.vertcat(equations, path.expr)
        self._w, self._p, self._f, self._g = w, p, cost, g
        self.nw, self.ng, self.n_eq, self.n_path = w.numel(), g.numel(), equations.numel(), \
            path.count
        self.n_params = shape.n_params
        self.lbg = np.concatenate([np.zeros(self.n_eq), path.lower])
        self.ubg = np.concatenate([np.zeros(self.n_eq), path.upper])
        lo, hi = (np.array(b) for b in zip(*(shape.control_bounds or [(-np.inf, np.inf)] * nu),
                                           strict=True))
        self.lbx = np.concatenate([np.full(nx * n, -np.inf), np.tile(lo, n)])
        self.ubx = np.concatenate([np.full(nx * n, np.inf), np.tile(hi, n)])
        block = slice(nx, 2 * nx)
        #: d²J*/dx̄_N² of the equations (w, λ_g, p) → (nx, nx): where no inequality is active
        self.end_hessian = _on_rows(cost_hessian_function("ms_end", w, p, cost, equations,
                                                          block), self.ng)
        #: the same on the active set given by a mask (w, λ_g, p, a): where one is
        self.active_hessian = cost_hessian_function("ms_end", w, p, cost, g, block,
                                                    active_set=True) \
            if shape.has_inequalities else None
        self.path_rows = ca.Function("path", [w, p], [path.expr])

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape (bounds and inequalities exact: no relaxation)."""
        nlp = {"x": self._w, "p": self._p, "f": self._f, "g": self._g}
        return ca.nlpsol("ms_endpoint", "ipopt", nlp, self.solver_settings["ipopt"])

    @cached_property
    def solver_settings(self) -> dict[str, dict]:
        """The options this shape's solvers are built with (defaults and the shape's
        ``solver_options``), by solver: ``ipopt`` (``nlpsol``'s) and the batched solver's,
        ``newton`` (``kkt_tol``, ``max_iter``: Newton steps at most) or ``sqpmethod``."""
        shape, given = self.shape, self.shape.solver_options
        settings = {"ipopt": ipopt(given, shape.tol, shape.max_iter, bound_relax_factor=0.0)}
        if shape.chosen_solver == "newton":
            settings["newton"] = {
                "kkt_solver": newton(given, "kkt_solver", "riccati"),
                "kkt_tol": newton(given, "kkt_tol", shape.kkt_tol),
                "max_iter": newton(given, "max_iter", min(NEWTON_ROUNDS, shape.max_iter))}
        elif shape.chosen_solver == "sqpmethod":
            settings["sqpmethod"] = sqpmethod(given, sqp_options(
                shape.kkt_tol, min(shape.max_iter, SQP_MAX_ITER)))
        return settings

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
                             self.shape.kkt_tol, options=self.shape.solver_options)
        return None

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
        """:meth:`default_guess` of each row of ``params`` (k, 2 nx): (k, nw)."""
        nx, n, k = self.nx, self.n, len(params)
        x0, xn = params[:, :nx], params[:, nx:].copy()
        free = list(self.shape.free_end)
        xn[:, free] = x0[:, free]
        guess = getattr(self.shape.model, "guess", None)
        if guess is not None:
            states, controls = guess(x0, xn, np.linspace(0.0, self.shape.duration, n + 1))
            return np.hstack([np.asarray(states, float)[:, 1:].reshape(k, -1),
                              np.asarray(controls, float).reshape(k, -1)])
        s = np.arange(1, n + 1)[None, :, None] / n
        states = x0[:, None] + s * (xn - x0)[:, None]
        return np.hstack([states.reshape(k, -1), np.zeros((k, self.nu * n))])

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """:meth:`default_guess`: an agent re-solves from its previous path first
        (:attr:`MsEndpointShape.resolves_from_previous`), from this where that fails."""
        yield self.default_guess(params)

    def warm_start(self, solution: MsEndpointSolution) -> np.ndarray:
        """The guess that re-solves from ``solution``."""
        return self.shape.previous_guesses(solution.q[None], solution.u[None])[0]

    def unpack_many(self, w: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States (k, N+1, nx) with x_0 from ``params`` and controls (k, N, nu) of w (k, nw)."""
        k, nx, n = len(w), self.nx, self.n
        q = np.concatenate([params[:, None, :nx], w[:, :nx * n].reshape(k, n, nx)], axis=1)
        return q, w[:, nx * n:].reshape(k, n, self.nu)

    # solves

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> MsEndpointSolution:
        """A failed solve: NaN cost, gradient, Hessian and path, with ``status``."""
        nx, nu, n = self.nx, self.nu, self.n
        return MsEndpointSolution(
            cost=float("nan"), status=status, success=False, iterations=0, attempts=1,
            solve_time_s=elapsed, cost_gradient=np.full(self.n_params, np.nan),
            end_hessian=np.full((nx, nx), np.nan), q=np.full((n + 1, nx), np.nan),
            u=np.full((n, nu), np.nan), duration=self.shape.duration)

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> MsEndpointSolution:
        """Solve by IPOPT for p = (x_0, x̄_N) from ``guess`` (default :meth:`default_guess`)
        and multipliers (default 0); a failed solve is returned, not raised. A solve IPOPT
        stopped short of its tolerance (e.g. at rounding) counts where the returned point
        meets the KKT conditions to ``kkt_tol`` (:func:`~ocpar.ocp.batch.kkt_met`), a
        batch's own test."""
        params = check_params(params, self.n_params, "multiple shooting (endpoint)")
        x0 = self.default_guess(params) if guess is None else np.asarray(guess, float)
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
            cost=float(call.out["f"]), status=status, success=success,
            iterations=call.iterations, attempts=1, solve_time_s=call.solve_time_s,
            cost_gradient=call.cost_gradient, end_hessian=hessian, q=q[0], u=u[0],
            duration=self.shape.duration)

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
        x0 = (guesses.astype(float) if isinstance(guesses, np.ndarray)
              and guesses.shape == (k, self.nw) else self.default_guesses(params))
        if not isinstance(guesses, np.ndarray):
            for i, guess in enumerate(guesses):
                if guess is not None:
                    x0[i] = guess
        lam0 = np.zeros((k, self.ng))
        if isinstance(multipliers, np.ndarray) and multipliers.shape == (k, self.ng):
            lam0 = multipliers.astype(float)
        else:
            for i, lam in enumerate(multipliers):
                if lam is not None:
                    lam0[i] = lam
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
        hessians = (batch.extra.reshape(k, self.nx, self.nx)
                    if isinstance(self.batch_solver, RiccatiNewton)
                    else self._hessians(batch.x, batch.lam_g, params, success))
        q, u = self.unpack_many(batch.x, params)
        statuses = [BATCH_STATUS[ok] for ok in success.tolist()]
        return Columns(cls=MsEndpointSolution, length=k, fields={
            "cost": (VALUES, np.asarray(batch.f, float)),
            "status": ((SHARED, statuses[0]) if len(set(statuses)) == 1
                       else (LISTED, statuses)),
            "success": (VALUES, success),
            "iterations": (VALUES, np.asarray(np.full(k, -1) if batch.iterations is None
                                              else batch.iterations, np.int64)),
            "attempts": (VALUES, np.ones(k, np.int64)),
            "solve_time_s": (VALUES, np.full(k, batch.solve_time_s / k)),
            "cost_gradient": (STACKED, -batch.lam_p),
            "end_hessian": (STACKED, hessians),
            "q": (STACKED, q), "u": (STACKED, u),
            "duration": (SHARED, self.shape.duration)})

    def _hessians(self, w: np.ndarray, lam_g: np.ndarray, params: np.ndarray,
                  solved: np.ndarray) -> np.ndarray:
        """``end_hessian`` (k, nx, nx) of solutions w (k, nw) with multipliers ``lam_g``
        (k, ng) where ``solved`` (k,), NaN elsewhere: that of the equations (one mapped call)
        where no inequality is within :data:`ACTIVE_RTOL` of its bound, else that of the
        active set; NaN where a KKT matrix is singular."""
        k, nx = len(w), self.nx
        hessians = np.full((k, nx, nx), np.nan)
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
        """``function`` at ``args`` as (nx, nx); NaN where its KKT matrix is singular."""
        try:
            return np.asarray(function(*args)).reshape(self.nx, self.nx)  # type: ignore[misc]
        except RuntimeError:
            return np.full((self.nx, self.nx), np.nan)


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

