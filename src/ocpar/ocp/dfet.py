"""DFET: Direct Finite Elements in Time for ẋ = F(x, u) on [0, t_f], t_f free (MACS paper §III).

[0, t_f] is split into N equal elements of length Δt = t_f/N, mapped to τ ∈ [−1, 1] by
t = t_{j−1} + (τ + 1) Δt/2. On element j the states are a polynomial of degree l through
l+1 Gauss–Lobatto nodes (independent per element: discontinuous in time), the controls a
polynomial of degree m through m+1 Gauss–Legendre nodes. The test functions w are global,
continuous and piecewise of degree l+1 (l+2 Gauss–Lobatto nodes per element, end nodes shared
by neighbours), so the inter-element boundary terms of the weak form cancel and only the
fixed initial state x_0 and the final boundary state x_f remain (eq. 3/9): for every w,

    Σ_j Σ_k σ_k [ẇ_j(τ_k)ᵀ X_j(τ_k) + w_j(τ_k)ᵀ F(X_j(τ_k), U_j(τ_k)) Δt/2] − w(t_f)ᵀ x_f
        + w(0)ᵀ x_0 = 0

with QUADRATURE_EXTRA + l Gauss–Legendre points (τ_k, σ_k) per element (exact for the
polynomial part ẇᵀX). That is (N(l+1) + 1) nx equations for N(l+1) nx state nodes and x_f;
the final conditions x_f[i] = value are added for i in ``final_components``.

NLP variables z = (state nodes, x_f, control nodes, t_f), nodes element-major, then node, then
component; the controls and t_f (the paper's search space p) are the contiguous tail of z.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, lru_cache

import casadi as ca
import numpy as np
from numpy.polynomial import legendre
from numpy.polynomial import polynomial as poly

from ocpar.models.ode import OdeModel
from ocpar.ocp.constraints import CompiledConstraint, ConstraintRows
from ocpar.ocp.ipopt import ipopt_options

#: Gauss–Legendre quadrature points per element = order l + QUADRATURE_EXTRA.
QUADRATURE_EXTRA = 2
#: Classical RK4 steps per element of the compiled integration
#: (:meth:`DfetTranscription.rk4_sweep`), shared among the intervals between state nodes in
#: proportion to their length, at least :data:`RK4_MIN_STEPS` per interval; its error estimate
#: comes from a second sweep with twice as many.
RK4_STEPS = 64
RK4_MIN_STEPS = 16
#: IPOPT tolerance and iteration limit of :meth:`DfetTranscription.solve_states`.
STATE_SOLVE_TOL = 1e-10
STATE_SOLVE_MAX_ITER = 200


def gauss_lobatto_nodes(n: int) -> np.ndarray:
    """The n ≥ 2 Gauss–Lobatto nodes on [−1, 1]: ±1 and the roots of P′_{n−1}, ascending."""
    interior = legendre.Legendre.basis(n - 1).deriv().roots() if n > 2 else np.empty(0)
    return np.concatenate([[-1.0], np.sort(np.real(interior)), [1.0]])


def gauss_legendre_nodes(n: int) -> np.ndarray:
    """The n ≥ 1 Gauss–Legendre nodes on [−1, 1] (roots of P_n), ascending."""
    return legendre.leggauss(n)[0]


def lagrange_basis(nodes: np.ndarray, points: np.ndarray, derivative: bool = False) -> np.ndarray:
    """L[k, s] = ℓ_s(points_k) (or ℓ′_s), ℓ_s the Lagrange polynomial of ``nodes`` that is 1 at
    nodes_s; shape (len(points), len(nodes))."""
    nodes, points = np.asarray(nodes, float), np.asarray(points, float)
    out = np.empty((points.size, nodes.size))
    for s, node in enumerate(nodes):
        others = np.delete(nodes, s)
        coef = poly.polyfromroots(others) / np.prod(node - others)
        out[:, s] = poly.polyval(points, poly.polyder(coef) if derivative else coef)
    return out


@dataclass(frozen=True)
class DfetShape:
    """Everything that fixes the structure of a DFET NLP (the solver-cache key).

    ``elements`` N; ``order`` l ≥ 1 (states of degree l, test functions of degree l+1);
    ``control_order`` m ≥ 0 (controls of degree m); ``control_bounds`` one (lo, hi) per control
    component; ``duration_bounds`` (lo, hi) on t_f > 0 (t_0 = 0), in the model's time unit;
    ``initial_state`` x(0) (nx,), fixed; ``final_values`` the fixed values of x_f at the state
    indices ``final_components`` (the other components are free).
    """

    model: OdeModel
    elements: int
    order: int
    control_order: int
    control_bounds: tuple[tuple[float, float], ...]
    duration_bounds: tuple[float, float]
    initial_state: tuple[float, ...]
    final_components: tuple[int, ...] = ()
    final_values: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        nx, nu = self.model.nx, self.model.nu
        if self.elements < 1:
            raise ValueError(f"DFET needs at least 1 element, got {self.elements}")
        if self.order < 1:
            raise ValueError(f"DFET state order must be >= 1, got {self.order}")
        if self.control_order < 0:
            raise ValueError(f"DFET control order must be >= 0, got {self.control_order}")
        bounds = tuple((float(lo), float(hi)) for lo, hi in self.control_bounds)
        if len(bounds) != nu or any(not lo <= hi for lo, hi in bounds):
            raise ValueError(f"control_bounds must be {nu} pairs (lo, hi) with lo <= hi, "
                             f"got {self.control_bounds}")
        lo, hi = (float(b) for b in self.duration_bounds)
        if not 0 < lo <= hi < np.inf:
            raise ValueError(f"duration_bounds must satisfy 0 < lo <= hi < inf, "
                             f"got {self.duration_bounds}")
        x0 = tuple(float(v) for v in self.initial_state)
        if len(x0) != nx or not np.all(np.isfinite(x0)):
            raise ValueError(f"initial_state must be {nx} finite numbers, got {self.initial_state}")
        final = tuple(int(i) for i in self.final_components)
        if any(not 0 <= i < nx for i in final) or len(set(final)) != len(final):
            raise ValueError(f"final_components {self.final_components} must be distinct "
                             f"indices in 0..{nx - 1}")
        values = tuple(float(v) for v in self.final_values)
        if len(values) != len(final):
            raise ValueError(f"{len(values)} final_values for {len(final)} final_components")
        for name, value in (("control_bounds", bounds), ("duration_bounds", (lo, hi)),
                            ("initial_state", x0), ("final_components", final),
                            ("final_values", values)):
            object.__setattr__(self, name, value)  # plain tuples: stable hashes, picklable

    @property
    def n_states(self) -> int:
        """Number of state nodal values, N (l+1) nx."""
        return self.elements * (self.order + 1) * self.model.nx

    @property
    def n_decision(self) -> int:
        """Length of p = (control nodes, t_f): N (m+1) nu + 1."""
        return self.elements * (self.control_order + 1) * self.model.nu + 1


class DfetTranscription:
    """The DFET equations of one shape, the bounds of z and an IPOPT state solver."""

    def __init__(self, shape: DfetShape) -> None:
        self.shape = shape
        model, n, m = shape.model, shape.elements, shape.control_order
        k = shape.order + 1  # state nodes per element, l+1
        nx, nu = model.nx, model.nu
        self.nx, self.nu, self.n = nx, nu, n
        self.state_nodes = gauss_lobatto_nodes(k)
        self.control_nodes = gauss_legendre_nodes(m + 1)
        tau, sigma = legendre.leggauss(shape.order + QUADRATURE_EXTRA)
        f_q = lagrange_basis(self.state_nodes, tau)  # (q, l+1) states at quadrature points
        g_q = lagrange_basis(self.control_nodes, tau)  # (q, m+1) controls
        test_nodes = gauss_lobatto_nodes(k + 1)
        h_q = lagrange_basis(test_nodes, tau)  # (q, l+2) test functions
        dh_q = lagrange_basis(test_nodes, tau, derivative=True)
        stiffness = (dh_q * sigma[:, None]).T @ f_q  # (l+2, l+1): Σ_k σ_k h′_s f_r
        load = (h_q * sigma[:, None]).T  # (l+2, q): σ_k h_s(τ_k)

        ns, nxf = shape.n_states, nx
        nc = n * (m + 1) * nu
        self.z = ca.SX.sym("z", ns + nxf + nc + 1)
        self.nz = self.z.numel()
        self._states = slice(0, ns)
        self._final = slice(ns, ns + nxf)
        self._controls = slice(ns + nxf, ns + nxf + nc)
        self.decision_slice = slice(ns + nxf, self.nz)

        x = ca.reshape(self.z[self._states], nx, n * k)
        u = ca.reshape(self.z[self._controls], nu, n * (m + 1))
        x_f, t_f = self.z[self._final], self.z[self.nz - 1]
        #: Gauss–Legendre points and weights (q,) of every element, on [−1, 1].
        self.quadrature = (tau, sigma)
        #: Per element, the states (nx, q) and controls (nu, q) at its quadrature points, as
        #: expressions of z: where the weak form, a running cost and path constraints
        #: evaluate.
        self.quadrature_states = [x[:, j * k : (j + 1) * k] @ f_q.T for j in range(n)]
        self.quadrature_controls = [u[:, j * (m + 1) : (j + 1) * (m + 1)] @ g_q.T
                                    for j in range(n)]
        xs, us = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        rhs = ca.Function("F", [xs, us], [model.rhs(xs, us)]).map(tau.size)
        half_step = t_f / (2 * n)
        residuals = []  # per element, (nx, l+2): contributions to the element's test nodes
        for j in range(n):
            xj = x[:, j * k : (j + 1) * k]
            fq = rhs(self.quadrature_states[j], self.quadrature_controls[j])  # (nx, q)
            residuals.append(xj @ stiffness.T + half_step * (fq @ load.T))
        columns = [residuals[0][:, 0] + ca.DM(shape.initial_state)]
        for j in range(n):
            columns += [residuals[j][:, s] for s in range(1, k)]
            end = residuals[j][:, k]
            columns.append(end + residuals[j + 1][:, 0] if j + 1 < n else end - x_f)
        self.dynamics = ca.vertcat(*columns)
        final = [x_f[i] - v for i, v in zip(shape.final_components, shape.final_values,
                                             strict=True)]
        self.constraints = ca.vertcat(self.dynamics, *final)
        self.ng = self.constraints.numel()

        lower, upper = model.state_bounds()
        c_lo, c_hi = np.array(shape.control_bounds).T
        self.p_lower = np.concatenate([np.tile(c_lo, n * (m + 1)), [shape.duration_bounds[0]]])
        self.p_upper = np.concatenate([np.tile(c_hi, n * (m + 1)), [shape.duration_bounds[1]]])
        self.lbz = np.concatenate([np.tile(lower, n * k + 1), self.p_lower])
        self.ubz = np.concatenate([np.tile(upper, n * k + 1), self.p_upper])

    def path_rows(self, constraints: tuple[CompiledConstraint, ...]) -> ConstraintRows:
        """Path constraints of ``x`` and ``u`` (:mod:`ocpar.ocp.constraints`) imposed at every
        element's quadrature points, the points where the weak form evaluates the dynamics.
        Between them the element's polynomials are not constrained: the guarantee of a
        collocation method, violations of O(Δt^{order}) in between."""
        rows = ConstraintRows()
        q = self.quadrature[0].size
        for constraint in constraints:
            rows.add(constraint, [{"x": xq[:, i], "u": uq[:, i]} for xq, uq in
                                  zip(self.quadrature_states, self.quadrature_controls,
                                      strict=True) for i in range(q)])
        return rows

    # --- slicing z ---------------------------------------------------------------------------

    def final_state(self, z):
        """x_f (nx,) from z: SX in, SX out; numpy in, numpy out."""
        if isinstance(z, ca.SX | ca.MX):
            return z[self._final]
        return np.asarray(z, float).ravel()[self._final]

    def final_time(self, z):
        """t_f from z: SX in, SX out; numpy in, float out."""
        return z[self.nz - 1] if isinstance(z, ca.SX | ca.MX) else float(np.ravel(z)[-1])

    def decision(self, z_or_p: np.ndarray) -> np.ndarray:
        """p = (control nodes, t_f) from a full z or from p itself (copied)."""
        arr = np.asarray(z_or_p, float).ravel()
        size = self.nz - self.decision_slice.start
        if arr.size == self.nz:
            return arr[self.decision_slice].copy()
        if arr.size == size:
            return arr.copy()
        raise ValueError(f"expected z ({self.nz}) or p ({size}) values, got {arr.size}")

    def state_nodes_of(self, z: np.ndarray) -> np.ndarray:
        """State nodal values (N, l+1, nx) from a numpy z."""
        shape = (self.n, self.shape.order + 1, self.nx)
        return np.asarray(z, float).ravel()[self._states].reshape(shape)

    # --- the control law and accurate integration ----------------------------------------------

    def sample_controls(self, law: Callable[[float], np.ndarray], t_f: float) -> np.ndarray:
        """p from a control law u(t) (nu,) sampled at every element's Gauss–Legendre nodes."""
        step = t_f / self.n
        times = (np.arange(self.n)[:, None] + (self.control_nodes + 1) / 2) * step
        values = [np.broadcast_to(np.asarray(law(t), float), (self.nu,)) for t in times.ravel()]
        return np.concatenate([np.ravel(values), [t_f]])

    def _control_polynomials(self, p: np.ndarray) -> np.ndarray:
        """Monomial coefficients in τ of every element's control polynomial, (N, m+1, nu)."""
        m1 = self.shape.control_order + 1
        nodes = p[:-1].reshape(self.n, m1, self.nu)
        vandermonde = np.vander(self.control_nodes, m1, increasing=True)
        return np.linalg.solve(vandermonde, nodes.transpose(1, 0, 2).reshape(m1, -1)).reshape(
            m1, self.n, self.nu).transpose(1, 0, 2)

    def _element_law(self, p: np.ndarray) -> Callable[[int, float], np.ndarray]:
        """u(j, t) (nu,): element j's control polynomial at time t (the bounds hold at the
        control nodes, as in the NLP; between them the polynomial is not clipped, so that a
        re-simulation uses exactly the control the NLP optimised)."""
        coefs = self._control_polynomials(p)
        step, m1 = p[-1] / self.n, self.shape.control_order + 1

        def law(j: int, t: float) -> np.ndarray:
            tau = 2 * (t - j * step) / step - 1
            return tau ** np.arange(m1) @ coefs[j]

        return law

    def control_law(self, z_or_p: np.ndarray) -> Callable[[float], np.ndarray]:
        """u(t) (nu,) for t in [0, t_f]: the element's control polynomial, as the NLP uses it.
        At an element boundary the later element's polynomial applies."""
        p = self.decision(z_or_p)
        element_law = self._element_law(p)
        step = p[-1] / self.n

        def law(t: float) -> np.ndarray:
            return element_law(min(max(int(np.floor(t / step)), 0), self.n - 1), t)

        return law

    @cached_property
    def rhs_function(self) -> ca.Function:
        """F(x (nx,), u (nu,)) → ẋ (nx,) of the model as a numeric CasADi function, for the
        accurate integrations below."""
        xs, us = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu)
        return ca.Function("F", [xs, us], [self.shape.model.rhs(xs, us)])

    @cached_property
    def rk4_sweep(self) -> ca.Function:
        """p (decision vector) → (coarse, fine): the control law integrated from x_0 by
        classical RK4, element by element, with :data:`RK4_STEPS` (coarse, at least
        :data:`RK4_MIN_STEPS` per interval between state nodes) and twice as many (fine) steps
        per element; each (nx, N (l+1)), the states at every element's
        Gauss–Lobatto nodes. One call into compiled code."""
        n, m1, nx, nu = self.n, self.shape.control_order + 1, self.nx, self.nu
        # one interval [a, b] of τ on one element: x(a) → x(b), dx/dτ = t_f/(2N) F(x, u(τ)),
        # u(τ) = C (1, τ, …, τ^m) with C the monomial coefficients of the element's nodes
        x, a, b = ca.SX.sym("x", nx), ca.SX.sym("a"), ca.SX.sym("b")
        coefs, half_step = ca.SX.sym("C", nu, m1), ca.SX.sym("h")

        def f(y, tau):
            return half_step * self.rhs_function(y, coefs @ tau ** ca.DM(np.arange(m1)))

        p = ca.MX.sym("p", n * m1 * nu + 1)
        to_monomial = np.linalg.inv(np.vander(self.control_nodes, m1, increasing=True)).T

        coarse = np.maximum(RK4_MIN_STEPS, np.round(RK4_STEPS * np.diff(self.state_nodes) / 2))
        sweeps = []
        for counts in (coarse.astype(int), 2 * coarse.astype(int)):
            intervals = {}
            for steps in set(counts.tolist()):
                y, h = x, (b - a) / steps
                for i in range(steps):
                    t = a + i * h
                    k1 = f(y, t)
                    k2 = f(y + h / 2 * k1, t + h / 2)
                    k3 = f(y + h / 2 * k2, t + h / 2)
                    y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + f(y + h * k3, t + h))
                intervals[steps] = ca.Function(f"rk4_{steps}", [x, a, b, coefs, half_step], [y])
            # the sweep over all elements and intervals, calling the interval functions
            y, columns = ca.MX(ca.DM(self.shape.initial_state)), []
            for j in range(n):
                element_coefs = ca.reshape(p[j * m1 * nu:(j + 1) * m1 * nu], nu, m1) @ to_monomial
                columns.append(y)
                for i, steps in enumerate(counts):
                    y = intervals[steps](y, self.state_nodes[i], self.state_nodes[i + 1],
                                         element_coefs, p[-1] / (2 * n))
                    columns.append(y)
            sweeps.append(ca.horzcat(*columns))
        return ca.Function("rk4_sweep", [p], sweeps, ["p"], ["coarse", "fine"])

    def _integrate(self, p: np.ndarray, rtol: float, atol: float, hold: bool = False
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Integrate the control law from x_0, element by element (the controls jump between
        elements); states at every element's Gauss–Lobatto nodes (N, l+1, nx) and x(t_f).
        First by :meth:`rk4_sweep`, kept if finite and |fine − coarse| (about 15 times the fine
        sweep's error) is within atol + rtol |x| everywhere; otherwise by scipy's adaptive
        DOP853. If that fails, raise RuntimeError, or with ``hold`` keep the last state."""
        coarse, fine = (np.asarray(a) for a in self.rk4_sweep(p))
        error = np.abs(fine - coarse)
        if np.all(np.isfinite(fine)) and np.all(error <= atol + rtol * np.abs(fine)):
            nodes = fine.T.reshape(self.n, self.shape.order + 1, self.nx)
            return nodes, nodes[-1, -1].copy()
        return self._integrate_adaptive(p, rtol, atol, hold)

    def _integrate_adaptive(self, p: np.ndarray, rtol: float, atol: float, hold: bool
                            ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_integrate` by scipy's DOP853, element by element."""
        from scipy.integrate import solve_ivp
        buffer, evaluate = self.rhs_function.buffer()  # one per call: thread-safe
        state, control, derivative = np.empty(self.nx), np.empty(self.nu), np.empty(self.nx)
        for i, array in enumerate((state, control)):
            buffer.set_arg(i, memoryview(array))
        buffer.set_res(0, memoryview(derivative))

        def rhs(y: np.ndarray, u: np.ndarray) -> np.ndarray:
            state[:], control[:] = y, u
            evaluate()
            return derivative.copy()

        law = self._element_law(p)
        step = p[-1] / self.n
        x = np.array(self.shape.initial_state)
        nodes = np.empty((self.n, self.shape.order + 1, self.nx))
        for j in range(self.n):
            t0 = j * step
            times = t0 + (self.state_nodes + 1) * step / 2
            times[-1] = t0 + step
            sol = solve_ivp(lambda t, y, j=j: rhs(y, law(j, t)), (t0, t0 + step), x,
                            t_eval=times, rtol=rtol, atol=atol, method="DOP853")
            if not sol.success or not np.all(np.isfinite(sol.y)):
                if not hold:
                    raise RuntimeError(f"integration failed on element {j}: {sol.message}")
                nodes[j:] = x
                return nodes, x
            nodes[j] = sol.y.T
            x = sol.y[:, -1]
        return nodes, x

    def guess_from_decision(self, p: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
        """A full z consistent with p (a full z or p): the control law integrated accurately
        (``rtol``, atol = rtol/100) fills the state nodes and x_f; should the integration
        fail, the last state reached fills the rest."""
        p = self.decision(p)
        nodes, x_f = self._integrate(p, rtol, rtol / 100, hold=True)
        return np.concatenate([nodes.ravel(), x_f, p])

    def simulate(self, z_or_p: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
        """x(t_f) (nx,) of the control law integrated accurately from x_0 (atol = rtol/100);
        RuntimeError if the integration fails."""
        return self._integrate(self.decision(z_or_p), rtol, rtol / 100)[1]

    # --- solving the state equations -----------------------------------------------------------

    @cached_property
    def state_solver(self) -> ca.Function:
        """IPOPT on the weak-form equations with a zero objective, built on first use."""
        nlp = {"x": self.z, "f": ca.SX(0), "g": self.dynamics}
        return ca.nlpsol("dfet_states", "ipopt", nlp,
                         ipopt_options(STATE_SOLVE_TOL, STATE_SOLVE_MAX_ITER))

    def solve_states(self, p: np.ndarray) -> tuple[np.ndarray, bool]:
        """Solve the weak-form equations for the state nodes and x_f with the controls and t_f
        fixed at p, from :meth:`guess_from_decision`; returns (z, ok). The final conditions are
        not imposed (with p fixed the equations are already square): check them on
        :meth:`final_state`."""
        p = self.decision(p)
        lbz, ubz = self.lbz.copy(), self.ubz.copy()
        lbz[self.decision_slice] = ubz[self.decision_slice] = p
        try:
            out = self.state_solver(x0=self.guess_from_decision(p), lbx=lbz, ubx=ubz, lbg=0,
                                    ubg=0)
        except RuntimeError:  # evaluation errors (NaN) in CasADi
            return np.concatenate([np.full(self.nz - p.size, np.nan), p]), False
        z = np.asarray(out["x"]).ravel()
        ok = bool(self.state_solver.stats()["success"])
        return z, ok


@lru_cache(maxsize=64)
def dfet_problem(shape: DfetShape) -> DfetTranscription:
    """The process-wide DFET transcription of ``shape``: built once, then reused."""
    return DfetTranscription(shape)
