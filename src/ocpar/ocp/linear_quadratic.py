"""Whether an ODE model is linear–quadratic: affine dynamics and a convex quadratic running
cost bounded below, decided exactly on the model's own CasADi expressions.

With ẋ = A x + B u + c, one step of RK4 or explicit Euler (:mod:`ocpar.ocp.multiple_shooting`)
maps (x_j, u_j) affinely to x_{j+1}, and every stage state is affine in (x_j, u_j); the
running cost integrated by the same stages is a positive combination (weights h/6, h/3, h/3,
h/6, or h) of g at those stages, so a convex quadratic in (x_j, u_j). The multiple-shooting
NLP between two states (:class:`~ocpar.ocp.MsEndpointShape`) is then a convex quadratic
programme in (w, p) jointly: its continuity and end rows are affine in both.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ocpar.models.ode import OdeModel

#: The running cost's Hessian counts as positive semidefinite where its smallest eigenvalue
#: is at least −this · its largest |entry|.
PSD_RTOL = 1e-12
#: Its gradient at 0 lies in the Hessian's range (the cost is bounded below) where the
#: least-squares residual is at most this · the gradient's length.
RANGE_RTOL = 1e-9


def is_linear_quadratic(model: OdeModel) -> bool:
    """Whether ``model``'s ``rhs`` is affine in (x, u) (its Jacobian does not depend on
    them: exact on CasADi's expression graph, a false negative possible where an expression
    only simplifies to an affine one) and its ``running_cost`` is a convex quadratic bounded
    below: a constant Hessian H in (x, u), positive semidefinite, with the gradient at 0 in
    H's range (:data:`PSD_RTOL`, :data:`RANGE_RTOL`)."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    z = ca.vertcat(x, u)
    if ca.depends_on(ca.jacobian(ca.SX(model.rhs(x, u)), z), z):
        return False
    hessian, gradient = ca.hessian(ca.SX(model.running_cost(x, u)), z)
    if ca.depends_on(hessian, z):
        return False
    h = np.asarray(ca.evalf(hessian))
    g = np.asarray(ca.Function("gradient", [z], [gradient])(np.zeros(z.numel()))).ravel()
    if np.linalg.eigvalsh(h).min() < -PSD_RTOL * np.max(np.abs(h)):
        return False
    shift = np.linalg.lstsq(h, g, rcond=None)[0]   # 0 where H = 0: then g must be 0
    return bool(np.linalg.norm(h @ shift - g) <= RANGE_RTOL * np.linalg.norm(g))
