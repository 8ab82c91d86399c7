"""Direct multiple shooting (MS) for ẋ = f(x, u) over a fixed horizon.

N+1 state samples x_0..x_N at spacing h and N piecewise-constant controls u_0..u_{N-1}; the
continuity constraints x_{j+1} = Φ_h(x_j, u_j) use explicit Euler, Φ_h = x + h f(x, u) (the
local-pursuit paper's eq. 13/17), or classical RK4. The cost is Σ_j h g(x_j, u_j). The initial
state x_0 and the values of the terminal components x_N[i] (i in ``terminal``; the others are
free: a target set Q(x) = x[terminal] − target = 0) are NLP parameters, p = (x_0, target).
Decision variables w = (x_1..x_N, u_0..u_{N-1}); states and controls are bounded by the
model's bounds (controls only if the model has ``control_bounds``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property, lru_cache

import casadi as ca
import numpy as np

from ocpar import faults
from ocpar.models.ode import OdeModel, control_bounds
from ocpar.ocp.ipopt import ipopt_options

INTEGRATORS = ("euler", "rk4")
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
    indices of the state components fixed at the end. ``warm_start`` tunes IPOPT for guesses
    close to the solution of a well-scaled problem (:data:`WARM_START_OPTIONS`).
    """

    model: OdeModel
    intervals: int
    step: float
    terminal: tuple[int, ...]
    integrator: str = "euler"
    tol: float = 1e-10
    max_iter: int = 1000
    warm_start: bool = False

    def __post_init__(self) -> None:
        if self.intervals < 1:
            raise ValueError(f"multiple shooting needs at least 1 interval, got {self.intervals}")
        if not self.step > 0:
            raise ValueError(f"step must be > 0, got {self.step}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.integrator!r}; choose one of {INTEGRATORS}")
        if any(not 0 <= i < self.model.nx for i in self.terminal):
            raise ValueError(f"terminal indices {self.terminal} outside 0..{self.model.nx - 1}")


@dataclass(frozen=True)
class MsTask:
    """One MS solve: shape, initial state (nx,), terminal target (len(terminal),) and an
    optional warm start: w0 (flattened states x_1..x_N then controls) and constraint
    multipliers λ_g0 (from a neighbouring solve of the same shape); ``fallback`` an optional
    second guess (like w0, without multipliers) to retry from if the first attempt fails.
    Numbers travel as float arrays (a tuple of numpy scalars pickles ~30x slower)."""

    shape: MsShape
    initial_state: np.ndarray
    target: np.ndarray
    warm_start: np.ndarray | None = None
    multipliers: np.ndarray | None = None
    fallback: np.ndarray | None = None


@dataclass
class MsSolution:
    """Result of one MS solve: ``cost``; states ``x`` (N+1, nx) including x_0; controls ``u``
    (N, nu); ``constraint_violation`` = max |continuity or terminal residual|; ``w`` and
    ``lam_g`` the NLP solution and constraint multipliers (to warm-start a similar solve)."""

    cost: float
    x: np.ndarray
    u: np.ndarray
    status: str
    success: bool
    iterations: int
    solve_time_s: float
    constraint_violation: float
    w: np.ndarray
    lam_g: np.ndarray
    attempts: int = 1


