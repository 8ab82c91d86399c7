"""Batched solves: one call into compiled code solves a whole chunk of NLPs of one shape.

:class:`KktNewton` (the default of the DMOC transcription, and the local solver of the
pursuit's multiple shooting) takes full Newton steps on the KKT system of an
equality-constrained NLP, min f(x, p) s.t. g(x, p) = 0, in one compiled CasADi function
(sparse QR), mapped over the chunk and called through preallocated buffers
(:class:`BufferedFunction`): ~0.8 ms per rigid-spacecraft solve, against ~1.7 ms for
:class:`MappedNlp` and ~1.5 ms for one IPOPT call (this machine, 2026-12). Where the KKT
matrix is constant (a quadratic cost with linear constraints, e.g. a point-mass DMOC: one
Newton step solves it) a batch factorises it once instead of once per column, and an end
Hessian that does not depend on the solution is evaluated once per batch: the same bits,
~0.006 ms per point-mass solve against ~0.02 ms per column (0.05 ms for :class:`MappedNlp`,
0.5 ms for IPOPT). Bounds, if any, are only checked afterwards.

:class:`MappedNlp` holds a parametric NLP (variables x, parameters p, cost f(x, p),
constraints g(x, p)) solved by CasADi's ``sqpmethod`` with the ``qrqp`` QP solver, mapped
over columns (``Function.map(k, "serial")``): k NLPs in one call, ~0.03 ms per point-mass
DMOC solve against ~0.5 ms for one IPOPT call. Each column is computed exactly as a call on
that column alone would compute it, so a task's result does not depend on which tasks share
its batch (tested bitwise).

Batches are cut into full blocks of :data:`COMPILED_BLOCKS` columns (256, then 32) and a
rest; a full block's calls (Newton steps, gradient, ``post``; the mapped ``sqpmethod`` and its
KKT residuals) run compiled by the host's C compiler (:func:`compiled_block`,
:mod:`ocpar.ocp.compiled`: once per shape and block size per host, cached on disk; the virtual
machine's bits), the rest (under 32 columns) on CasADi's virtual machine. Per call of a
256-column block, compiled against the virtual machine (this machine, 2026-12,
``scripts/compiled_kernels.py``): point-mass Newton step 2.0×, its gradient 2.1×, point-mass
``sqpmethod`` 1.7×, rigid-spacecraft Newton 1.17× and ``sqpmethod`` 0.98× (a sparse QR per
column: the same C++ either way).

A mapped call returns no per-column solver status, so each column's success is decided from
its KKT residuals at the returned point (:meth:`MappedNlp.solve`): primal infeasibility,
stationarity of the Lagrangian and complementarity of active bounds, each at most
``kkt_tol`` · (1 + scale). Columns that fail are re-solved one by one by the caller's
failure policy (:func:`ocpar.ocp.solve_tasks`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import casadi as ca
import numpy as np

from ocpar.ocp.compiled import compiled
from ocpar.ocp.solver_options import SolverOptions, sqpmethod

#: Solver names a transcription's ``solver`` option accepts: ``newton`` (:class:`KktNewton`)
#: or ``sqpmethod`` (:class:`MappedNlp`), both batched with IPOPT as fallback, or ``ipopt`` (one
#: IPOPT call per task).
SOLVERS = ("newton", "sqpmethod", "ipopt")
#: A shape's default solver: chosen from its constraints (``DmocShape.chosen_solver``).
AUTO_SOLVER = "auto"

#: Columns per mapped call at most (larger chunks are split): bounds the compiled map's size.
MAX_COLUMNS = 256
#: The block sizes whose calls are compiled (:func:`compiled_block`), largest first: a batch is
#: cut into blocks of these sizes in turn and a rest of fewer columns than the smallest (e.g.
#: 625 = 2 · 256 + 113: 82 % compiled; a rank's share of a formation on 16 ranks). Only full
#: blocks of 256: a compile (0.45 s for a point mass's Newton step, 2–8 s for a mapped
#: sqpmethod) pays for itself only over many columns, and a fleet of tens of agents of a new
#: shape should not wait for a compiler (the test suite's shapes compiled 360 libraries from an
#: empty cache with blocks of 32 too).
COMPILED_BLOCKS = (MAX_COLUMNS,)


def sqp_options(tol: float, max_iter: int, qp_max_iter: int | None = None) -> dict:
    """Silent ``sqpmethod`` + ``qrqp`` options with primal and dual tolerance ``tol``; a
    failed QP is a failed column, never an exception. ``qp_max_iter``: ``qrqp``'s active-set
    iterations per QP at most (None: its default, 1000)."""
    qp = {"print_iter": False, "print_header": False, "error_on_fail": False}
    if qp_max_iter is not None:
        qp["max_iter"] = qp_max_iter
    return {"qpsol": "qrqp", "tol_pr": tol, "tol_du": tol, "max_iter": max_iter,
            "print_header": False, "print_iteration": False, "print_status": False,
            "print_time": False, "error_on_fail": False, "qpsol_options": qp}


@dataclass
class BatchSolve:
    """Outputs of one batched solve of k NLPs, one row per NLP: ``x`` (k, nx), ``f`` (k,),
    ``lam_g`` (k, ng), ``lam_p`` (k, np), ``success`` (k,) from the KKT check, ``extra``
    (k, m) the NLP's post-solve function at each solution (column-major entries; (k, 0) if
    it has none), ``iterations`` (k,) where the solver reports them (−1 otherwise), and
    ``solve_time_s``, the whole call's wall time (s); ``lam_x`` (k, nx) the bounds'
    multipliers where the solver has them (:class:`MappedNlp`)."""

    x: np.ndarray
    f: np.ndarray
    lam_g: np.ndarray
    lam_p: np.ndarray
    success: np.ndarray
    extra: np.ndarray
    solve_time_s: float
    iterations: np.ndarray | None = None
    lam_x: np.ndarray | None = None


class MappedNlp:
    """The NLP min f(x, p) s.t. lbg ≤ g(x, p) ≤ ubg, lbx ≤ x ≤ ubx (SX expressions of the
    symbols ``x`` and ``p``), solved in batches by ``sqpmethod`` to tolerance ``tol`` and
    checked column by column to ``kkt_tol``. ``post``, a Function of (x*, λ_g*, p) with one
    output, is evaluated at every solution in the same mapped call (e.g. a sensitivity).
    ``qp_max_iter`` as in :func:`sqp_options`; ``options`` the user's ``sqpmethod.*`` and
    ``qrqp.*`` solver options over these (:mod:`ocpar.ocp.solver_options`)."""

    def __init__(self, name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX, tol: float,
                 max_iter: int, kkt_tol: float, post: ca.Function | None = None,
                 qp_max_iter: int | None = None, options: SolverOptions = ()) -> None:
        self.kkt_tol = kkt_tol
        self.post = post
        self.nx, self.ng = x.numel(), g.numel()
        self.solver = ca.nlpsol(name, "sqpmethod", {"x": x, "p": p, "f": f, "g": g},
                                sqpmethod(options, sqp_options(tol, max_iter, qp_max_iter)))
        self.residuals = kkt_residuals(name, x, p, f, g)
        self._mapped = lru_cache(maxsize=16)(self._map)

    def _map(self, columns: int) -> tuple[ca.Function, ca.Function, ca.Function | None]:
        """The mapped solver, KKT residuals and ``post`` of a block of ``columns`` columns,
        compiled (:func:`compiled_block`) for full blocks."""
        post = None if self.post is None else compiled_block(self.post.map(columns, "serial"),
                                                             columns)
        return (compiled_block(self.solver.map(columns, "serial"), columns),
                compiled_block(self.residuals.map(columns, "serial"), columns), post)

    def prepare(self, count: int) -> None:
        """Build the mapped calls that solving ``count`` NLPs at once takes (one per block
        size), so that the first solve does not."""
        for rows in _full_blocks(np.arange(count)):
            self._mapped(len(rows))

    def solve(self, x0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray, lbg: np.ndarray,
              ubg: np.ndarray, lbx: np.ndarray, ubx: np.ndarray) -> BatchSolve:
        """Solve k NLPs from guesses ``x0`` (k, nx), parameters ``p`` (k, np) and constraint
        multipliers ``lam_g0`` (k, ng); bounds are vectors shared by all. Raises RuntimeError
        if CasADi does (e.g. NaN in a model): the caller then solves one by one."""
        start = time.perf_counter()
        parts = [self._solve_block(x0[rows], p[rows], lam_g0[rows], lbg, ubg, lbx, ubx)
                 for rows in map(_as_slice, _full_blocks(np.arange(len(p))))]
        x, f, lam_g, lam_p, ok, extra, lam_x = (np.concatenate(column)
                                                for column in zip(*parts, strict=True))
        return BatchSolve(x, f, lam_g, lam_p, ok, extra, time.perf_counter() - start,
                          lam_x=lam_x)

    def _solve_block(self, x0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray,
                     lbg: np.ndarray, ubg: np.ndarray, lbx: np.ndarray, ubx: np.ndarray
                     ) -> tuple[np.ndarray, ...]:
        solver, residuals, post = self._mapped(len(p))
        out = solver(x0=x0.T, p=p.T, lam_g0=lam_g0.T, lbg=lbg, ubg=ubg, lbx=lbx, ubx=ubx)
        x, lam_g, lam_x = (np.asarray(out[k]).T for k in ("x", "lam_g", "lam_x"))
        g, stationarity, gradient = (np.asarray(r) for r in residuals(x.T, p.T, lam_g.T,
                                                                      lam_x.T))
        ok = kkt_met(x, p, lam_g, lam_x, g.T, stationarity.ravel(), gradient.ravel(),
                     (lbg, ubg, lbx, ubx), self.kkt_tol)
        if post is None:
            extra = np.zeros((len(p), 0))
        else:  # the map stacks the (r, c) outputs side by side: (r, k c) -> (k, r c)
            value = np.asarray(post(x.T, lam_g.T, p.T))
            extra = value.reshape(value.shape[0], len(p), -1).transpose(1, 2, 0).reshape(
                len(p), -1)
        return (x, np.asarray(out["f"]).ravel(), lam_g, np.asarray(out["lam_p"]).T, ok, extra,
                lam_x)


def kkt_residuals(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX) -> ca.Function:
    """(x, p, λ_g, λ_x) ↦ (g, |∇_x L|_∞, |∇f|_∞) of the NLP min f(x, p) s.t. g(x, p) in its
    bounds, L = f + λ_gᵀg + λ_xᵀx: what :func:`kkt_met` checks a returned point with."""
    lam_g, lam_x = ca.SX.sym("lam_g", g.numel()), ca.SX.sym("lam_x", x.numel())
    stationarity = ca.gradient(f + ca.dot(lam_g, g), x) + lam_x
    return ca.Function(f"{name}_kkt", [x, p, lam_g, lam_x],
                       [g, ca.norm_inf(stationarity), ca.norm_inf(ca.gradient(f, x))])


def kkt_met(x: np.ndarray, p: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray,
            g: np.ndarray, stationarity: np.ndarray, gradient: np.ndarray,
            bounds: tuple[np.ndarray, ...], tol: float) -> np.ndarray:
    """Whether each of k returned points (rows of x (k, nx), p, λ_g, λ_x, g (k, ng), and the
    residuals (k,) of :func:`kkt_residuals`) meets the KKT conditions to ``tol``: primal
    infeasibility under ``bounds`` (lbg, ubg, lbx, ubx) at most ``tol`` (1 + max |p|),
    stationarity and complementarity at most ``tol`` (1 + |∇f|_∞), x finite. (k,) bool."""
    lbg, ubg, lbx, ubx = bounds
    primal = np.maximum(np.max(np.maximum(lbg - g, g - ubg), axis=1, initial=0.0),
                        np.max(np.maximum(lbx - x, x - ubx), axis=1, initial=0.0))
    complementarity = np.maximum(
        _complementarity(lam_g, g, lbg, ubg), _complementarity(lam_x, x, lbx, ubx))
    scale = 1.0 + np.abs(gradient)
    return ((primal <= tol * (1.0 + np.max(np.abs(p), axis=1)))
            & (stationarity <= tol * scale)
            & (complementarity <= tol * scale)
            & np.all(np.isfinite(x), axis=1))


def _full_blocks(rows: np.ndarray) -> list[np.ndarray]:
    """``rows`` split into consecutive blocks of each size of :data:`COMPILED_BLOCKS` in turn
    (as many as fit) and the rest (the blocks whose calls are compiled, :func:`kernel`)."""
    blocks, start = [], 0
    for size in COMPILED_BLOCKS:
        while len(rows) - start >= size:
            blocks.append(rows[start:start + size])
            start += size
    return [*blocks, rows[start:]] if start < len(rows) else blocks


def compiled_block(function: ca.Function, columns: int) -> ca.Function:
    """``function``, a call on a block of ``columns`` columns, compiled by the host's C
    compiler (:func:`ocpar.ocp.compiled.compiled`: cached on disk by content, the same bits
    as the virtual machine's) where ``columns`` is one of :data:`COMPILED_BLOCKS`, the full
    blocks that batches are made of: a shape then compiles once per block size per host,
    whatever the batch sizes, and batches under 256 tasks never wait for a compiler. Elsewhere
    (or without a compiler) the function itself, on the virtual machine."""
    if columns in COMPILED_BLOCKS:
        return compiled(function) or function
    return function


def kernel(function: ca.Function, columns: int) -> BufferedFunction:
    """:func:`compiled_block` called through buffers."""
    return BufferedFunction(compiled_block(function, columns))


def _complementarity(lam: np.ndarray, value: np.ndarray, lower: np.ndarray,
                     upper: np.ndarray) -> np.ndarray:
    """max_i |λ_i| · (distance of value_i to the bound λ_i's sign makes active), per row;
    a multiplier on an infinite bound counts as infinite."""
    with np.errstate(invalid="ignore"):
        slack = np.where(lam > 0, upper - value, np.where(lam < 0, value - lower, 0.0))
        product = np.where(lam == 0, 0.0, np.abs(lam) * np.abs(slack))
    return np.max(np.nan_to_num(product, nan=np.inf), axis=1, initial=0.0)


class BufferedFunction:
    """A CasADi Function called through preallocated numpy buffers: converting numpy arrays to
    and from CasADi's DM costs ~0.3 µs per element, more than a small solve's arithmetic.
    Inputs and outputs are dense vectors (matrices column-major); one call at a time. An
    evaluation that fails (e.g. a singular KKT matrix in a linear solve) raises RuntimeError,
    as a direct call does: its outputs would be left at zero."""

    def __init__(self, function: ca.Function) -> None:
        self._name = function.name()
        self._buffer, self._evaluate = function.buffer()
        self._inputs = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self._outputs = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        for i, array in enumerate(self._inputs):
            self._buffer.set_arg(i, memoryview(array))
        for i, array in enumerate(self._outputs):
            self._buffer.set_res(i, memoryview(array))

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        """The outputs (copies) for inputs ``args``, in the Function's order."""
        return [array.copy() for array in self.evaluate(*args)]

    def evaluate(self, *args: np.ndarray) -> list[np.ndarray]:
        """The outputs for inputs ``args``: the output buffers themselves, overwritten by the
        next call."""
        for array, value in zip(self._inputs, args, strict=True):
            array[:] = value
        self._evaluate()
        if self._buffer.ret():
            raise RuntimeError(f"{self._name}: evaluation failed")
        return self._outputs


@dataclass(frozen=True)
class KktSystem:
    """The KKT system of min f(x, p) s.t. g(x, p) = 0, L = f + λ_gᵀ g, built once: the
    symbols ``x``, ``lam`` (λ_g) and ``p``, the KKT ``matrix`` (an SX of them), ``rhs`` the
    Function (x, λ_g, p) → −(∇f, g) and ``check`` the Function (x, λ_g, p) → (f, g,
    ‖∇_x L‖∞, ∇_p L) of an iterate."""

    x: ca.SX
    lam: ca.SX
    p: ca.SX
    matrix: ca.SX
    rhs: ca.Function
    check: ca.Function

    @classmethod
    def of(cls, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX) -> KktSystem:
        lam = ca.SX.sym("lam", g.numel())
        lagrangian = f + ca.dot(lam, g)
        jac, grad = ca.jacobian(g, x), ca.gradient(f, x)
        matrix = ca.blockcat([[ca.hessian(lagrangian, x)[0], jac.T],
                              [jac, ca.SX(g.numel(), g.numel())]])
        rhs = ca.Function("kkt_rhs", [x, lam, p], [-ca.vertcat(grad, g)])
        check = ca.Function("check", [x, lam, p], [
            f, g, ca.norm_inf(grad + jac.T @ lam), ca.gradient(lagrangian, p)])
        return cls(x=x, lam=lam, p=p, matrix=matrix, rhs=rhs, check=check)

    def constant_matrix(self) -> ca.DM | None:
        """The KKT matrix if it depends on neither x, λ_g nor p (a quadratic cost with
        linear constraints: an equality-constrained QP), else None."""
        if ca.depends_on(self.matrix, ca.vertcat(self.x, self.lam, self.p)):
            return None
        return ca.evalf(self.matrix)

    def parameter_rows(self) -> list[int] | None:
        """The entries of p the KKT matrix depends on where it depends on p alone (not on x
        or λ_g) and not constant (e.g. a linear–quadratic problem with its duration a
        parameter), else None."""
        if ca.depends_on(self.matrix, ca.vertcat(self.x, self.lam)):
            return None
        rows = [i for i in range(self.p.numel()) if ca.depends_on(self.matrix, self.p[i])]
        return rows or None

    def shared_newton(self, name: str, steps: int, columns: int) -> ca.Function:
        """:meth:`newton` mapped over ``columns`` columns whose KKT matrix, a function of p
        alone (:meth:`parameter_rows`), is the same: the first column's, factorised once per
        call (as :meth:`batched_newton` does a constant one)."""
        kkt = ca.Function("kkt", [self.p], [self.matrix])
        return self._steps(f"{name}_shared_newton_{columns}", steps, columns,
                           lambda _x, _lam, ps: kkt(ps[:, 0]), self.rhs.map(columns, "serial"),
                           self.check.map(columns, "serial"))

    def newton(self, name: str, steps: int) -> ca.Function:
        """Function (x, λ_g, p) → (x, λ_g, f, g, ‖∇_x L‖∞, ∇_p L) after ``steps`` full Newton
        steps (sparse QR, one factorisation per call; no globalisation, bounds ignored). At a
        KKT point ∇_p L is dJ*/dp."""
        kkt = ca.Function("kkt", [self.x, self.lam, self.p], [self.matrix])
        return self._steps(f"{name}_newton", steps, 1, kkt, self.rhs, self.check)

    def batched_newton(self, name: str, steps: int, matrix: ca.DM, columns: int
                       ) -> ca.Function:
        """:meth:`newton` mapped over ``columns`` columns (inputs and outputs side by side)
        where the KKT matrix is the constant ``matrix`` (:meth:`constant_matrix`): one QR
        factorisation per call instead of one per column. Each column's solve applies the
        same factors in the same order, so the results are those of the per-column map bit
        for bit (tested), ~4× faster on a point-mass DMOC."""
        return self._steps(f"{name}_newton_{columns}", steps, columns,
                           lambda *_: ca.MX(matrix), self.rhs.map(columns, "serial"),
                           self.check.map(columns, "serial"))

    def _steps(self, name: str, steps: int, columns: int, kkt: Any, rhs: ca.Function,
               check: ca.Function) -> ca.Function:
        """The Function of ``steps`` Newton steps on ``columns`` columns, the KKT matrix of
        an iterate from ``kkt`` and its right-hand side from ``rhs``, then ``check``."""
        nx = self.x.numel()
        linsol = ca.Linsol(f"{name}_kkt_qr", "qr", self.matrix.sparsity())
        x0, lam0, ps = (ca.MX.sym(s, v.numel(), columns)
                        for s, v in (("x", self.x), ("lam", self.lam), ("p", self.p)))
        xk, lam_k = x0, lam0
        for _ in range(steps):
            step = linsol.solve(kkt(xk, lam_k, ps), rhs(xk, lam_k, ps))
            xk, lam_k = xk + step[:nx, :], step[nx:, :]
        return ca.Function(name, [x0, lam0, ps], [xk, lam_k, *check(xk, lam_k, ps)])


def kkt_newton_function(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                        steps: int) -> ca.Function:
    """:meth:`KktSystem.newton` of min f(x, p) s.t. g(x, p) = 0."""
    return KktSystem.of(x, p, f, g).newton(name, steps)


def constant_outputs(function: ca.Function) -> bool:
    """True if no output of ``function`` depends (structurally) on any of its inputs: its
    value at one point is its value everywhere, e.g. the end Hessian of an LQ problem."""
    return all(function.sparsity_jac(i, o).nnz() == 0
               for i in range(function.n_in()) for o in range(function.n_out()))


class KktNewton:
    """The equality-constrained NLP min f(x, p) s.t. g(x, p) = 0 (SX expressions of ``x`` and
    ``p``) solved in batches by rounds of ``steps`` Newton steps on its KKT system
    (:meth:`KktSystem.newton`), each column accepted if ‖g‖∞ ≤ ``tol``·(1 + ‖p‖∞),
    ‖∇_x L‖∞ ≤ ``tol``·(1 + ‖∇f‖∞) and lbx ≤ x ≤ ubx. ``post`` as in :class:`MappedNlp`,
    evaluated once per column, at its last iterate (once per batch where it is constant).
    A constant KKT matrix is factorised once per batch (:meth:`KktSystem.batched_newton`);
    one that depends on p alone, once per block whose columns share the entries it depends
    on (:meth:`KktSystem.shared_newton`; e.g. T, set alike for a superstep's agents), and
    ``post`` then by ``shared_post(k)``, a Function of k such columns at once (e.g.
    :func:`~ocpar.ocp.sensitivity.shared_cost_hessian_function`)."""

    def __init__(self, name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX, steps: int,
                 tol: float, post: ca.Function | None = None,
                 shared_post: Callable[[int], ca.Function] | None = None) -> None:
        self.name, self.tol, self.steps = name, tol, steps
        self.nx, self.ng, self.np = x.numel(), g.numel(), p.numel()
        self.system = KktSystem.of(x, p, f, g)
        #: The KKT matrix where it is constant (an equality-constrained QP: batches factorise
        #: it once per call, :meth:`KktSystem.batched_newton`), else None.
        self.constant_matrix = self.system.constant_matrix()
        #: The entries of p a KKT matrix of p alone depends on (None: constant, or of x, λ).
        self.shared_rows = None if self.constant_matrix is not None else \
            self.system.parameter_rows()
        self.shared_post = shared_post
        self.gradient = ca.Function(f"{name}_grad", [x, p], [ca.norm_inf(ca.gradient(f, x))])
        self.post = post
        #: ``post`` is evaluated once per batch and repeated where its value is constant.
        self.constant_post = post is not None and constant_outputs(post)
        self._mapped = lru_cache(maxsize=16)(self._map)

    @cached_property
    def _per_column(self) -> ca.Function:
        """One column's Newton steps (:meth:`KktSystem.newton`), where the matrix varies."""
        return self.system.newton(self.name, self.steps)

    @cached_property
    def _constant_post(self) -> BufferedFunction:
        """``post`` where its value is constant: evaluated once per batch."""
        assert self.post is not None
        return BufferedFunction(self.post)

    def _map(self, k: int, shared: bool = False
             ) -> tuple[BufferedFunction, BufferedFunction, BufferedFunction | None]:
        """The calls of a block of ``k`` columns: the Newton steps, the cost gradient's norm
        and ``post`` (None where it has none or it is constant); ``shared``: columns sharing
        a KKT matrix of p alone (:attr:`shared_rows`). Compiled (:func:`kernel`) for full
        blocks (:data:`COMPILED_BLOCKS`)."""
        post = None
        if self.post is not None and not self.constant_post:
            post = kernel(self.shared_post(k) if shared and self.shared_post is not None
                          else self.post.map(k, "serial"), k)
        if self.constant_matrix is not None:
            newton = self.system.batched_newton(self.name, self.steps, self.constant_matrix, k)
        elif shared:
            newton = self.system.shared_newton(self.name, self.steps, k)
        else:
            newton = self._per_column.map(k, "serial")
        return kernel(newton, k), kernel(self.gradient.map(k, "serial"), k), post

    def prepare(self, count: int) -> None:
        """Build (and compile, or load from the cache) the mapped calls that solving
        ``count`` NLPs at once takes (one per block size), so that the first solve does not."""
        for rows in _full_blocks(np.arange(count)):
            self._mapped(len(rows), self.shared_rows is not None)

    def _shares(self, p: np.ndarray) -> bool:
        """Whether the columns ``p`` (k, np) share a KKT matrix of p alone."""
        rows = self.shared_rows
        return rows is not None and bool(np.all(p[:, rows] == p[0, rows]))

    def solve(self, x0: np.ndarray, p: np.ndarray, lam_g0: np.ndarray, lbx: np.ndarray,
              ubx: np.ndarray, rounds: int = 1) -> BatchSolve:
        """Solve k NLPs from guesses ``x0`` (k, nx), parameters ``p`` (k, np) and constraint
        multipliers ``lam_g0`` (k, ng); ``lbx``/``ubx`` (nx,) are checked, not imposed. The
        columns not accepted after a call go on from where they are, up to ``rounds`` calls
        in all; ``iterations`` counts each column's Newton steps."""
        start = time.perf_counter()
        k = len(p)
        x, lam = np.array(x0, float), np.array(lam_g0, float)
        f, ok = np.full(k, np.nan), np.zeros(k, dtype=bool)
        lam_p, iterations = np.full((k, self.np), np.nan), np.zeros(k, int)
        primal, dual, scale = np.empty(k), np.empty(k), np.empty(k)
        finite = np.empty(k, dtype=bool)
        with np.errstate(invalid="ignore"):
            limit = self.tol * (1.0 + np.max(np.abs(p), axis=1))
        todo = np.arange(k)
        bounded = (lbx > -np.inf) | (ubx < np.inf)   # the other entries hold all but NaN
        for _ in range(rounds):
            for rows in _full_blocks(todo):
                self._solve_block(_as_slice(rows), x, lam, p,
                                  (f, lam_p, primal, dual, scale, finite))
            rows = _as_slice(todo)
            with np.errstate(invalid="ignore"):
                ok[rows] = ((primal[rows] <= limit[rows])
                            & (dual[rows] <= self.tol * scale[rows])
                            & _within(x[rows], finite[rows], lbx, ubx, bounded))
            iterations[todo] += self.steps
            todo = todo[~ok[rows] & finite[rows]]
            if not len(todo):
                break
        if self.post is None:
            extra = np.zeros((k, 0))
        elif self.constant_post:
            extra = np.tile(self._constant_post(x[0], lam[0], p[0])[0], (k, 1))
        else:
            extra = np.concatenate([self._post(x[rows], lam[rows], p[rows])
                                    for rows in _full_blocks(np.arange(k))])
        return BatchSolve(x, f, lam, lam_p, ok, extra, time.perf_counter() - start, iterations)

    def _post(self, x: np.ndarray, lam: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``post`` (not constant) at each row, (k, m) with each output's entries
        column-major."""
        post = self._mapped(len(p), self._shares(p))[2]
        return post(x.ravel(), lam.ravel(), p.ravel())[0].reshape(len(p), -1)

    def _solve_block(self, rows: slice | np.ndarray, x: np.ndarray, lam: np.ndarray,
                     p: np.ndarray, out: tuple[np.ndarray, ...]) -> None:
        """One call on the columns ``rows`` of x (k, nx) and λ_g (k, ng), overwritten with the
        call's iterates, and of ``out``: f (k,), λ_p (k, np), ‖g‖∞ (k,), ‖∇_x L‖∞ (k,),
        1 + ‖∇f‖∞ (k,) and whether x is finite (k,) at the new iterate (what a column is
        accepted by), written (the norms while the block's arrays are in cache)."""
        f, lam_p, primal, dual, scale, finite = out
        block_p = p[rows]
        k = len(block_p)
        newton, gradient, _ = self._mapped(k, self._shares(block_p))
        x_new, lam_new, f_new, g_new, dual_new, grad_p = newton.evaluate(
            x[rows].ravel(), lam[rows].ravel(), block_p.ravel())
        x[rows], lam[rows] = x_new.reshape(k, self.nx), lam_new.reshape(k, self.ng)
        f[rows], dual[rows] = f_new, dual_new
        primal[rows] = np.max(np.abs(g_new.reshape(k, self.ng)), axis=1, initial=0.0)
        finite[rows] = np.all(np.isfinite(x[rows]), axis=1)
        lam_p[rows] = -grad_p.reshape(k, self.np)
        scale[rows] = 1.0 + gradient.evaluate(x_new, block_p.ravel())[0]


def _within(x: np.ndarray, finite: np.ndarray, lbx: np.ndarray, ubx: np.ndarray,
            bounded: np.ndarray) -> np.ndarray:
    """Whether each row of x (k, nx) lies within [lbx, ubx] (nx,), given which rows are
    ``finite`` (k,) and which entries are ``bounded`` (nx,; the others only exclude NaN)."""
    inside = finite.copy()
    if not inside.all():
        inside[~finite] = ~np.any(np.isnan(x[~finite]), axis=1)
    if bounded.any():
        inside &= np.all((x[:, bounded] >= lbx[bounded]) & (x[:, bounded] <= ubx[bounded]),
                         axis=1)
    return inside


def _as_slice(rows: np.ndarray) -> slice | np.ndarray:
    """Increasing indices ``rows`` as the slice they make where consecutive (its arrays are
    views, not copies), else themselves."""
    if len(rows) and rows[-1] - rows[0] == len(rows) - 1:
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows
