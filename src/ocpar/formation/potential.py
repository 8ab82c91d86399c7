"""The artificial potential on the circle and the equidistance constraint g(φ) = dG/dφ = 0.

G(φ) = Σ_{i≠j} 1/|z_i − z_j|² with z_i = r (cos φ_i, sin φ_i), so
|z_i − z_j|² = 2 r² (1 − cos(φ_i − φ_j)). g = ∇G has rank n−1 (a common rotation changes
nothing) and entries that grow like n³/r²; the constraint used is the scaled, reduced
c(φ) = (r²/n³) g(φ)[:n−1].
"""

from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np


def potential_expr(phi: ca.SX | ca.MX, radius: float) -> ca.SX | ca.MX:
    """G(φ) as a CasADi expression of the angle vector φ (n,)."""
    n = phi.numel()
    terms = [
        1.0 / (2 * radius**2 * (1 - ca.cos(phi[i] - phi[j])))
        for i in range(n)
        for j in range(i + 1, n)
    ]
    return 2 * ca.sum1(ca.vertcat(*terms))


def coupling_expr(phi: ca.SX | ca.MX, radius: float) -> ca.SX | ca.MX:
    """The scaled, reduced constraint c(φ) = (r²/n³) dG/dφ[:n−1], a column of n−1 entries."""
    n = phi.numel()
    return (radius**2 / n**3) * ca.gradient(potential_expr(phi, radius), phi)[: n - 1]


@lru_cache(maxsize=16)
def coupling_functions(agents: int, radius: float) -> tuple[ca.Function, ca.Function]:
    """CasADi functions c(φ) and its Jacobian dc/dφ ((n−1) × n) for ``agents`` angles."""
    phi = ca.SX.sym("phi", agents)
    c = coupling_expr(phi, radius)
    return ca.Function("c", [phi], [c]), ca.Function("dc", [phi], [ca.jacobian(c, phi)])


def equidistance_error(phi: np.ndarray) -> float:
    """max_i |gap_i − 2π/n| over the n gaps between consecutive angles on the circle (rad)."""
    angles = np.sort(np.mod(np.asarray(phi, float), 2 * np.pi))
    gaps = np.diff(np.append(angles, angles[0] + 2 * np.pi))
    return float(np.max(np.abs(gaps - 2 * np.pi / len(angles))))
