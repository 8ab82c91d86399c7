"""Batched Newton on the KKT system of multiple shooting between two states by a Riccati
recursion: the equality-constrained NLP of :class:`~ocpar.ocp.MsEndpointShape` (dynamics rows
x_{j+1} = Φ(x_j, u_j), the fixed end entries E x_N = x̄_N) solved stage by stage, each stage's
small matrices stacked over the k columns of a batch.

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

The stage data of all k N stages are one evaluation of one SX function per Newton step
(compiled, :mod:`ocpar.ocp.compiled`; numpy over the points where this host has no C
compiler, :func:`~ocpar.ocp.columns_eval.evaluate_columns`); the recursion is
numpy on (k, nx, nx) arrays. Each column's arithmetic is that of the column alone, so a task's
result does not depend on which tasks share its batch (tested bitwise). Per unicycle solve
this replaces one sparse QR of the whole KKT matrix per Newton step (module
:mod:`ocpar.ocp.batch`) by O(N) small dense solves.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ocpar.ocp.batch import BatchSolve
from ocpar.ocp.columns_eval import evaluate_columns
from ocpar.ocp.compiled import CompiledPoints


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


class RiccatiNewton:
    """Newton's method on the KKT system of min Σ_j c_j s.t. x_{j+1} = Φ_j(x_j, u_j),
    x_N[fixed] = x̄_N[fixed] (module docstring) for batches of columns. ``stage`` as
    :func:`stage_function` returns; ``n`` intervals N; ``fixed`` the end entries fixed;
    ``tol`` the acceptance test of :class:`~ocpar.ocp.batch.KktNewton`: ‖g‖∞ ≤ tol (1 + ‖p‖∞)
    and ‖∇_w L‖∞ ≤ tol (1 + ‖∇f‖∞)."""

    def __init__(self, stage: ca.Function, n: int, fixed: tuple[int, ...], tol: float) -> None:
        self.stage, self.n, self.tol = stage, n, tol
        self.nx, self.nu = stage.size1_in(0), stage.size1_in(1)
        self.fixed = np.asarray(fixed, int)
        self.nw = n * (self.nx + self.nu)
        self.ng = n * self.nx + len(self.fixed)
        #: The stage data at many points, each entry's values a row (size, m): compiled
        #: (:mod:`ocpar.ocp.compiled`), else by numpy.
        self.evaluate = CompiledPoints.of(stage) or (lambda *rows: [
            out.T for out in evaluate_columns(stage, *(row.T for row in rows))])

    def prepare(self, count: int) -> None:
        """Nothing to build per batch size (as :class:`~ocpar.ocp.batch.KktNewton` has)."""

    def solve(self, w0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray, lbx: np.ndarray,
              ubx: np.ndarray, max_iter: int = 12) -> BatchSolve:
        """Solve k NLPs from guesses ``w0`` (k, nw), parameters p = (x_0, x̄_N) (k, 2 nx) and
        multipliers ``lam_g0`` (k, ng), at most ``max_iter`` Newton steps per column;
        ``lbx``/``ubx`` (nw,) are checked, not imposed. ``extra`` (k, nx²): each accepted
        column's end Hessian d²J*/dx̄_N² (row-major; rows and columns of a free entry 0),
        NaN where a column is not accepted; ``iterations`` the Newton steps taken;
        ``lam_p`` −dJ*/dp."""
        start = time.perf_counter()
        k, nx = len(p), self.nx
        w, lam = np.array(w0, float), np.array(lam_g0, float)
        f, ok = np.full(k, np.nan), np.zeros(k, bool)
        grad_p, hessians = np.full((k, 2 * nx), np.nan), np.full((k, nx, nx), np.nan)
        iterations = np.zeros(k, np.int64)
        todo = np.arange(k)
        for step in range(max_iter + 1):
            data = self._stages(w[todo], p[todo], lam[todo])
            f[todo], met, grad_p[todo] = self._check(data, w[todo], p[todo], lam[todo])
            finite = np.all(np.isfinite(w[todo]), axis=1) & np.all(np.isfinite(lam[todo]), 1)
            live = met | (finite & (step < max_iter))
            if not live.all():   # compress keeps the columns last and contiguous
                data = {key: value.compress(live, axis=-1) for key, value in data.items()}
            rows = todo[live]
            met = met[live]
            if not len(rows):
                break
            with np.errstate(all="ignore"):
                dw, new_lam, end_hessian = self._newton_step(data, p[rows])
            ok[rows[met]] = True
            hessians[rows[met]] = end_hessian[met]
            moving = rows[~met]
            w[moving] += dw[~met]
            lam[moving] = new_lam[~met]
            iterations[moving] += 1
            todo = moving
            if not len(todo):
                break
        ok &= np.all((w >= lbx) & (w <= ubx), axis=1)
        hessians[~ok] = np.nan
        return BatchSolve(w, f, lam, -grad_p, ok, hessians.reshape(k, -1),
                          time.perf_counter() - start, iterations)

    def _stages(self, w: np.ndarray, p: np.ndarray, lam: np.ndarray) -> dict[str, np.ndarray]:
        """The stage data of k columns, the columns last: x (N+1, nx, k), u (N, nu, k),
        λ (N, nx, k), μ (nf, k), and per stage (N, …, k): Φ, c, A, B, gx, gu, Hxx, Hxu, Huu."""
        k, nx, nu, n = len(p), self.nx, self.nu, self.n
        x = np.concatenate([p[None, :, :nx], w[:, :n * nx].reshape(k, n, nx).swapaxes(0, 1)]
                           ).transpose(0, 2, 1)
        u = w[:, n * nx:].reshape(k, n, nu).transpose(1, 2, 0)
        lam_x = lam[:, :n * nx].reshape(k, n, nx).transpose(1, 2, 0)
        rows = [np.ascontiguousarray(a.transpose(1, 0, 2)).reshape(len(a[0]), n * k)
                for a in (x[:n], u, lam_x)]
        nxt, cost, jac, grad, hess = self.evaluate(*rows)
        nz = nx + nu
        jac = jac.reshape(nz, nx, n, k).transpose(2, 1, 0, 3)   # column-major entries
        hess = hess.reshape(nz, nz, n, k).transpose(2, 1, 0, 3)
        grad = grad.reshape(nz, n, k).swapaxes(0, 1)
        return {"x": x, "u": u, "lam": lam_x, "mu": lam[:, n * nx:].T,
                "next": nxt.reshape(nx, n, k).swapaxes(0, 1), "cost": cost.reshape(n, k),
                "A": jac[:, :, :nx], "B": jac[:, :, nx:], "gx": grad[:, :nx],
                "gu": grad[:, nx:], "Hxx": hess[:, :nx, :nx], "Hxu": hess[:, :nx, nx:],
                "Huu": hess[:, nx:, nx:]}

    def _check(self, d: dict[str, np.ndarray], w: np.ndarray, p: np.ndarray,
               lam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cost (k,), acceptance (k,) and ∇_p L (k, 2 nx) of k iterates from their stage data."""
        nx, fixed = self.nx, self.fixed
        x, lam_x, mu = d["x"], d["lam"], d["mu"]
        gaps = x[1:] - d["next"]
        ends = x[-1, fixed] - p[:, nx + fixed].T
        primal = np.maximum(np.max(np.abs(gaps), axis=(0, 1)),
                            np.max(np.abs(ends), axis=0, initial=0.0))
        at = _mv(_t(d["A"]), lam_x)                            # A_jᵀ λ_{j+1}
        grad_x = d["gx"][1:] + lam_x[:-1] - at[1:]
        last = lam_x[-1].copy()
        last[fixed] += mu
        grad_u = d["gu"] - _mv(_t(d["B"]), lam_x)
        dual = np.maximum.reduce([np.max(np.abs(grad_x), axis=(0, 1), initial=0.0),
                                  np.max(np.abs(last), axis=0),
                                  np.max(np.abs(grad_u), axis=(0, 1))])
        gradient = np.maximum(np.max(np.abs(d["gx"][1:]), axis=(0, 1), initial=0.0),
                              np.max(np.abs(d["gu"]), axis=(0, 1)))
        grad_p = np.zeros((2 * nx, len(p)))
        grad_p[:nx] = d["gx"][0] - at[0]
        grad_p[nx + fixed] = -mu
        with np.errstate(invalid="ignore"):
            met = ((primal <= self.tol * (1.0 + np.max(np.abs(p), axis=1)))
                   & (dual <= self.tol * (1.0 + gradient))
                   & np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(lam), axis=1))
        cost = d["cost"][0].copy()
        for stage in d["cost"][1:]:   # in stage order (numpy's sum pairs along a contiguous axis)
            cost += stage
        return cost, met, grad_p.T

    def _newton_step(self, d: dict[str, np.ndarray], p: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The Newton step dw (k, nw), the new multipliers (k, ng) and the end Hessians
        (k, nx, nx) of the KKT matrix at k iterates (module docstring)."""
        k, nx, nu, n, fixed = len(p), self.nx, self.nu, self.n, self.fixed
        nf = len(fixed)
        A, B, b = d["A"], d["B"], d["next"] - d["x"][1:]
        P, s = np.zeros((n + 1, nx, nx, k)), np.zeros((n + 1, nx, k))
        S = np.zeros((n + 1, nx, nf, k))
        S[n, fixed, np.arange(nf)] = 1.0
        gains = np.zeros((n, nu, nx + 1 + nf, k))
        for j in range(n - 1, -1, -1):
            a, bj, bt = A[j], B[j], _t(B[j])
            pa, pb = _mm(P[j + 1], a), _mm(P[j + 1], bj)
            v = _mv(P[j + 1], b[j]) + s[j + 1]
            quu = d["Huu"][j] + _mm(bt, pb)
            qux = _t(d["Hxu"][j]) + _mm(bt, pa)
            rhs = np.concatenate([qux, (d["gu"][j] + _mv(bt, v))[:, None],
                                  _mm(bt, S[j + 1])], axis=1)
            gains[j] = -_solve(quu, rhs)
            if j:
                at, qxu = _t(a), _t(qux)
                P[j] = d["Hxx"][j] + _mm(at, pa) + _mm(qxu, gains[j, :, :nx])
                P[j] = 0.5 * (P[j] + _t(P[j]))
                s[j] = d["gx"][j] + _mv(at, v) + _mv(qxu, gains[j, :, nx])
                S[j] = _mm(at, S[j + 1]) + _mm(qxu, gains[j, :, nx + 1:])
        # forward: dx_j = c_j + D_j μ, du_j = e_j + F_j μ
        c, D = np.zeros((n + 1, nx, k)), np.zeros((n + 1, nx, nf, k))
        e, F = np.zeros((n, nu, k)), np.zeros((n, nu, nf, k))
        for j in range(n):
            gain = gains[j, :, :nx]
            e[j] = _mv(gain, c[j]) + gains[j, :, nx]
            F[j] = _mm(gain, D[j]) + gains[j, :, nx + 1:]
            c[j + 1] = _mv(A[j], c[j]) + _mv(B[j], e[j]) + b[j]
            D[j + 1] = _mm(A[j], D[j]) + _mm(B[j], F[j])
        schur = D[n, fixed]                                      # E D_N (nf, nf, k)
        r = p[:, nx + fixed].T - d["x"][n, fixed] - c[n, fixed]
        mu = _solve(schur, r[:, None])[:, 0]
        dx = c[1:] + _mv(D[1:], mu)
        du = e + _mv(F, mu)
        lam = -(_mv(P[1:], dx) + s[1:] + _mv(S[1:], mu))
        hessian = np.zeros((nx, nx, k))
        hessian[fixed[:, None], fixed] = -_solve(schur, np.broadcast_to(
            np.eye(nf)[:, :, None], (nf, nf, k)))
        dw = np.concatenate([dx.transpose(2, 0, 1).reshape(k, -1),
                             du.transpose(2, 0, 1).reshape(k, -1)], axis=1)
        return dw, np.concatenate([lam.transpose(2, 0, 1).reshape(k, -1), mu.T], axis=1), \
            hessian.transpose(2, 0, 1)


# Stacked small matrices with the columns last, (…, r, c, k): each column's arithmetic is
# elementwise over k, in a fixed order (the same bits whatever else shares the batch).

def _t(a: np.ndarray) -> np.ndarray:
    """The transposes (…, c, r, k) of matrices (…, r, c, k)."""
    return a.swapaxes(-3, -2)


def _mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Products a b: (…, r, c, k) × (…, c, m, k) → (…, r, m, k)."""
    out = a[..., :, 0, None, :] * b[..., None, 0, :, :]
    for i in range(1, a.shape[-2]):
        out += a[..., :, i, None, :] * b[..., None, i, :, :]
    return out


def _mv(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Products a v: (…, r, c, k) × (…, c, k) → (…, r, k)."""
    out = a[..., :, 0, :] * v[..., None, 0, :]
    for i in range(1, a.shape[-2]):
        out += a[..., :, i, :] * v[..., None, i, :]
    return out


def _solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with a x = b: (n, n, k), (n, m, k) → (n, m, k), by Gaussian elimination with
    partial pivoting (the first largest entry), column by column; a singular column gives
    inf or NaN."""
    a, b = a.copy(), b.copy()
    n = len(a)
    for i in range(n):
        for r in range(i + 1, n):   # the largest |a[r, i]|, r ≥ i, into row i
            swap = np.abs(a[r, i]) > np.abs(a[i, i])
            if swap.any():
                for matrix in (a, b):
                    top = np.where(swap, matrix[r], matrix[i])
                    matrix[r] = np.where(swap, matrix[i], matrix[r])
                    matrix[i] = top
        for r in range(i + 1, n):
            factor = a[r, i] / a[i, i]
            a[r, i:] -= factor * a[i, i:]
            b[r] -= factor * b[i]
    x = np.empty_like(b)
    for i in range(n - 1, -1, -1):
        acc = b[i].copy()
        for c in range(i + 1, n):
            acc -= a[i, c] * x[c]
        x[i] = acc / a[i, i]
    return x
