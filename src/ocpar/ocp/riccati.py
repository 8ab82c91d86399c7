"""Batched Newton on the KKT system of multiple shooting between two states by a Riccati
recursion: the equality-constrained NLP of :class:`~ocpar.ocp.MsEndpointShape` (dynamics rows
x_{j+1} = Φ(x_j, u_j), the fixed end entries E x_N = x̄_N) solved stage by stage.

Decision w = (x_1..x_N, u_0..u_{N−1}), x_0 given, multipliers λ = (λ_1..λ_N, μ) of the rows
g = (x_{j+1} − Φ_j, E x_N − x̄_N) as CasADi orders them (L = Σ_j c_j + λᵀ g). A Newton step is
the equality-constrained QP of the Lagrangian's stage Hessians H_j = ∇²_{(x_j,u_j)}(c_j −
λ_{j+1}ᵀ Φ_j), the cost's gradients and the Jacobians A_j, B_j of Φ_j; its multipliers are the
new λ (as :class:`~ocpar.ocp.batch.KktSystem` takes them). The QP is solved by the backward
Riccati recursion of the cost-to-go ½ dxᵀ P_j dx + dxᵀ(s_j + S_j μ) (affine in the end rows'
multiplier μ: P_N = 0, s_N = 0, S_N = Eᵀ), a forward pass that gives dx_N = c + D μ, and
μ = (E D)⁻¹ (r − E c); λ_j = −(P_j dx_j + s_j + S_j μ). The same factorisation at the
returned point gives the end Hessian d²J*/dx̄_N² = −(E D)⁻¹ on the fixed entries (d²J*/dx̄²
= −dμ/dx̄: the Schur complement of the end rows).

The recursion is written once, per agent, as a CasADi SX function of (w, λ, p)
(:func:`newton_step_function`: the KKT check of the iterate, its Newton step and its end
Hessian; the small solves by Gaussian elimination with partial pivoting), whose sparsity
CasADi exploits, its common subexpressions (the stages' derivatives repeat their sines and
cosines) computed once (a unicycle's N = 10 step: ~5,700 instructions, ~6,900 without; the
same bits, 5 % faster); it is compiled by the
host's C compiler (:mod:`ocpar.ocp.compiled`, cached on disk by content; numpy over the agents,
:func:`~ocpar.ocp.columns_eval.evaluate_columns`, where the host has none) and evaluated on
all of a batch's agents at once, one call per Newton step. Each agent's arithmetic is that of
the agent alone, so a task's result does not depend on which tasks share its batch (tested
bitwise). It replaces one sparse QR of the whole KKT matrix per agent and step
(:class:`~ocpar.ocp.batch.KktNewton`).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ocpar.ocp.batch import BatchSolve
from ocpar.ocp.columns_eval import evaluate_columns
from ocpar.ocp.compiled import CompiledPoints

#: The outputs of :func:`newton_step_function`, in order.
STEP_OUTPUTS = ("cost", "primal", "dual", "gradient", "finite", "grad_p", "dw", "new_lam",
                "hessian")


def stage_function(phi: ca.Function, steps: int, step: float) -> ca.Function:
    """(x, u, λ_next) ↦ (Φ, c, J, ∇c, H) of one interval: ``steps`` steps of ``phi``
    ((x, u) → (next state, mean rate), :func:`~ocpar.ocp.multiple_shooting.step_function`)
    of length ``step``, the interval's cost c = step · Σ rates, J = ∂Φ/∂(x, u) (nx, nx + nu),
    ∇c (nx + nu) and H = ∇²_{(x,u)} (c − λ_nextᵀ Φ) (nx + nu, nx + nu), all dense."""
    nx, nu = phi.size1_in(0), phi.size1_in(1)
    x, u, lam = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("lam", nx)
    state, rates = x, []
    for _ in range(steps):
        state, rate = phi(state, u)
        rates.append(rate)
    cost = step * ca.sum1(ca.vertcat(*rates))
    z = ca.vertcat(x, u)
    hessian = ca.hessian(cost - ca.dot(lam, state), z)[0]
    return ca.Function("ms_stage", [x, u, lam], [
        state, cost, ca.densify(ca.jacobian(state, z)), ca.densify(ca.gradient(cost, z)),
        ca.densify(hessian)])


def newton_step_function(stage: ca.Function, n: int, fixed: tuple[int, ...]) -> ca.Function:
    """(w, λ, p) ↦ :data:`STEP_OUTPUTS` of one agent (module docstring): the cost; the KKT
    check's ‖g‖∞, ‖∇_w L‖∞ and ‖∇f‖∞; ``finite`` the sum of every residual (NaN or inf where
    one is: ``fmax`` drops NaN); ∇_p L (2 nx); the Newton step dw (nw), the new multipliers
    (ng) and the end Hessian (nx, nx; rows and columns of a free entry 0) of the KKT matrix
    at (w, λ). ``stage`` as :func:`stage_function` returns, ``n`` intervals, ``fixed`` the
    end entries fixed."""
    nx, nu, nf = stage.size1_in(0), stage.size1_in(1), len(fixed)
    w, lam, p = ca.SX.sym("w", n * (nx + nu)), ca.SX.sym("lam", n * nx + nf), \
        ca.SX.sym("p", 2 * nx)
    x = [p[:nx]] + [w[j * nx:(j + 1) * nx] for j in range(n)]
    u = [w[n * nx + j * nu:n * nx + (j + 1) * nu] for j in range(n)]
    lam_x, mu = [lam[j * nx:(j + 1) * nx] for j in range(n)], lam[n * nx:]
    nxt, cost, jac, grad, hess = zip(*(stage(x[j], u[j], lam_x[j]) for j in range(n)),
                                     strict=True)
    a, b = [j[:, :nx] for j in jac], [j[:, nx:] for j in jac]
    gx, gu = [g[:nx] for g in grad], [g[nx:] for g in grad]
    select = np.zeros((nf, nx))
    select[np.arange(nf), list(fixed)] = 1.0
    # the KKT check of the iterate
    gaps = [x[j + 1] - nxt[j] for j in range(n)]
    ends = x[n][list(fixed)] - p[nx:][list(fixed)]
    stationary = [gx[j] + lam_x[j - 1] - a[j].T @ lam_x[j] for j in range(1, n)]
    stationary += [lam_x[n - 1] + select.T @ mu] + [gu[j] - b[j].T @ lam_x[j] for j in range(n)]
    residuals = ca.vertcat(*gaps, ends, *stationary)
    gradient = ca.vertcat(*gx[1:], *gu)
    grad_p = ca.vertcat(gx[0] - a[0].T @ lam_x[0], -select.T @ mu)
    # the Newton step: backward Riccati recursion, affine in the end rows' multiplier
    offset = [nxt[j] - x[j + 1] for j in range(n)]
    P, s, S = [None] * (n + 1), [None] * (n + 1), [None] * (n + 1)
    P[n], s[n], S[n] = ca.SX(nx, nx), ca.SX(nx, 1), ca.SX(select.T)
    gains = [None] * n
    for j in range(n - 1, -1, -1):
        pa, pb = P[j + 1] @ a[j], P[j + 1] @ b[j]
        v = P[j + 1] @ offset[j] + s[j + 1]
        quu = hess[j][nx:, nx:] + b[j].T @ pb
        qux = hess[j][nx:, :nx] + b[j].T @ pa
        gains[j] = -_solve(quu, ca.horzcat(qux, gu[j] + b[j].T @ v, b[j].T @ S[j + 1]))
        if j:
            P[j] = hess[j][:nx, :nx] + a[j].T @ pa + qux.T @ gains[j][:, :nx]
            s[j] = gx[j] + a[j].T @ v + qux.T @ gains[j][:, nx]
            S[j] = a[j].T @ S[j + 1] + qux.T @ gains[j][:, nx + 1:]
    # forward: dx_j = c_j + D_j μ, du_j = e_j + F_j μ
    c, d = [ca.SX(nx, 1)], [ca.SX(nx, nf)]
    e, f = [], []
    for j in range(n):
        gain = gains[j][:, :nx]
        e.append(gain @ c[j] + gains[j][:, nx])
        f.append(gain @ d[j] + gains[j][:, nx + 1:])
        c.append(a[j] @ c[j] + b[j] @ e[j] + offset[j])
        d.append(a[j] @ d[j] + b[j] @ f[j])
    schur = select @ d[n]
    new_mu = _solve(schur, p[nx:][list(fixed)] - x[n][list(fixed)] - select @ c[n])
    dx = [c[j] + d[j] @ new_mu for j in range(1, n + 1)]
    du = [e[j] + f[j] @ new_mu for j in range(n)]
    new_lam = [-(P[j] @ dx[j - 1] + s[j] + S[j] @ new_mu) for j in range(1, n + 1)]
    hessian = -select.T @ _solve(schur, ca.SX(np.eye(nf))) @ select
    return ca.Function("ms_riccati_step", [w, lam, p], [
        ca.sum1(ca.vertcat(*cost)), ca.norm_inf(ca.vertcat(*gaps, ends)),
        ca.norm_inf(ca.vertcat(*stationary)), ca.norm_inf(gradient),
        ca.sum1(residuals) + ca.sum1(gradient) + ca.sum1(grad_p), grad_p,
        ca.vertcat(*dx, *du), ca.vertcat(*new_lam, new_mu), ca.densify(hessian)],
        ["w", "lam", "p"], list(STEP_OUTPUTS), {"cse": True})


def _solve(a: ca.SX, b: ca.SX) -> ca.SX:
    """x with a x = b (a square) by Gaussian elimination with partial pivoting (the first
    largest entry; the row swaps by ``if_else``): CasADi's symbolic ``solve`` (QR) lost the
    Clohessy–Wiltshire tasks' last digits (their KKT check failed at 1e-12)."""
    n = a.size1()
    rows, rhs = [a[i, :] for i in range(n)], [b[i, :] for i in range(n)]
    for i in range(n):
        for r in range(i + 1, n):   # the largest |a[r, i]|, r ≥ i, into row i
            swap = ca.fabs(rows[r][i]) > ca.fabs(rows[i][i])
            for m in (rows, rhs):
                m[i], m[r] = ca.if_else(swap, m[r], m[i]), ca.if_else(swap, m[i], m[r])
        for r in range(i + 1, n):
            factor = rows[r][i] / rows[i][i]
            rows[r] = rows[r] - factor * rows[i]
            rhs[r] = rhs[r] - factor * rhs[i]
    x: list[ca.SX] = [ca.SX()] * n
    for i in range(n - 1, -1, -1):
        acc = rhs[i]
        for c in range(i + 1, n):
            acc = acc - rows[i][c] * x[c]
        x[i] = acc / rows[i][i]
    return ca.vertcat(*x)


