"""Batched convex QPs: many columns of one parametric convex quadratic programme solved at
once by a primal–dual interior-point method (Mehrotra's predictor–corrector) in numpy.

The NLP min f(x, p) s.t. lbg ≤ g(x, p) ≤ ubg, lbx ≤ x ≤ ubx is a convex QP in x where f
has a constant, positive semidefinite Hessian in x and g is affine in x (checked exactly on
the CasADi expressions, :meth:`ConvexQp.of`); its equality rows (lbg = ubg, and lbx = ubx)
must have a Jacobian that does not depend on p either. All columns then share the structure:

- the equalities A x = b(p) are eliminated once per shape: x = x_p(p) + Z y, with x_p the
  least-norm solution and Z an orthonormal basis of A's null space on the entries A touches
  (the other entries stay as they are);
- the inequalities (each finite bound of a row or entry, as r(y, p) = G(p) y + r_0(p) ≥ 0)
  and the reduced Hessian H_r (constant) give, per iteration and column, the normal
  equations (H_r + Gᵀ diag(z/s) G) dy = rhs. Entries of y that share no inequality row with
  one another and no Hessian entry (e.g. elastic slacks, one per keep-out slot) are
  eliminated by their diagonal block, so the dense system is only as large as the others.

Each column starts from the least-squares point of its rows and stops when its primal and
dual residuals and its complementarity are at most ``tol`` (scaled), or when its normal
equations no longer factorise; the point is then taken back to x with CasADi's multipliers
(λ_g, λ_x; λ_p = −∇_p L) and checked by the batched solvers' own KKT test
(:func:`~ocpar.ocp.batch.kkt_met`), which gives each column's success. A column that fails
it (its multipliers lose digits as z/s spreads near the solution) is solved once more with
its active rows (z > s) as equalities; a column that still fails is the caller's to
re-solve (e.g. by IPOPT). Columns are solved in blocks of :data:`BLOCK`, each computed as it
would be alone (per-column products only).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from functools import lru_cache

import casadi as ca
import numpy as np

from ocpar.ocp.batch import BatchSolve, kkt_met, kkt_residuals

#: Columns per block at most (larger batches are split): its arrays stay in cache (CPU time
#: of 700 keep-out point masses: 3.5 s in blocks of 64 against 4.4 s in one, 2026-12).
BLOCK = 64
#: Interior-point iterations at most per column.
MAX_ITER = 60
#: Steps of iterative refinement of each Newton step (the normal equations lose digits
#: where the weights z/s of active and inactive rows lie far apart).
REFINEMENTS = 1
#: Active-set solves at most per column whose interior point fails the KKT check.
ACTIVE_SET_PASSES = 3
#: Fraction of the step to the boundary of s, z ≥ 0 taken.
STEP_FRACTION = 0.995
#: The Hessian counts as positive semidefinite where its smallest eigenvalue is at least
#: −this · its largest |entry|.
PSD_RTOL = 1e-12


class ConvexQp:
    """A parametric convex QP (module docstring) in the reduced variables y, built once per
    shape by :meth:`of`; :meth:`solve` solves k columns (parameter rows) at once."""

    def __init__(self, name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                 bounds: tuple[np.ndarray, ...], eq: np.ndarray, tol: float,
                 kkt_tol: float) -> None:
        lbg, ubg, lbx, ubx = (np.asarray(b, float) for b in bounds)
        self.bounds, self.tol, self.kkt_tol = (lbg, ubg, lbx, ubx), tol, kkt_tol
        nx, ng = x.numel(), g.numel()
        self.nx, self.ng = nx, ng
        rows = ca.vertcat(g, x)                       # G = (g, x) with bounds (lb, ub)
        lower, upper = np.concatenate([lbg, lbx]), np.concatenate([ubg, ubx])
        a = np.asarray(ca.evalf(ca.jacobian(rows[eq.tolist()], x)))
        touched = np.flatnonzero(np.any(a != 0, axis=0))
        kept = np.setdiff1d(np.arange(nx), touched)
        u, sv, vt = np.linalg.svd(a[:, touched]) if len(touched) else (None, np.zeros(0), None)
        rank = int(np.sum(sv > sv.max(initial=0.0) * max(a.shape) * np.finfo(float).eps))
        z_basis = np.zeros((nx, 0))
        if len(touched):
            z_basis = np.zeros((nx, len(touched) - rank))
            z_basis[touched] = vt[rank:].T
            pinv = vt[:rank].T / sv[:rank] @ u[:, :rank].T    # A_E⁺ (|E|, n_eq)
        identity = np.zeros((nx, len(kept)))
        identity[kept, np.arange(len(kept))] = 1.0
        basis = np.hstack([z_basis, identity])            # Z (nx, ny)
        x_zero = ca.substitute(rows[eq.tolist()], x, ca.DM.zeros(nx))
        target = ca.DM(lower[eq]) - x_zero                 # A x = b(p)
        x_p = ca.SX.zeros(nx)
        if len(touched):
            x_p[touched.tolist()] = ca.mtimes(ca.DM(pinv), target)
        y = ca.SX.sym("y", basis.shape[1])
        x_of_y = x_p + ca.mtimes(ca.sparsify(ca.DM(basis)), y)
        self.x_of = ca.Function(f"{name}_x", [y, p], [x_of_y])
        f_y = ca.substitute(f, x, x_of_y)
        hessian, gradient = ca.hessian(f_y, y)
        self.h = np.asarray(ca.evalf(hessian))
        # inequalities r(y, p) ≥ 0: each finite lower and upper bound of a row not an equality
        free = np.setdiff1d(np.arange(ng + nx), eq)
        low = free[np.isfinite(lower[free])]
        high = free[np.isfinite(upper[free])]
        rows_y = ca.substitute(rows, x, x_of_y)
        ineq = ca.vertcat(rows_y[low.tolist()] - ca.DM(lower[low]),
                          ca.DM(upper[high]) - rows_y[high.tolist()])
        signs = np.concatenate([-np.ones(len(low)), np.ones(len(high))])
        self.separate, self.dense = _separable(self.h, ca.jacobian(ineq, y).sparsity())
        sep, dense = self.separate.tolist(), self.dense.tolist()
        pattern = np.asarray(ca.DM(ca.jacobian(ineq, y).sparsity(), 1)) != 0
        sep_rows = pattern[:, sep]
        owner = np.where(sep_rows.any(axis=1), np.argmax(sep_rows, axis=1), len(sep))
        # the inequalities ordered by the separable entry they involve (those first)
        order = np.argsort(owner, kind="stable")
        ineq, owner = ineq[order.tolist()], owner[order]
        jac = ca.jacobian(ineq, y)
        #: (kind, row of G) of each inequality: kind −1 a lower bound, +1 an upper one
        self.signs = signs[order]
        self.rows = np.concatenate([low, high]).astype(int)[order]
        self.n_sep_rows = int(np.sum(owner < len(sep)))
        self.starts = np.searchsorted(owner, np.arange(len(sep)))
        #: each inequality row's separable entry (index into ``separate``), and which have one
        self.row_owner = np.minimum(owner, max(len(sep) - 1, 0))
        self.has_owner = owner < len(sep)
        # the pairs of inequality rows of one separable entry: both with dense entries
        # (``pairs``), or one (``folds``: (that row, the other), its term a multiple of g gᵀ)
        with_dense = (np.asarray(ca.DM(jac.sparsity(), 1)) != 0)[:, dense].any(axis=1)
        pairs = np.array([(a, b) for j in range(len(sep))
                          for a, b in itertools.combinations(np.flatnonzero(owner == j), 2)],
                         np.intp).reshape(-1, 2)
        first, second = with_dense[pairs[:, 0]], with_dense[pairs[:, 1]]
        self.pairs = tuple(pairs[first & second].T)
        self.folds = tuple(np.concatenate([pairs[first & ~second], pairs[~first & second][:, ::-1]
                                           ]).T)
        ineq_zero = ca.substitute(ineq, y, ca.DM.zeros(y.numel()))
        sep_coefficient = ca.sum2(jac[:, sep]) if sep else ca.SX.zeros(ineq.numel())
        self.data = ca.Function(f"{name}_qp_data", [p], [
            ca.substitute(gradient, y, ca.DM.zeros(y.numel())), ineq_zero,
            ca.densify(jac[:, dense]), sep_coefficient])
        lam_g, lam_x = ca.SX.sym("lam_g", ng), ca.SX.sym("lam_x", nx)
        lagrangian = f + ca.dot(lam_g, g)
        self.gradient_x = ca.Function(f"{name}_grad_x", [x, p, lam_g, lam_x],
                                      [ca.gradient(lagrangian, x) + lam_x])
        self.gradient_p = ca.Function(f"{name}_grad_p", [x, p, lam_g],
                                      [ca.gradient(lagrangian, p)])
        self.cost = ca.Function(f"{name}_f", [x, p], [f])
        self.residuals = kkt_residuals(name, x, p, f, g)
        #: p ↦ the rows' Jacobian (ng + nx, nx), the rows and ∇f at x = 0
        self.affine = ca.Function(f"{name}_affine", [p], ca.substitute(
            [ca.densify(ca.jacobian(rows, x)), rows, ca.gradient(f, x)], [x],
            [ca.SX.zeros(nx)]))
        self.hessian_x = np.asarray(ca.evalf(ca.hessian(f, x)[0]))
        self.row_bounds = lower, upper
        self.eq = eq
        self._mapped = lru_cache(maxsize=16)(self._map)
        # the equality multipliers: Aᵀ λ_eq = −(the rest of ∇_x L), least squares
        self.eq_solve = np.linalg.pinv(a.T)

    def _map(self, k: int) -> tuple[ca.Function, ...]:
        """This QP's functions mapped over k columns."""
        return tuple(function.map(k, "serial") for function in (
            self.data, self.x_of, self.gradient_x, self.cost, self.gradient_p, self.residuals))

    @classmethod
    def of(cls, name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
           bounds: tuple[np.ndarray, ...], tol: float, kkt_tol: float) -> ConvexQp | None:
        """The batched QP of the NLP, or None where it is not a convex QP of the module
        docstring's form (f not quadratic with a constant PSD Hessian in x, g not affine in
        x, or an equality row's Jacobian depending on p)."""
        lbg, ubg, lbx, ubx = (np.asarray(b, float) for b in bounds)
        jac = ca.jacobian(g, x)
        hessian = ca.hessian(f, x)[0]
        if ca.depends_on(jac, x) or ca.depends_on(hessian, ca.vertcat(x, p)):
            return None
        h = np.asarray(ca.evalf(hessian))
        if h.size and np.linalg.eigvalsh(h).min() < -PSD_RTOL * max(np.abs(h).max(), 1.0):
            return None
        eq = np.flatnonzero(np.concatenate([lbg == ubg, lbx == ubx]))
        eq_g = eq[eq < g.numel()]
        if len(eq_g) and ca.depends_on(jac[eq_g.tolist(), :], p):
            return None
        return cls(name, x, p, f, g, bounds, eq, tol, kkt_tol)

    def solve(self, p: np.ndarray) -> BatchSolve:
        """Solve the columns ``p`` (k, np): x (k, nx), f, λ_g, λ_p (= −∇_p L), λ_x, the
        success of each column (:func:`~ocpar.ocp.batch.kkt_met` to ``kkt_tol``) and its
        interior-point iterations; in blocks of at most :data:`BLOCK` columns, each column
        computed as it would be alone in its block."""
        start = time.perf_counter()
        parts = [self._solve_block(p[i:i + BLOCK]) for i in range(0, len(p), BLOCK)]
        x, f, lam_g, lam_p, ok, lam_x, iterations = (np.concatenate(part)
                                                      for part in zip(*parts, strict=True))
        return BatchSolve(x, f, lam_g, lam_p, ok, np.zeros((len(p), 0)),
                          time.perf_counter() - start, iterations=iterations, lam_x=lam_x)

    def _solve_block(self, p: np.ndarray) -> tuple[np.ndarray, ...]:
        """:meth:`solve` of one block: x, f, λ_g, λ_p, success, λ_x, iterations."""
        k = len(p)
        data, x_of, gradient_x, cost, gradient_p, residuals = self._mapped(k)
        c, r0, g_dense, g_sep = (np.asarray(out) for out in data(p.T))
        c, r0, g_sep = c.T, r0.T, g_sep.T
        m = r0.shape[1]
        g_dense = g_dense.reshape(m, k, -1).transpose(1, 0, 2) if len(self.dense) else \
            np.zeros((k, m, 0))
        y, slack, z, iterations = self._interior_point(c, r0, g_dense, g_sep)
        x = np.asarray(x_of(y.T, p.T)).T
        lam = np.zeros((k, self.ng + self.nx))
        np.add.at(lam.T, self.rows, (self.signs[None] * z).T)
        rest = np.asarray(gradient_x(x.T, p.T, lam[:, :self.ng].T, lam[:, self.ng:].T)).T
        lam[:, self.eq] = -_each(self.eq_solve, rest)
        ok = self._kkt_met(x, p, lam, residuals)
        failed = np.flatnonzero(~ok)
        if len(failed):   # again, each with its active set as equalities
            jac, at_zero, gradient = (np.asarray(out) for out in self.affine.map(len(failed))(
                p[failed].T))
            jac = jac.reshape(len(at_zero), len(failed), self.nx).transpose(1, 0, 2)
            for j, i in enumerate(failed.tolist()):
                x[i], lam[i], ok[i] = self._polished(
                    p[i], (jac[j], at_zero[:, j], gradient[:, j]), z[i] > slack[i])
        lam_g, lam_x = lam[:, :self.ng], lam[:, self.ng:]
        f = np.asarray(cost(x.T, p.T)).ravel()
        lam_p = -np.asarray(gradient_p(x.T, p.T, lam_g.T)).T
        return x, f, lam_g, lam_p, ok, lam_x, iterations

    def _kkt_met(self, x: np.ndarray, p: np.ndarray, lam: np.ndarray,
                 residuals: ca.Function) -> np.ndarray:
        """:func:`~ocpar.ocp.batch.kkt_met` of points x (k, nx) with multipliers
        ``lam`` (k, ng + nx) (``residuals``: :attr:`residuals` mapped over k)."""
        lam_g, lam_x = lam[:, :self.ng], lam[:, self.ng:]
        g, stationarity, gradient = (np.asarray(r) for r in residuals(
            x.T, p.T, lam_g.T, lam_x.T))
        return kkt_met(x, p, lam_g, lam_x, g.T, stationarity.ravel(), gradient.ravel(),
                       self.bounds, self.kkt_tol)

    def _polished(self, p: np.ndarray, affine: tuple[np.ndarray, ...], active: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, bool]:
        """One column's point and multipliers from :meth:`_on_active_set` (``affine``: its
        rows' Jacobian, values and ∇f at x = 0) with the rows ``active`` (z > s), rows
        whose multiplier has the wrong sign dropped and solved again (at most
        :data:`ACTIVE_SET_PASSES` times), and whether it meets the KKT check."""
        active = active.copy()
        for _ in range(ACTIVE_SET_PASSES):
            x, lam = self._on_active_set(affine, active)
            if self._kkt_met(x[None], p[None], lam[None], self.residuals)[0]:
                return x, lam, True
            wrong = active & (lam[self.rows] * self.signs < 0)
            if not wrong.any():
                break
            active &= ~wrong
        return x, lam, False

    def _on_active_set(self, affine: tuple[np.ndarray, ...], active: np.ndarray
                       ) -> tuple[np.ndarray, ...]:
        """One column's point x (nx) and multipliers (ng + nx) with its equality rows and
        the inequalities ``active`` (m,) at their bounds, the others dropped: the KKT system
        of that equality-constrained QP (least squares where it is singular). Where the
        interior point's own have lost digits (its normal equations ill-conditioned as z/s
        spreads near the solution); the KKT check then decides."""
        lower, upper = self.row_bounds
        picked = self.rows[active]
        rows = np.concatenate([self.eq, picked])
        bound = np.concatenate([lower[self.eq],
                                np.where(self.signs[active] < 0, lower[picked], upper[picked])])
        jac, at_zero, gradient = affine
        jac = jac[rows]
        n = self.nx
        kkt = np.block([[self.hessian_x, jac.T], [jac, np.zeros((len(rows), len(rows)))]])
        rhs = np.concatenate([-gradient.ravel(), bound - at_zero.ravel()[rows]])
        try:
            solution = np.linalg.solve(kkt, rhs)
        except np.linalg.LinAlgError:   # dependent rows: the least-squares solution
            solution = np.linalg.lstsq(kkt, rhs, rcond=None)[0]
        lam = np.zeros(self.ng + n)
        lam[rows] = solution[n:]
        return solution[:n], lam

    def _interior_point(self, c: np.ndarray, r0: np.ndarray, g_dense: np.ndarray,
                        g_sep: np.ndarray) -> tuple[np.ndarray, ...]:
        """Mehrotra's predictor–corrector on min ½ yᵀH_r y + cᵀy s.t. G y + r_0 ≥ 0 for
        each column (c (k, ny), r_0 (k, m), G's dense columns (k, m, n_dense) and its
        separable entries' coefficients (k, m)): y (k, ny), the rows' slacks s (k, m) and
        multipliers z (k, m), both ≥ 0, and the iterations of each column. A column stops
        where its residuals are at most ``tol`` (scaled), or where its normal equations no
        longer factorise."""
        k, m = r0.shape
        scale_d = 1.0 + np.max(np.abs(c), axis=1, initial=0.0)
        scale_p = 1.0 + np.max(np.abs(r0), axis=1, initial=0.0)
        # the start: y minimising ½ yᵀH_r y + cᵀy + ½ |G y + r_0|², s its rows (at least 1),
        # z the square root of the cost's scale (fewer iterations, measured: 14 against 18)
        solve, _ = self._factor(np.ones((k, m)), g_dense, g_sep)
        y = solve(-c - self._transposed(r0, g_dense, g_sep))
        s = np.maximum(self._rows(y, g_dense, g_sep) + r0, 1.0)
        z = np.repeat(np.sqrt(scale_d)[:, None], m, axis=1)
        iterations = np.zeros(k, np.int64)
        done = np.zeros(k, bool)
        for _ in range(MAX_ITER):
            live = np.flatnonzero(~done)
            if not len(live):
                break
            cl, gd, gs = c[live], g_dense[live], g_sep[live]
            yl, sl, zl = y[live], s[live], z[live]
            r_p = self._rows(yl, gd, gs) + r0[live] - sl
            r_d = _each(self.h, yl) + cl - self._transposed(zl, gd, gs)
            mu = np.mean(sl * zl, axis=1) if m else np.zeros(len(live))
            met = ((np.max(np.abs(r_p), axis=1, initial=0.0) <= self.tol * scale_p[live])
                   & (np.max(np.abs(r_d), axis=1) <= self.tol * scale_d[live])
                   & (np.max(sl * zl, axis=1, initial=0.0) <= self.tol * scale_d[live]))
            done[live[met]] = True
            if met.all():
                break
            keep = ~met
            live, cl, gd, gs = live[keep], cl[keep], gd[keep], gs[keep]
            yl, sl, zl, r_p, r_d, mu = (a[keep] for a in (yl, sl, zl, r_p, r_d, mu))
            solve, factored = self._factor(zl / sl, gd, gs)
            done[live[~factored]] = True   # weights too far apart: the KKT check judges
            system = (solve, r_d, r_p, sl, zl, gd, gs)
            dy, ds, dz = self._direction(sl * zl, *system)
            alpha = np.minimum(_step(sl, ds), _step(zl, dz))[:, None]
            mu_aff = np.mean((sl + alpha * ds) * (zl + alpha * dz), axis=1)
            sigma = (mu_aff / mu) ** 3
            dy, ds, dz = self._direction(sl * zl + ds * dz - (sigma * mu)[:, None], *system)
            alpha = STEP_FRACTION * np.minimum(np.minimum(_step(sl, ds), _step(zl, dz)), 1 /
                                               STEP_FRACTION)[:, None]
            step = live[factored]
            y[step], s[step], z[step] = ((v + alpha * dv)[factored] for v, dv in
                                         ((yl, dy), (sl, ds), (zl, dz)))
            iterations[step] += 1
        return y, s, z, iterations

    def _direction(self, r_c: np.ndarray, solve: Callable[[np.ndarray], np.ndarray],
                   r_d: np.ndarray, r_p: np.ndarray, s: np.ndarray, z: np.ndarray,
                   gd: np.ndarray, gs: np.ndarray) -> tuple[np.ndarray, ...]:
        """The Newton step (dy, ds, dz) for the complementarity target r_c (s∘z − that),
        the dual and primal residuals r_d, r_p, from the normal equations' ``solve`` with
        :data:`REFINEMENTS` steps of iterative refinement on their residual."""
        rhs = -r_d - self._transposed((r_c + z * r_p) / s, gd, gs)
        dy = solve(rhs)
        for _ in range(REFINEMENTS):
            dy += solve(rhs - _each(self.h, dy) - self._transposed(z / s * self._rows(dy, gd, gs),
                                                             gd, gs))
        ds = self._rows(dy, gd, gs) + r_p
        return dy, ds, -(r_c + z * ds) / s

    def _rows(self, v: np.ndarray, gd: np.ndarray, gs: np.ndarray) -> np.ndarray:
        """G v (k, m) for directions v (k, ny)."""
        out = (gd @ v[:, self.dense, None])[..., 0]
        if len(self.separate):
            out += np.where(self.has_owner, gs * v[:, self.separate][:, self.row_owner], 0.0)
        return out

    def _transposed(self, w: np.ndarray, gd: np.ndarray, gs: np.ndarray) -> np.ndarray:
        """Gᵀ w (k, ny) for row weights w (k, m)."""
        out = np.zeros((len(w), self.h.shape[0]))
        out[:, self.dense] = (w[:, None] @ gd)[:, 0]
        if len(self.separate):
            out[:, self.separate] = self._sum_by_owner(gs * w)
        return out

    def _sum_by_owner(self, values: np.ndarray) -> np.ndarray:
        """Sums over the rows of each separable entry (axis 1 of ``values`` (k, m, ...))."""
        return np.add.reduceat(values[:, :self.n_sep_rows], self.starts, axis=1)

    def _factor(self, weights: np.ndarray, gd: np.ndarray, gs: np.ndarray
                ) -> tuple[Callable[[np.ndarray], np.ndarray], np.ndarray]:
        """The solver of (H_r + Gᵀ diag(weights) G) dy = rhs, batched, the separable entries
        eliminated by their diagonal block, and the columns (k,) where it factorised. The
        Schur complement on the dense entries is summed in its cancellation-free form: an
        entry j with Hessian h_j, rows r of weight W_r, coefficient c_r and dense part g_r
        (a pair's term with one g_r' = 0 added to the other row's weight),
        and M_j = h_j + Σ W_r c_r², gives
        Σ_r (h_j / M_j) W_r g_r g_rᵀ + Σ_{r<r'} (W_r W_r' / M_j) d d ᵀ, d = c_r' g_r − c_r g_r'
        (no difference of large terms where a weight is huge, near an active row)."""
        dense, sep = self.dense, self.separate
        h_dd = self.h[np.ix_(dense, dense)]
        if not len(sep):
            factor, ok = _cholesky(h_dd + (gd * weights[..., None]).transpose(0, 2, 1) @ gd)
            return (lambda rhs: _cho_solve(factor, rhs)), ok
        h_s = np.diagonal(self.h)[sep]
        m_ss = h_s[None] + self._sum_by_owner(gs * gs * weights)
        direct = np.where(self.has_owner, weights * (h_s / m_ss)[:, self.row_owner], weights)
        row, other = self.folds
        np.add.at(direct, (slice(None), row), weights[:, row] * weights[:, other]
                  * gs[:, other] ** 2 / m_ss[:, self.row_owner[row]])
        first, second = self.pairs
        owner = self.row_owner[first]
        d = gs[:, second, None] * gd[:, first] - gs[:, first, None] * gd[:, second]
        pair_weight = weights[:, first] * weights[:, second] / m_ss[:, owner]
        schur = (h_dd + (gd * direct[..., None]).transpose(0, 2, 1) @ gd
                 + (d * pair_weight[..., None]).transpose(0, 2, 1) @ d)
        m_sd = self._sum_by_owner(gd * (weights * gs)[..., None])
        factor, ok = _cholesky(schur)

        def solve(rhs: np.ndarray) -> np.ndarray:
            r_d, r_s = rhs[:, dense], rhs[:, sep]
            dy_d = _cho_solve(factor, r_d - ((r_s / m_ss)[:, None] @ m_sd)[:, 0])
            out = np.empty_like(rhs)
            out[:, dense] = dy_d
            out[:, sep] = (r_s - (m_sd @ dy_d[..., None])[..., 0]) / m_ss
            return out
        return solve, ok


