"""Limits by a guessed active set: an NLP with limits, batched on the KKT Newton kernel.

The NLP min f(x, p) s.t. g(x, p) = 0, lo ≤ c(x, p) ≤ hi (the limit rows c: path rows and
bounded entries of x, each with a finite lower or upper bound or both) is solved, one column
per task, as a sequence of equality-constrained NLPs on which :class:`~ocpar.ocp.batch.KktNewton`
takes its Newton steps: each limit row i has a mask (a_i, b_i) ∈ {(0, 0), (1, 0), (0, 1)}
(inactive, at its lower bound, at its upper bound), parameters of the equality NLP

    min f(x, p) + ½ Σ (a_i + b_i) μ_i²   s.t.   g(x, p) = 0,
    a_i (c_i − lo_i) + b_i (c_i − hi_i) + (1 − a_i − b_i) μ_i = 0

in (x, μ): an active row is held at its bound (μ_i = 0 by stationarity in μ_i), an inactive
row forces μ_i = 0 and its multiplier to 0 (stationarity in μ_i), so the KKT matrix stays
regular whatever the mask and one compiled kernel serves every active set. After each solve
the mask of each column is corrected as a primal–dual active-set method does: an inactive row
beyond its bound becomes active at it, an active row whose multiplier has the wrong sign
(λ < 0 at an upper bound, λ > 0 at a lower one; CasADi's L = f + λᵀg) becomes inactive, and
a column whose mask no longer changes is done. The caller checks the result against the
NLP's own KKT conditions (:func:`~ocpar.ocp.batch.kkt_met`) before it accepts it.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from ocpar.ocp.batch import BatchSolve, KktNewton

#: Corrections of the active set at most (each a batched Newton solve of the columns left).
MAX_CORRECTIONS = 6

#: The Newton steps' own test is this factor below ``tol``: with nonlinear limit rows (a norm)
#: a column that stops just below ``tol`` missed the caller's KKT check on ~1 in 5 solves,
#: one more (quadratic) step puts it far below.
TOL_FACTOR = 1e-2


@dataclass
class ActiveSetSolve:
    """Outputs of :meth:`ActiveSetNewton.solve` for k columns: ``x`` (k, nx), ``f`` (k,),
    ``lam_g`` (k, ng) of the equations, ``lam_c`` (k, nc) of the limit rows (λ ≥ 0 at an
    upper bound, ≤ 0 at a lower one), ``lam_p`` (k, np), ``done`` (k,): the Newton solve
    met its test and the active set stood still (the caller's KKT check decides),
    ``iterations`` (k,) the Newton steps taken."""

    x: np.ndarray
    f: np.ndarray
    lam_g: np.ndarray
    lam_c: np.ndarray
    lam_p: np.ndarray
    done: np.ndarray
    iterations: np.ndarray


class ActiveSetNewton:
    """The NLP min f(x, p) s.t. g(x, p) = 0, ``lower`` ≤ c(x, p) ≤ ``upper`` (SX expressions;
    bounds (nc,) with ±inf where a side is open) by masked equality NLPs on
    :class:`~ocpar.ocp.batch.KktNewton` (module docstring), ``tol`` the relative tolerance
    of a limit's activity (its Newton steps' test :data:`TOL_FACTOR` below it)."""

    def __init__(self, name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX, c: ca.SX,
                 lower: np.ndarray, upper: np.ndarray, tol: float) -> None:
        self.nx, self.np, self.ng, self.nc = x.numel(), p.numel(), g.numel(), c.numel()
        self.lower, self.upper, self.tol = np.asarray(lower, float), np.asarray(upper, float), tol
        mu, at_lower, at_upper = (ca.SX.sym(s, self.nc) for s in ("mu", "at_lower", "at_upper"))
        lo = np.where(np.isfinite(self.lower), self.lower, 0.0)
        hi = np.where(np.isfinite(self.upper), self.upper, 0.0)
        rows = at_lower * (c - lo) + at_upper * (c - hi) + (1 - at_lower - at_upper) * mu
        cost = f + 0.5 * ca.dot(at_lower + at_upper, mu**2)
        self.newton = KktNewton(name, ca.vertcat(x, mu), ca.vertcat(p, at_lower, at_upper),
                                cost, ca.vertcat(g, rows), 1, tol * TOL_FACTOR)
        self.rows = ca.Function(f"{name}_limits", [x, p], [c])
        self._rows_of = lru_cache(maxsize=16)(lambda k: self.rows.map(k, "serial"))

    def solve(self, x0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray, rounds: int
              ) -> ActiveSetSolve:
        """Solve k columns from ``x0`` (k, nx), ``p`` (k, np) and the equations' multipliers
        ``lam_g0`` (k, ng), the first active set the limits ``x0`` meets or breaks, each
        equality NLP by ``rounds`` Newton steps at most, at most :data:`MAX_CORRECTIONS`
        corrections of the set."""
        k = len(p)
        x = np.array(x0, float)
        c = self._rows(x, p)
        at_lower, at_upper = self._beyond(c, 1.0)
        lam = np.hstack([lam_g0, np.zeros((k, self.nc))])
        f, lam_p = np.full(k, np.nan), np.full((k, self.np), np.nan)
        done, iterations = np.zeros(k, bool), np.zeros(k, int)
        todo = np.arange(k)
        for _ in range(MAX_CORRECTIONS):
            masks = np.hstack([p[todo], at_lower[todo], at_upper[todo]])
            start = np.hstack([x[todo], np.zeros((len(todo), self.nc))])
            batch = self._newton(start, masks, lam[todo], rounds)
            x[todo], f[todo], lam[todo] = batch.x[:, :self.nx], batch.f, batch.lam_g
            lam_p[todo] = batch.lam_p[:, :self.np]
            iterations[todo] += batch.iterations
            lam_c = batch.lam_g[:, self.ng:]
            wrong = self.tol * (1 + np.max(np.abs(batch.lam_g), axis=1, keepdims=True))
            was_lower, was_upper = at_lower[todo], at_upper[todo]
            beyond_lower, beyond_upper = self._beyond(self._rows(x[todo], p[todo]), -1.0)
            active = was_lower | was_upper
            lower = np.where(active, was_lower & ~(lam_c > wrong), beyond_lower)
            upper = np.where(active, was_upper & ~(lam_c < -wrong), beyond_upper)
            changed = np.any((lower != was_lower) | (upper != was_upper), axis=1)
            at_lower[todo], at_upper[todo] = lower, upper
            done[todo] = batch.success & ~changed
            todo = todo[~done[todo] & batch.success]
            if not len(todo):
                break
        # an inactive row's multiplier is 0 (stationarity in its μ), not rounding's ±1e-16
        lam_c = np.where(at_lower | at_upper, lam[:, self.ng:], 0.0)
        return ActiveSetSolve(x, f, lam[:, :self.ng], lam_c, lam_p, done,
                              iterations)

    def _newton(self, x0: np.ndarray, p: np.ndarray, lam0: np.ndarray, rounds: int
                ) -> BatchSolve:
        """The masked NLPs' Newton solve of the columns x0, p, lam0; where CasADi raises
        (e.g. a singular KKT matrix of a column whose limits cannot all hold), column by
        column, a column that raises alone failed (NaN)."""
        n = self.nx + self.nc
        free = np.full(n, -np.inf), np.full(n, np.inf)
        try:
            return self.newton.solve(x0, p, lam0, *free, rounds)
        except RuntimeError:
            pass
        rows = []
        for i in range(len(p)):
            try:
                rows.append(self.newton.solve(x0[i:i + 1], p[i:i + 1], lam0[i:i + 1], *free,
                                              rounds))
            except RuntimeError:
                nan = np.full((1, n), np.nan)
                rows.append(BatchSolve(nan, np.full(1, np.nan), np.full_like(lam0[:1], np.nan),
                                       np.full((1, p.shape[1]), np.nan), np.zeros(1, bool),
                                       np.zeros((1, 0)), 0.0, np.zeros(1, int)))
        return BatchSolve(*(np.concatenate([getattr(r, name) for r in rows]) for name in
                            ("x", "f", "lam_g", "lam_p", "success", "extra")),
                          sum(r.solve_time_s for r in rows),
                          np.concatenate([r.iterations for r in rows]))

    def _rows(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The limit rows c (k, nc) at the points x (k, nx) with p (k, np)."""
        return np.asarray(self._rows_of(len(p))(x.T, p.T)).reshape(self.nc, len(p)).T

    def _beyond(self, c: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
        """Masks (k, nc) of the rows c beyond their lower and upper bounds by more than
        ``tol`` (relative; ``side`` −1), or at or beyond them to within it (``side`` 1)."""
        with np.errstate(invalid="ignore"):
            lower = np.isfinite(self.lower) & (
                c - self.lower <= side * self.tol * (1 + np.abs(self.lower)))
            upper = np.isfinite(self.upper) & (
                self.upper - c <= side * self.tol * (1 + np.abs(self.upper)))
        return lower, upper & ~lower
