"""The objective vector J of a :class:`~ocpar.macs.problem.MacsProblem` on its DFET
transcription, and of a control law integrated accurately.

On the transcription, J_i(z) = φ_i(x_f, t_f) + Σ_j Σ_k σ_k L_i(X_j(τ_k), U_j(τ_k)) t_f/(2N):
the running costs are integrated by the DFET's own element quadrature (Gauss–Legendre points
τ_k, weights σ_k, order + QUADRATURE_EXTRA of them per element), on the state and control
polynomials of every element. Re-simulated, the running costs are extra states q̇_i = L_i(x, u)
integrated with the dynamics (:class:`CostAugmentedModel`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np
from numpy.polynomial import legendre

from ocpar.macs.problem import MacsProblem
from ocpar.ocp import DfetShape, DfetTranscription, dfet_problem
from ocpar.ocp.dfet import QUADRATURE_EXTRA, lagrange_basis


def _terms(problem: MacsProblem, kind: str, first: ca.SX, second: ca.SX) -> list:
    """Each objective's ``kind`` term ("mayer" or "running") at (first, second), 0 if absent."""
    return [0 if getattr(o, kind) is None else getattr(o, kind)(first, second)
            for o in problem.objectives]


@dataclass(frozen=True)
class CostAugmentedModel:
    """The problem's model with one extra state per objective, q̇_i = L_i(x, u) (0 without a
    running term), started at 0: integrating it gives the running costs' integrals."""

    problem: MacsProblem

    @property
    def nx(self) -> int:
        return self.problem.model.nx + self.problem.n_objectives

    @property
    def nu(self) -> int:
        return self.problem.model.nu

    def rhs(self, x, u):
        state = x[: self.problem.model.nx]
        return ca.vertcat(self.problem.model.rhs(state, u),
                          *_terms(self.problem, "running", state, u))

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower, upper = self.problem.model.state_bounds()
        free = np.full(self.problem.n_objectives, np.inf)
        return np.concatenate([lower, -free]), np.concatenate([upper, free])


class ObjectiveFunctions:
    """J of one problem: ``symbolic(z)`` on the transcription, ``resimulated(z)`` numerically."""

    def __init__(self, problem: MacsProblem) -> None:
        self.problem = problem
        self.dfet: DfetTranscription = dfet_problem(problem.shape)
        model = problem.model
        xf, tf = ca.SX.sym("xf", model.nx), ca.SX.sym("tf")
        self.mayer = ca.Function("mayer", [xf, tf], [ca.vertcat(*_terms(problem, "mayer", xf,
                                                                          tf))])
        self.has_running = any(o.running is not None for o in problem.objectives)

    def symbolic(self, z: ca.SX) -> ca.SX:
        """J(z) (m, 1) on the DFET transcription's NLP vector z."""
        dfet, shape = self.dfet, self.problem.shape
        j = self.mayer(dfet.final_state(z), dfet.final_time(z))
        if not self.has_running:
            return j
        nx, nu, n = dfet.nx, dfet.nu, dfet.n
        k, m1 = shape.order + 1, shape.control_order + 1
        tau, sigma = legendre.leggauss(shape.order + QUADRATURE_EXTRA)
        states_at = lagrange_basis(dfet.state_nodes, tau)  # (q, l+1)
        controls_at = lagrange_basis(dfet.control_nodes, tau)  # (q, m+1)
        xs, us = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        running = ca.Function("L", [xs, us], [ca.vertcat(*_terms(self.problem, "running", xs,
                                                                 us))]).map(tau.size)
        x = ca.reshape(z[: shape.n_states], nx, n * k)
        u = ca.reshape(z[dfet.decision_slice.start: dfet.nz - 1], nu, n * m1)
        integral = 0
        for e in range(n):
            xq = x[:, e * k: (e + 1) * k] @ states_at.T
            uq = u[:, e * m1: (e + 1) * m1] @ controls_at.T
            integral += running(xq, uq) @ sigma
        return j + integral * dfet.final_time(z) / (2 * n)

    def resimulated(self, z_or_p: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
        """J (m,) of the control law of z (or p) integrated accurately from x_0 (rtol, atol =
        rtol/100); RuntimeError if the integration fails."""
        p = self.dfet.decision(z_or_p)
        t_f = float(p[-1])
        if not self.has_running:
            return np.asarray(self.mayer(self.dfet.simulate(p, rtol), t_f), float).ravel()
        final = _augmented(self.problem).simulate(p, rtol)
        nx = self.problem.model.nx
        return np.asarray(self.mayer(final[:nx], t_f), float).ravel() + final[nx:]


def _augmented(problem: MacsProblem) -> DfetTranscription:
    shape = problem.shape
    return dfet_problem(DfetShape(
        CostAugmentedModel(problem), shape.elements, shape.order, shape.control_order,
        shape.control_bounds, shape.duration_bounds,
        shape.initial_state + (0.0,) * problem.n_objectives))


@lru_cache(maxsize=8)
def objective_functions(problem: MacsProblem) -> ObjectiveFunctions:
    """This process's objective functions of ``problem``: built once, then reused."""
    return ObjectiveFunctions(problem)
