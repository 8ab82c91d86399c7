"""Second-order parametric sensitivity of an NLP's optimal cost, from its KKT system.

For min_x f(x, p) s.t. g(x, p) = 0 with Lagrangian L = f + λᵀg (CasADi's sign of λ), the
optimal cost J*(p) has gradient ∇_p L at the solution (x*, λ*) and Hessian

    ∇²J* = ∇²_pp L − [∇²_px L, ∇_p gᵀ] K⁻¹ [∇²_xp L; ∇_p g],   K = [∇²_xx L, ∇_x gᵀ; ∇_x g, 0]

(differentiate the KKT conditions in p). K is the matrix an SQP or interior-point solver
factorises at its last iterate; here it is factorised once more by CasADi's sparse QR.
Valid where no inequality is active (the DMOC inner problems have equalities only).
"""

from __future__ import annotations

import casadi as ca


def cost_hessian_function(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                          block: slice) -> ca.Function:
    """Function (x*, λ*, p) → ∇²J* restricted to the parameters ``block`` (rows and columns),
    a (m, m) matrix with m = len(range(p.numel())[block])."""
    lam = ca.SX.sym("lam_g", g.numel())
    lagrangian = f + ca.dot(lam, g)
    grad_x = ca.gradient(lagrangian, x)
    grad_p = ca.gradient(lagrangian, p)[block]
    pb = p[block]
    kkt = ca.blockcat([[ca.hessian(lagrangian, x)[0], ca.jacobian(g, x).T],
                       [ca.jacobian(g, x), ca.SX(g.numel(), g.numel())]])
    rhs = ca.vertcat(ca.jacobian(grad_x, pb), ca.jacobian(g, pb))
    cross = ca.horzcat(ca.jacobian(grad_p, x), ca.jacobian(grad_p, lam))
    parts = ca.Function(f"{name}_kkt_parts", [x, lam, p],
                        [kkt, rhs, cross, ca.jacobian(grad_p, pb)])
    xs, lams, ps = (ca.MX.sym(s, v.numel()) for s, v in (("x", x), ("lam_g", lam), ("p", p)))
    k, r, c, h = parts(xs, lams, ps)
    return ca.Function(f"{name}_cost_hessian", [xs, lams, ps], [h - c @ ca.solve(k, r, "qr")])