def step_function(model: OdeModel, step: float, integrator: str) -> ca.Function:
    """Φ_h(x, u): one step of the chosen integrator with u held constant."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    if integrator == "euler":
        nxt = x + step * model.rhs(x, u)
    else:
        k1 = model.rhs(x, u)
        k2 = model.rhs(x + step / 2 * k1, u)
        k3 = model.rhs(x + step / 2 * k2, u)
        k4 = model.rhs(x + step * k3, u)
        nxt = x + step / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("Phi", [x, u], [nxt])


class MsTranscription:
    """The MS NLP of one shape and its IPOPT solver."""

    def __init__(self, shape: MsShape) -> None:
        self.shape = shape
        model, n = shape.model, shape.intervals
        nx, nu = model.nx, model.nu
        self.nx, self.nu, self.n = nx, nu, n
        phi = step_function(model, shape.step, shape.integrator)
        cost_rate = ca.Function("g", [xs := ca.SX.sym("x", nx), us := ca.SX.sym("u", nu)],
                                [model.running_cost(xs, us)])

        p = ca.SX.sym("p", nx + len(shape.terminal))
        x_free = ca.SX.sym("x", nx, n)
        u = ca.SX.sym("u", nu, n)
        x = ca.horzcat(p[:nx], x_free)
        gaps = [x[:, j + 1] - phi(x[:, j], u[:, j]) for j in range(n)]
        terminal = [x[i, n] - p[nx + k] for k, i in enumerate(shape.terminal)]
        cost = shape.step * ca.sum1(ca.vertcat(*[cost_rate(x[:, j], u[:, j]) for j in range(n)]))

        self.w = ca.vertcat(ca.vec(x_free), ca.vec(u))
        self.p = p
        self.nw = self.w.numel()
        self.cost = cost
        self.g = ca.vertcat(*gaps, *terminal)
        self.ng = self.g.numel()
        lower, upper = model.state_bounds()
        u_lower, u_upper = control_bounds(model)
        self.lbw = np.concatenate([np.tile(lower, n), np.tile(u_lower, n)])
        self.ubw = np.concatenate([np.tile(upper, n), np.tile(u_upper, n)])

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape, built on first use and then reused."""
        nlp = {"x": self.w, "p": self.p, "f": self.cost, "g": self.g}
        extra = WARM_START_OPTIONS if self.shape.warm_start else {}
        return ca.nlpsol("ms", "ipopt", nlp,
                         ipopt_options(self.shape.tol, self.shape.max_iter, **extra))

    @cached_property
    def resolver(self) -> ca.Function:
        """CasADi's SQP (exact Hessian, qrqp QP solver) for warm-started re-solves: from a
        guess near the solution it needs no barrier iterations; on the pursuit subproblems
        ~1.5 ms instead of IPOPT's ~3 ms, same optimum to ~1e-13."""
        nlp = {"x": self.w, "p": self.p, "f": self.cost, "g": self.g}
        return ca.nlpsol("ms_sqp", "sqpmethod", nlp, SQP_OPTIONS | {
            "tol_pr": self.shape.tol, "tol_du": self.shape.tol})

    def pack(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """w from states x (N+1, nx) (x_0 is dropped) and controls u (N, nu)."""
        return np.concatenate([np.asarray(x)[1:].ravel(), np.asarray(u).ravel()])

    def unpack(self, w: np.ndarray, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """States (N+1, nx) including x0, and controls (N, nu), from w."""
        n, nx = self.n, self.nx
        x = np.vstack([x0, np.asarray(w[: nx * n]).reshape(n, nx)])
        return x, np.asarray(w[nx * n :]).reshape(n, self.nu)

    def solve(
        self,
        x0: np.ndarray,
        target: np.ndarray,
        w0: np.ndarray | None = None,
        lam_g0: np.ndarray | None = None,
    ) -> MsSolution:
        """Solve from x0 to the target; w0 defaults to x0 held and zero controls, λ_g0 to
        zero. With a ``warm_start`` shape and a guess, the SQP :attr:`resolver` runs first and
        IPOPT only if it fails. A failed solve is returned, not raised."""
        if self.shape.warm_start and w0 is not None:
            first = self._solve_with(self.resolver, x0, target, w0, lam_g0)
            if first.success:
                return first
        return self._solve_with(self.solver, x0, target, w0, lam_g0)

    def _solve_with(
        self,
        solver: ca.Function,
        x0: np.ndarray,
        target: np.ndarray,
        w0: np.ndarray | None,
        lam_g0: np.ndarray | None,
    ) -> MsSolution:
        x0, target = np.asarray(x0, float), np.asarray(target, float)
        if w0 is None:
            w0 = self.pack(np.tile(x0, (self.n + 1, 1)), np.zeros((self.n, self.nu)))
        p = np.concatenate([x0, target])
        start = time.perf_counter()
        try:
            out = solver(x0=w0, p=p, lbg=0, ubg=0, lbx=self.lbw, ubx=self.ubw,
                         lam_g0=0 if lam_g0 is None else lam_g0)
        except RuntimeError as exc:  # evaluation errors (NaN) in CasADi
            return self.failure(x0, f"error: {exc}".splitlines()[0],
                                time.perf_counter() - start)
        elapsed = time.perf_counter() - start
        stats = solver.stats()
        w = np.asarray(out["x"]).ravel()
        x, u = self.unpack(w, x0)
        return MsSolution(
            cost=float(out["f"]),
            x=x,
            u=u,
            status=str(stats["return_status"]),
            success=bool(stats["success"]),
            iterations=int(stats["iter_count"]),
            solve_time_s=elapsed,
            constraint_violation=float(np.max(np.abs(np.asarray(out["g"])))),
            w=w,
            lam_g=np.asarray(out["lam_g"]).ravel(),
        )


    def failure(self, x0: np.ndarray, status: str, elapsed: float) -> MsSolution:
        """A failed solve from ``x0``: NaN cost, path and multipliers, with ``status``."""
        w = np.full(self.nw, np.nan)
        x, u = self.unpack(w, np.asarray(x0, float))
        return MsSolution(float("nan"), x, u, status, False, 0, elapsed, float("inf"), w,
                          np.full(self.ng, np.nan))


@lru_cache(maxsize=64)
def ms_problem(shape: MsShape) -> MsTranscription:
    """The process-wide MS transcription of ``shape``: built once, then reused."""
    return MsTranscription(shape)


def solve_ms_task(task: MsTask) -> MsSolution:
    """Engine kernel: solve one MS task with this process's cached solver; if that fails and
    the task has a ``fallback`` guess, retry once from it (``attempts`` says how many were
    made). (Test-only: first attempts chosen by :mod:`ocpar.faults` fail without solving.)"""
    ms = ms_problem(task.shape)
    key = np.concatenate([task.initial_state, task.target]).tobytes()
    if faults.injected(key):
        solution = ms.failure(task.initial_state, faults.STATUS, 0.0)
    else:
        solution = ms.solve(task.initial_state, task.target, task.warm_start, task.multipliers)
    if not solution.success and task.fallback is not None:
        solution = ms.solve(task.initial_state, task.target, task.fallback)
        solution.attempts = 2
    return solution
