"""The artificial potential on the circle and the equidistance constraint g(φ) = dG/dφ = 0.

G(φ) = Σ_{i≠j} 1/|z_i − z_j|² with z_i = r (cos φ_i, sin φ_i), so
|z_i − z_j|² = 2 r² (1 − cos(φ_i − φ_j)). g = ∇G has rank n−1 (a common rotation changes
nothing) and entries that grow like n³/r²; the constraint used is the scaled, reduced
c(φ) = (r²/n³) g(φ)[:n−1]. :func:`coupling_expr` builds it symbolically (for one NLP of the
whole problem); :func:`coupling` and :func:`coupling_jacobian` evaluate it in closed form
(for the outer SQP: a symbolic Jacobian would cost O(n²) expression nodes to build).
"""

from __future__ import annotations

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


def coupling(phi: np.ndarray, radius: float) -> np.ndarray:
    """c(φ) (n−1,) in closed form, as :func:`coupling_expr`: with h(d) = 1/(2r²(1 − cos d)),
    g_k = 2 Σ_{j≠k} h′(φ_k − φ_j), h′(d) = −sin d / (2r²(1 − cos d)²). O(n²) numpy."""
    phi = np.asarray(phi, float).ravel()
    n = phi.size
    d = phi[:, None] - phi[None, :]
    one_minus_cos = 1.0 - np.cos(d)
    np.fill_diagonal(one_minus_cos, 1.0)  # the i = j terms are excluded (sin 0 = 0 below)
    h1 = -np.sin(d) / (2 * radius**2 * one_minus_cos**2)
    return (radius**2 / n**3) * 2 * h1.sum(axis=1)[: n - 1]


def coupling_jacobian(phi: np.ndarray, radius: float) -> np.ndarray:
    """dc/dφ ((n−1) × n) in closed form: off the diagonal −2 h″(φ_k − φ_m), on it
    2 Σ_{j≠k} h″(φ_k − φ_j), with h″(d) = (2 + cos d)/(2r²(1 − cos d)²). O(n²) numpy."""
    phi = np.asarray(phi, float).ravel()
    n = phi.size
    d = phi[:, None] - phi[None, :]
    cos = np.cos(d)
    one_minus_cos = 1.0 - cos
    np.fill_diagonal(one_minus_cos, 1.0)
    h2 = (2.0 + cos) / (2 * radius**2 * one_minus_cos**2)
    np.fill_diagonal(h2, 0.0)
    hessian = -2.0 * h2
    np.fill_diagonal(hessian, 2.0 * h2.sum(axis=1))
    return (radius**2 / n**3) * hessian[: n - 1]


def equidistance_error(phi: np.ndarray) -> float:
    """max_i |gap_i − 2π/n| over the n gaps between consecutive angles on the circle (rad)."""
    angles = np.sort(np.mod(np.asarray(phi, float), 2 * np.pi))
    gaps = np.diff(np.append(angles, angles[0] + 2 * np.pi))
    return float(np.max(np.abs(gaps - 2 * np.pi / len(angles))))
