"""Second-order parametric sensitivity of an NLP's optimal cost, from its KKT system.

For min_x f(x, p) s.t. g(x, p) = 0 with Lagrangian L = f + λᵀg (CasADi's sign of λ), the
optimal cost J*(p) has gradient ∇_p L at the solution (x*, λ*) and Hessian

    ∇²J* = ∇²_pp L − [∇²_px L, ∇_p gᵀ] K⁻¹ [∇²_xp L; ∇_p g],   K = [∇²_xx L, ∇_x gᵀ; ∇_x g, 0]

(differentiate the KKT conditions in p). K is the matrix an SQP or interior-point solver
factorises at its last iterate; here it is factorised once more by CasADi's sparse QR.
Valid where no inequality is active.

With inequalities (lbg ≤ g ≤ ubg, lbx ≤ x ≤ ubx) the same holds on the active set under strict
complementarity: the active rows (the equalities, and the inequalities and bounds at a bound)
are equalities of the differentiated system, the inactive ones keep λ = 0. With an activity
mask a ∈ {0, 1} over the rows of G = (g, x), the system is

    [∇²_xx L, ∇_x Gᵀ diag(a); diag(a) ∇_x G, diag(1 − a)] [dx; dλ] = −[∇²_xp L; diag(a) ∇_p G] dp

(a bound row's multiplier enters L linearly, so ∇²L needs only λ_g). At a degenerate point (a
row at its bound with λ = 0) J* has one-sided second derivatives only; counting the row as
active gives the one of the directions that keep it at its bound.
"""

from __future__ import annotations

import casadi as ca


def cost_hessian_function(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                          block: slice | list[int], active_set: bool = False) -> ca.Function:
    """Function (x*, λ*, p) → ∇²J* restricted to the parameters ``block`` (a slice or a list
    of indices; rows and columns), a (m, m) matrix with m the number of entries it picks.
    With ``active_set`` the function takes a fourth input, the activity mask a (ng + nx: the
    rows of g, then the bounds of x; module docstring)."""
    if active_set:
        return _active_set_hessian_function(name, x, p, f, g, block)
    kkt, parts = _kkt_parts(name, x, p, f, g, block)
    xs, lams, ps = (ca.MX.sym(s, v.numel()) for s, v in (("x", x), ("lam_g", g), ("p", p)))
    r, c, h = parts(xs, lams, ps)
    return ca.Function(f"{name}_cost_hessian", [xs, lams, ps],
                       [h - c @ ca.solve(kkt(xs, lams, ps), r, "qr")])


def shared_cost_hessian_function(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                                 block: slice | list[int], columns: int) -> ca.Function:
    """:func:`cost_hessian_function` of ``columns`` NLPs at once whose KKT matrix K is the
    same, that of the first column (it depends on p alone, and the columns share the entries
    it depends on, e.g. a linear–quadratic problem's common duration T): K factorised once
    per call for every column's right-hand side. Function (x* (nx, k), λ* (ng, k),
    p (np, k)) → the k Hessians (m, m k) side by side; each column's is
    :func:`cost_hessian_function`'s at that column."""
    kkt, parts = _kkt_parts(name, x, p, f, g, block)
    xs, lams, ps = (ca.MX.sym(s, v.numel(), columns)
                    for s, v in (("x", x), ("lam_g", g), ("p", p)))
    r, c, h = parts.map(columns, "serial")(xs, lams, ps)
    solved = ca.solve(kkt(xs[:, 0], lams[:, 0], ps[:, 0]), r, "qr")
    m = h.size1()
    cs, ss, hs = ca.MX.sym("c", m, c.size2() // columns), ca.MX.sym("s", c.size2() // columns,
                                                                    m), ca.MX.sym("h", m, m)
    combine = ca.Function(f"{name}_combine", [cs, ss, hs], [hs - cs @ ss]).map(columns,
                                                                                "serial")
    return ca.Function(f"{name}_shared_cost_hessian_{columns}", [xs, lams, ps],
                       [combine(c, solved, h)])


def _kkt_parts(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX, block: slice | list[int]
               ) -> tuple[ca.Function, ca.Function]:
    """The KKT matrix K (x, λ, p) and the parts (x, λ, p) → ([∇²_xp L; ∇_p g],
    [∇²_px L, ∇_p gᵀ], ∇²_pp L) of the module docstring's formula, over ``block``."""
    lam = ca.SX.sym("lam_g", g.numel())
    lagrangian = f + ca.dot(lam, g)
    grad_x = ca.gradient(lagrangian, x)
    grad_p = ca.gradient(lagrangian, p)[block]
    pb = p[block]
    kkt = ca.blockcat([[ca.hessian(lagrangian, x)[0], ca.jacobian(g, x).T],
                       [ca.jacobian(g, x), ca.SX(g.numel(), g.numel())]])
    rhs = ca.vertcat(ca.jacobian(grad_x, pb), ca.jacobian(g, pb))
    cross = ca.horzcat(ca.jacobian(grad_p, x), ca.jacobian(grad_p, lam))
    return (ca.Function(f"{name}_kkt", [x, lam, p], [kkt]),
            ca.Function(f"{name}_kkt_parts", [x, lam, p],
                        [rhs, cross, ca.jacobian(grad_p, pb)]))


def _active_set_hessian_function(name: str, x: ca.SX, p: ca.SX, f: ca.SX, g: ca.SX,
                                 block: slice | list[int]) -> ca.Function:
    """:func:`cost_hessian_function` on the active set given by a mask (module docstring)."""
    ng, nx = g.numel(), x.numel()
    lam = ca.SX.sym("lam_g", ng)
    active = ca.SX.sym("active", ng + nx)
    lagrangian = f + ca.dot(lam, g)
    grad_x = ca.gradient(lagrangian, x)
    grad_p = ca.gradient(lagrangian, p)[block]
    pb = p[block]
    rows = ca.vertcat(g, x)  # G = (g, x)
    jac_rows = ca.diag(active) @ ca.jacobian(rows, x)
    kkt = ca.blockcat([[ca.hessian(lagrangian, x)[0], jac_rows.T],
                       [jac_rows, ca.diag(1 - active)]])
    rhs = ca.vertcat(ca.jacobian(grad_x, pb), ca.diag(active) @ ca.jacobian(rows, pb))
    cross = ca.horzcat(ca.jacobian(grad_p, x), ca.jacobian(grad_p, lam), ca.SX(pb.numel(), nx))
    parts = ca.Function(f"{name}_active_kkt_parts", [x, lam, p, active],
                        [kkt, rhs, cross, ca.jacobian(grad_p, pb)])
    xs, lams, ps, acts = (ca.MX.sym(s, v.numel()) for s, v in
                          (("x", x), ("lam_g", lam), ("p", p), ("active", active)))
    k, r, c, h = parts(xs, lams, ps, acts)
    return ca.Function(f"{name}_active_cost_hessian", [xs, lams, ps, acts],
                       [h - c @ ca.solve(k, r, "qr")])