class RiccatiNewton:
    """Newton's method on the KKT system of min Σ_j c_j s.t. x_{j+1} = Φ_j(x_j, u_j),
    x_N[fixed] = x̄_N[fixed] (module docstring) for batches of columns. ``stage`` as
    :func:`stage_function` returns; ``n`` intervals N; ``fixed`` the end entries fixed;
    ``tol`` the acceptance test of :class:`~ocpar.ocp.batch.KktNewton`: ‖g‖∞ ≤ tol (1 + ‖p‖∞)
    and ‖∇_w L‖∞ ≤ tol (1 + ‖∇f‖∞), met by an iterate reached by a step from one that met
    the same test to √tol (or by the guess itself): a step from further away can land just
    inside tol, a solution accurate to tol only (a re-solve from the previous solution's
    multipliers often does), where one more step makes it exact to rounding."""

    def __init__(self, stage: ca.Function, n: int, fixed: tuple[int, ...], tol: float) -> None:
        self.n, self.tol = n, tol
        self.nx, self.nu = stage.size1_in(0), stage.size1_in(1)
        self.nw = n * (self.nx + self.nu)
        self.ng = n * self.nx + len(fixed)
        step = newton_step_function(stage, n, fixed)
        #: The Newton step of many agents, each input's and output's entries a row (size, k):
        #: compiled (:mod:`ocpar.ocp.compiled`), else by numpy.
        self.evaluate = CompiledPoints.of(step) or (lambda *rows: [
            out.T for out in evaluate_columns(step, *(row.T for row in rows))])

    def prepare(self, count: int) -> None:
        """Nothing to build per batch size (as :class:`~ocpar.ocp.batch.KktNewton` has)."""

    def solve(self, w0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray, lbx: np.ndarray,
              ubx: np.ndarray, max_iter: int = 12) -> BatchSolve:
        """Solve k NLPs from guesses ``w0`` (k, nw), parameters p = (x_0, x̄_N) (k, 2 nx) and
        multipliers ``lam_g0`` (k, ng), at most ``max_iter`` Newton steps per column;
        ``lbx``/``ubx`` (nw,) are checked, not imposed. ``extra`` (k, nx²): each accepted
        column's end Hessian d²J*/dx̄_N² (row-major; rows and columns of a free entry 0), NaN
        where a column is not accepted; ``iterations`` the Newton steps taken; ``lam_p``
        −dJ*/dp. The iterates are kept as the compiled function takes them: each entry's
        values over the columns a row."""
        start = time.perf_counter()
        k, nx, tol = len(p), self.nx, self.tol
        w, lam = np.array(w0, float).T.copy(), np.array(lam_g0, float).T.copy()
        p_rows = np.ascontiguousarray(np.asarray(p, float).T)
        primal_scale = 1.0 + np.max(np.abs(p_rows), axis=0)
        f, ok = np.full(k, np.nan), np.zeros(k, bool)
        grad_p, hessians = np.full((2 * nx, k), np.nan), np.full((k, nx * nx), np.nan)
        iterations = np.zeros(k, np.int64)
        near = np.ones(k, bool)    # the last step was taken from within √tol (or none was)
        todo = np.arange(k)
        for step in range(max_iter + 1):
            every = len(todo) == k
            out = dict(zip(STEP_OUTPUTS, self.evaluate(
                *((w, lam, p_rows) if every else (w[:, todo], lam[:, todo], p_rows[:, todo]))),
                strict=True))
            primal, dual = out["primal"][0], out["dual"][0]
            scales = (primal_scale[todo], 1.0 + out["gradient"][0])
            finite = np.isfinite(out["finite"][0])   # w, λ and every residual
            met = _within(primal, dual, scales, tol) & finite & near[todo]
            moving = ~met & finite
            leaving = ~moving if step < max_iter else np.ones(len(todo), bool)
            f[todo[leaving]] = out["cost"][0, leaving]
            grad_p[:, todo[leaving]] = out["grad_p"][:, leaving]
            ok[todo[met]] = True
            hessians[todo[met]] = out["hessian"][:, met].T.reshape(-1, nx, nx).transpose(
                0, 2, 1).reshape(-1, nx * nx)      # column-major entries to row-major
            if step == max_iter or not moving.any():
                break
            near[todo] = _within(primal, dual, scales, np.sqrt(tol))
            if every and moving.all():
                w += out["dw"]
                lam[:] = out["new_lam"]
            else:
                rows = todo[moving]
                w[:, rows] += out["dw"][:, moving]
                lam[:, rows] = out["new_lam"][:, moving]
                todo = rows
            iterations[todo] += 1
        x = w.T.copy()
        ok &= np.all((x >= lbx) & (x <= ubx), axis=1)
        hessians[~ok] = np.nan
        return BatchSolve(x, f, lam.T.copy(), -grad_p.T.copy(), ok, hessians,
                          time.perf_counter() - start, iterations)


def _within(primal: np.ndarray, dual: np.ndarray, scales: tuple[np.ndarray, np.ndarray],
            tol: float) -> np.ndarray:
    """Where ‖g‖∞ ≤ tol · scales[0] and ‖∇_w L‖∞ ≤ tol · scales[1] (NaN: not)."""
    return (primal <= tol * scales[0]) & (dual <= tol * scales[1])