def _each(matrix: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``matrix`` times each row of ``vectors`` (k, n), one product per row: a row's result
    does not depend on the others (a matrix product of all k rows may block them by k)."""
    return (matrix @ vectors[..., None])[..., 0]


def _cholesky(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of symmetric matrices (k, n, n) and which (k,) are positive
    definite (the others' factor the identity)."""
    try:
        return np.linalg.cholesky(matrices), np.ones(len(matrices), bool)
    except np.linalg.LinAlgError:
        ok = np.ones(len(matrices), bool)
        factors = np.empty_like(matrices)
        for i, matrix in enumerate(matrices):
            try:
                factors[i] = np.linalg.cholesky(matrix)
            except np.linalg.LinAlgError:
                ok[i] = False
                factors[i] = np.eye(len(matrix))
        return factors, ok


def _cho_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x with L Lᵀ x = rhs for lower factors L (k, n, n) and rhs (k, n)."""
    half = np.linalg.solve(factor, rhs[..., None])
    return np.linalg.solve(factor.transpose(0, 2, 1), half)[..., 0]


def _step(v: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """The largest α ≤ 1 with v + α dv ≥ 0, per row."""
    with np.errstate(divide="ignore"):
        ratio = np.where(dv < 0, -v / dv, np.inf)
    return np.minimum(1.0, np.min(ratio, axis=1, initial=np.inf))


def _separable(h: np.ndarray, pattern: ca.Sparsity) -> tuple[np.ndarray, np.ndarray]:
    """Entries of y eliminated by their diagonal block (module docstring): greedily, those in
    at least one inequality row (those in the fewest first), sharing no row with another one
    chosen, with no Hessian entry off the diagonal; and the others (both sorted)."""
    jac = np.asarray(ca.DM(pattern, 1)) != 0
    taken = np.zeros(jac.shape[0], bool)
    chosen: list[int] = []
    for j in np.argsort(jac.sum(axis=0), kind="stable").tolist():   # fewest rows first
        rows = jac[:, j]
        if (rows.any() and not (taken & rows).any()
                and not np.any(np.delete(h[j], j)) and h[j, j] >= 0):
            chosen.append(j)
            taken |= rows
    sep = np.sort(np.array(chosen, np.intp))
    return sep, np.setdiff1d(np.arange(h.shape[0]), sep)
