"""Couplings c(φ) = 0 of the final angles φ (n,) on a curve: what the outer problem imposes.

One protocol, :class:`Coupling`, three kinds:

* :class:`PotentialCoupling` (the default, the paper's): c = (ℓ²/n³) dG/dφ of the artificial
  potential (:mod:`ocpar.formation.couplings.potential`). On a circle its solutions are the
  equidistant
  angles, a one-parameter family (a free common rotation, chosen by the cost); on any other
  curve they are isolated (the critical points of G).
* :class:`EqualArcLength`: the agents equally spaced in arc length along any closed curve,
  with a free common shift along it that the cost chooses, as a circle's rotation.
* :class:`UserCoupling`: any g(φ) = 0 the user writes as CasADi expressions.

Each gives its residual and Jacobian (closed form where n is large, CasADi otherwise), its
symbolic rows (for the monolithic NLP), a projection of any angles onto c = 0 and, where its
solutions form a one-parameter family through a point (:class:`ShiftFamily`), that family:
there :func:`~ocpar.formation.hierarchical.solve_outer_newton` searches the shift alone, a
handful of supersteps at any n. Elsewhere it takes Newton steps in the tangent space of
c = 0 (dense: the coordinator's work grows like n³, its superstep count with the dimension
of that space), or ends after the projection where the solutions are isolated.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.formation.couplings.potential import (
    coupling,
    coupling_expr,
    coupling_jacobian,
    relax,
    respace,
)
from ocpar.formation.targets.curve import Circle, Curve, CurveEvaluator
from ocpar.formation.targets.surface import Surface

#: A projection onto c(φ) = 0 (and a solution found from the start guess) must reach
#: max |c_k| ≤ this.
PROJECTION_TOL = 1e-8

#: Gauss–Newton iterations of :meth:`Coupling.project` at most.
PROJECTION_ITERATIONS = 50

#: Singular values of dc/dφ below this times the largest count as zero (the dimension of
#: the tangent space of c = 0).
RANK_RTOL = 1e-9

#: The unit circle: equidistant parameters are the solutions of its potential's coupling.
UNIT_CIRCLE = Circle(radius=1.0)


@dataclass(frozen=True, eq=False)
class ShiftFamily:
    """Solutions φ(θ) of c = 0 through a point, one per common shift θ (rad): agent i at
    φ_i(θ) = φ(u_i + θ), u = ``base`` (n,) (rad), the map φ(u) the identity where ``chart``
    is None (a circle's equidistant angles) or the inverse of the arc-length angle
    u(φ) = 2π s(φ)/ℓ of a curve (``chart``: its :attr:`~ocpar.formation.Curve.arc_evaluator`,
    equal arc length). :meth:`angles` gives φ, dφ/dθ and d²φ/dθ² (n,) each. An agent's angle
    depends on its own u_i and θ alone (:func:`shifted`): a worker computes its agents'
    (:mod:`ocpar.formation.outer_step`)."""

    base: np.ndarray
    chart: CurveEvaluator | None = None

    def angles(self, theta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """φ (n,) rad, dφ/dθ and d²φ/dθ² (n,) at the shift ``theta`` (rad)."""
        return shifted(self.base + theta, self.chart)


def shifted(u: np.ndarray, chart: CurveEvaluator | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The angles φ(u) (rad) of shifted base angles ``u`` (m,) and their first and second
    derivatives in the shift (m,) each (:class:`ShiftFamily`), element by element: φ = u
    (``chart`` None), or s(φ) = u ℓ/2π on the curve of ``chart`` with dφ/dθ = 1/u′(φ) and
    d²φ/dθ² = −u″/u′³."""
    u = np.asarray(u, float)
    if chart is None:
        return u, np.ones(u.size), np.zeros(u.size)
    scale = 2 * np.pi / chart.length
    phi = chart.at_arc_lengths(u / scale)
    du, d2u = scale * chart.arc_lengths(phi, 1), scale * chart.arc_lengths(phi, 2)
    return phi, 1 / du, -d2u / du**3


class Coupling(ABC):
    """c(φ) = 0, m rows in the n angles φ (rad) of the agents on ``curve``.

    Subclasses give :meth:`expr`; the numeric methods default to CasADi functions of it,
    compiled once per curve and n."""

    #: Name in results and status lines.
    label: str = "coupling"

    @abstractmethod
    def expr(self, phi: ca.SX, curve: Curve) -> ca.SX:
        """c(φ) as a CasADi column (m, 1) of the angle column ``phi`` (n, 1)."""

    def _compiled(self, curve: Curve, n: int) -> tuple[Curve, ca.Function, ca.Function]:
        """φ ↦ (c, dc/dφ); (φ, λ) ↦ d²(λᵀc)/dφ²: built on first use for (curve, n)."""
        cache = self.__dict__.setdefault("_functions", {})
        key = (id(curve), n)
        if key not in cache:
            phi = ca.SX.sym("phi", n)
            c = ca.vertcat(self.expr(phi, curve))
            lam = ca.SX.sym("lam", c.numel())
            cache[key] = (curve, ca.Function("coupling", [phi], [c, ca.jacobian(c, phi)]),
                          ca.Function("coupling_hessian", [phi, lam],
                                      [ca.hessian(ca.dot(lam, c), phi)[0]]))
        return cache[key]

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_functions"}

    def residual(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        """c(φ) (m,)."""
        phi = np.asarray(phi, float).ravel()
        return np.asarray(self._compiled(curve, phi.size)[1](phi)[0]).ravel()

    def jacobian(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        """dc/dφ (m, n)."""
        phi = np.asarray(phi, float).ravel()
        return np.asarray(self._compiled(curve, phi.size)[1](phi)[1])

    def weighted_hessian(self, phi: np.ndarray, weights: np.ndarray, curve: Curve
                         ) -> np.ndarray:
        """d²(weightsᵀ c)/dφ² (n, n): the coupling's part of the outer Lagrangian's Hessian."""
        phi = np.asarray(phi, float).ravel()
        return np.asarray(self._compiled(curve, phi.size)[2](phi, weights))

    def project(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        """The solution of c = 0 that a guess ``phi`` leads to (an initial formation): here
        :meth:`retract`."""
        return self.retract(phi, curve)

    def retract(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        """The solution of c = 0 nearest ``phi`` (back onto c = 0 after a step along it):
        Gauss–Newton with minimum-norm steps while max |c_k| falls (to rounding)."""
        phi = np.asarray(phi, float).ravel()
        c = self.residual(phi, curve)
        for _ in range(PROJECTION_ITERATIONS):
            trial = phi - np.linalg.lstsq(self.jacobian(phi, curve), c, rcond=None)[0]
            trial_c = self.residual(trial, curve)
            if not np.max(np.abs(trial_c), initial=0.0) < np.max(np.abs(c), initial=0.0):
                break
            phi, c = trial, trial_c
        return phi

    def family(self, phi: np.ndarray, curve: Curve) -> ShiftFamily | None:
        """The one-parameter family of solutions through the projection of ``phi``, where
        the coupling's solutions form one; None otherwise."""
        return None

    def free_directions(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        """An orthonormal basis (n, r) of the tangent space of c = 0 at ``phi``: r = 0 where
        the solution is isolated."""
        from scipy.linalg import null_space
        return null_space(self.jacobian(phi, curve), rcond=RANK_RTOL)

    def feasible_set(self, phi: np.ndarray, curve: Curve) -> str:
        """``continuous`` if the solutions near ``phi`` (a solution) form a manifold the cost
        chooses on, ``discrete`` if they are isolated."""
        return "continuous" if self.free_directions(phi, curve).shape[1] else "discrete"

    def check(self, curve: Curve, n: int) -> None:
        """Raise ValueError (one line naming ``coupling``) unless c evaluates on n symbolic
        angles to a column of 1…n rows."""
        try:
            rows = ca.vertcat(self.expr(ca.SX.sym("phi", n), curve))
        except Exception as exc:  # a user's function: any failure means "does not evaluate"
            raise ValueError(f"coupling: g(phi) does not evaluate on {n} symbolic angles: "
                             f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                             ) from None
        if rows.shape[1] != 1 or not 1 <= rows.shape[0] <= n:
            raise ValueError(f"coupling: g(phi) must be a column of 1 to {n} rows for {n} "
                             f"agents, got shape {rows.shape}")


@dataclass(frozen=True)
class PotentialCoupling(Coupling):
    """The paper's c(φ) = (ℓ²/n³) dG/dφ = 0 (:mod:`ocpar.formation.couplings.potential`), G the sum
    of 1/|z_i − z_j|² over pairs. On a curve in closed form, on a circle its first n − 1 rows
    (the free rotation is the family). On a :class:`~ocpar.formation.targets.surface.Surface` all 2n
    rows by CasADi (ℓ its length scale); on a sphere its solutions come with three free
    directions, the rotations, which the outer solver searches."""

    label: str = "potential"

    def expr(self, phi: ca.SX, curve: Curve | Surface) -> ca.SX:
        if isinstance(curve, Surface):
            return ca.gradient(_scaled_surface_potential(phi, curve), phi)
        return coupling_expr(phi, curve)

    def residual(self, phi: np.ndarray, curve: Curve | Surface) -> np.ndarray:
        if isinstance(curve, Surface):
            return super().residual(phi, curve)
        return coupling(phi, curve)

    def jacobian(self, phi: np.ndarray, curve: Curve | Surface) -> np.ndarray:
        if isinstance(curve, Surface):
            return super().jacobian(phi, curve)
        return coupling_jacobian(phi, curve)

    def project(self, phi: np.ndarray, curve: Curve | Surface) -> np.ndarray:
        """The local minimum of G that ``phi`` leads to (:func:`relax`; on a surface SciPy's
        trust-exact on the scaled G, then :meth:`retract`); circles: ``phi``."""
        if not isinstance(curve, Surface):
            return relax(phi, curve)
        from scipy.optimize import minimize

        phi = np.asarray(phi, float).ravel()

        relaxed = minimize(lambda x: self.scaled_potential(x, curve), phi,
                           jac=lambda x: self.residual(x, curve),
                           hess=lambda x: self.jacobian(x, curve), method="trust-exact",
                           options={"gtol": 1e-12})
        return self.retract(np.asarray(relaxed.x, float), curve)

    def scaled_potential(self, phi: np.ndarray, surface: Surface) -> float:
        """The scaled potential (ℓ²/n³) G on a surface (its gradient is c)."""
        n = phi.size // 2
        cache = self.__dict__.setdefault("_functions", {})
        key = ("G", id(surface), n)
        if key not in cache:
            x = ca.SX.sym("phi", 2 * n)
            cache[key] = (surface, ca.Function("G", [x], [_scaled_surface_potential(x, surface)]))
        return float(cache[key][1](phi))

    def family(self, phi: np.ndarray, curve: Curve | Surface) -> ShiftFamily | None:
        """On a circle the equidistant angles in ``phi``'s cyclic order, rotated by θ."""
        if isinstance(curve, Surface) or not curve.rotation_invariant:
            return None
        return ShiftFamily(respace(phi))

    def free_directions(self, phi: np.ndarray, curve: Curve | Surface) -> np.ndarray:
        if isinstance(curve, Surface):
            return super().free_directions(phi, curve)
        n = np.asarray(phi).size
        return (np.full((n, 1), 1 / np.sqrt(n)) if curve.rotation_invariant
                else np.zeros((n, 0)))

    def check(self, curve: Curve | Surface, n: int) -> None:
        """The potential evaluates on every target the problem accepts: nothing to check."""


def _scaled_surface_potential(phi: ca.SX, surface: Surface) -> ca.SX:
    """(ℓ²/n³) G, G = Σ_{i≠j} 1/|z(φ_i) − z(φ_j)|², for the parameters φ (2n, 1), agent i's
    at 2i, 2i+1 (ℓ the surface's length scale)."""
    n = phi.numel() // 2
    z = [surface.point(phi[2 * i : 2 * i + 2]) for i in range(n)]
    return surface.length_scale**2 / n**3 * 2 * ca.sum1(ca.vertcat(*[1.0 / ca.sumsqr(z[i] - z[j])
                                    for i in range(len(z)) for j in range(i + 1, len(z))]))


@dataclass(frozen=True)
class EqualArcLength(Coupling):
    """The agents equally spaced in arc length along the curve, in any cyclic order, with a
    free common shift.

    With u(φ) = 2π s(φ)/ℓ the arc-length angle (:meth:`~ocpar.formation.Curve.arc_lengths`),
    c(φ) is the unit circle's potential coupling at u (n − 1 rows, zero exactly where the u_i
    are equidistant): the same rows in the monolithic NLP and in the outer solver. The family
    through φ: u_i = u_i⁰ + θ, u⁰ the nearest equidistant arc-length angles."""

    label: str = "equal-arc-length"

    def _u(self, phi: np.ndarray, curve: Curve, which: int = 0) -> np.ndarray:
        """u(φ) (rad) or its derivatives in φ (``which`` 1, 2), (n,)."""
        return 2 * np.pi / curve.length * curve.arc_lengths(phi, which)

    def expr(self, phi: ca.SX, curve: Curve) -> ca.SX:
        u = ca.SX.sym("u", phi.numel())
        on_circle = ca.Function("equidistance", [u], [coupling_expr(u, UNIT_CIRCLE)])
        return on_circle(2 * np.pi / curve.length * curve.arc_length_expr(phi))

    def residual(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        return coupling(self._u(phi, curve), UNIT_CIRCLE)

    def jacobian(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        return coupling_jacobian(self._u(phi, curve), UNIT_CIRCLE) * self._u(phi, curve, 1)

    def _angles(self, u: np.ndarray, curve: Curve) -> np.ndarray:
        return curve.at_arc_lengths(u * curve.length / (2 * np.pi))

    def project(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        return self._angles(respace(self._u(phi, curve)), curve)

    def family(self, phi: np.ndarray, curve: Curve) -> ShiftFamily:
        return ShiftFamily(respace(self._u(phi, curve)), chart=curve.arc_evaluator)

    def free_directions(self, phi: np.ndarray, curve: Curve) -> np.ndarray:
        along = 1 / self._u(phi, curve, 1)
        return (along / np.linalg.norm(along))[:, None]

    def check(self, curve: Curve, n: int) -> None:
        """Every closed curve has an arc length: nothing to check."""


@dataclass(frozen=True)
class UserCoupling(Coupling):
    """A user's coupling: ``g`` maps the angle column φ (n, 1), a CasADi SX symbol, to the
    column g(φ) (m, 1), 1 ≤ m ≤ n, built from CasADi operations. Its Jacobian and Hessian
    come from CasADi; the outer solver projects onto g = 0 by Gauss–Newton and steps in its
    tangent space (dense: for tens to hundreds of agents)."""

    g: Callable[[ca.SX], ca.SX]
    label: str = "user"

    def __post_init__(self) -> None:
        if not callable(self.g):
            raise ValueError(f"coupling: g must be callable (phi -> g(phi)), got "
                             f"{type(self.g).__name__}")

    def expr(self, phi: ca.SX, curve: Curve) -> ca.SX:
        return ca.vertcat(self.g(phi))
