"""Surfaces z(φ) in 3-D on which a formation ends, two parameters per agent: φ_i ∈ R².

A surface is defined once, symbolically: :meth:`Surface.point` maps a CasADi column φ (2, 1)
to the point z(φ) (3, 1) (the model's length unit); its derivatives come from CasADi's
automatic differentiation: the Jacobian ∂z/∂φ (3 × 2) for the outer gradient
dĴ_i/dφ_i = (∂z/∂φ_i)ᵀ ∇_pos J*_i and the second derivatives for the outer Hessian's 2 × 2
blocks. The formation's φ holds the agents' parameters as an (n, 2) array.

* :class:`SphereSurface` and :class:`EllipsoidSurface`: φ = (polar angle, azimuth), rad, of the unit
  vector e in a chart whose pole is ``pole`` (a direction in the ellipsoid's frame), the
  point center + Σ_k a_k e_k axes[k]. At the chart's poles (polar angle 0, π) the
  parametrisation is singular (the azimuth does not move the point); the default pole is a
  direction off every symmetry axis, where symmetric formations do not put an agent.
* :class:`ParametricSurface`: any φ ↦ z(φ), a Python function of a CasADi (2, 1) symbol.

Each is checked when built (finite data, orthonormal axes, z evaluates to 3 finite entries
with a Jacobian of rank 2 away from the poles): one ValueError naming the field.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

#: Parameters per agent on a surface.
PARAMETERS = 2

#: Newton steps of :meth:`Surface.locate` at most (from a hint on the surface: one or two).
LOCATE_STEPS = 8

#: Directions sampled for checks, the length scale and the nearest parameters of a point.
SAMPLES = 2048


def fibonacci_directions(n: int) -> np.ndarray:
    """n unit vectors (n, 3) spread evenly over the sphere (the Fibonacci lattice), none at
    the poles (z = ±1)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    azimuth = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), z])


class Surface(ABC):
    """A surface z(φ) ∈ R³ with two parameters φ = (φ_1, φ_2) per point."""

    #: The position entries a surface fixes.
    dim: int = 3

    @abstractmethod
    def point(self, phi: ca.SX | ca.MX) -> ca.SX | ca.MX:
        """z(φ) as a CasADi column (3, 1) of the parameter column φ (2, 1) (rad)."""

    @abstractmethod
    def parameters_toward(self, directions: np.ndarray) -> np.ndarray:
        """Parameters (n, 2) of the points seen in ``directions`` (n, 3) from the surface's
        centre: where an initial formation is laid out."""

    @cached_property
    def _derivatives(self) -> ca.Function:
        """φ ↦ (z, ∂z/∂φ as a row (1, 6), ∂²z/∂φ² as a row (1, 12)), maps over columns."""
        phi = ca.SX.sym("phi", PARAMETERS)
        z = self.point(phi)
        jacobian = ca.jacobian(z, phi)
        second = ca.jacobian(ca.vec(jacobian), phi)
        return ca.Function("surface", [phi], [z, ca.vec(jacobian).T, ca.vec(second).T])

    def _evaluate(self, phi: np.ndarray, which: int) -> np.ndarray:
        phi = np.asarray(phi, float).reshape(-1, PARAMETERS)
        out = np.asarray(self._derivatives(phi.T)[which])
        return out.T if which == 0 else out.reshape(len(phi), -1)

    def points(self, phi: np.ndarray) -> np.ndarray:
        """z(φ) for parameters φ (n, 2) rad: shape (n, 3)."""
        return self._evaluate(phi, 0)

    def jacobians(self, phi: np.ndarray) -> np.ndarray:
        """∂z/∂φ (n, 3, 2), length unit per rad."""
        return self._evaluate(phi, 1).reshape(-1, PARAMETERS, 3).transpose(0, 2, 1)

    def second_derivatives(self, phi: np.ndarray) -> np.ndarray:
        """∂²z/∂φ_a∂φ_b (n, 3, 2, 2), length unit per rad²."""
        return (self._evaluate(phi, 2).reshape(-1, PARAMETERS, PARAMETERS, 3)
                .transpose(0, 3, 2, 1))

    def locate(self, points: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`points` through the chart: for ``points`` (n, 3) the
        parameters (n, 2) of the nearest points of the surface by Newton's method on
        ½|z(φ) − x|² from ``hint`` (n, 2) (at most :data:`LOCATE_STEPS` steps; Gauss–Newton
        where its Hessian is not positive definite, pseudo-inverses at a chart's pole), and
        the distances |z(φ) − x| (n,), length unit."""
        x = np.asarray(points, float)
        phi = np.array(hint, float).reshape(-1, PARAMETERS)
        finite = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(phi), axis=1)
        if not np.all(finite):   # a failed path's point: NaN parameters and distance
            located, distance = np.full_like(phi, np.nan), np.full(len(phi), np.nan)
            if np.any(finite):
                located[finite], distance[finite] = self.locate(x[finite], phi[finite])
            return located, distance
        for _ in range(LOCATE_STEPS):
            gap, jac = self.points(phi) - x, self.jacobians(phi)
            gauss = np.einsum("nka,nkb->nab", jac, jac)
            hessian = gauss + np.einsum("nk,nkab->nab", gap, self.second_derivatives(phi))
            convex = (np.linalg.det(hessian) > 0) & (np.trace(hessian, axis1=1, axis2=2) > 0)
            hessian = np.where(convex[:, None, None], hessian, gauss)
            step = np.einsum("nab,nb->na", np.linalg.pinv(hessian),
                             np.einsum("nka,nk->na", jac, gap))
            phi = phi - step
            if not np.max(np.abs(step), initial=0.0) > 1e-15 * (1 + np.max(np.abs(phi),
                                                                          initial=0.0)):
                break
        return phi, np.linalg.norm(self.points(phi) - x, axis=1)

    @cached_property
    def length_scale(self) -> float:
        """The RMS distance (length unit) of :data:`SAMPLES` evenly spread points from their
        centroid (a sphere's radius)."""
        z = self.points(self.parameters_toward(fibonacci_directions(SAMPLES)))
        return float(np.sqrt(np.mean(np.sum((z - z.mean(axis=0)) ** 2, axis=1))))

    def check(self) -> None:
        """Raise ValueError (naming ``curve``, the problem's target field) unless z and its
        Jacobian are finite, of rank 2, at :data:`SAMPLES` points spread over the surface."""
        try:
            phi = self.parameters_toward(fibonacci_directions(SAMPLES))
            z, jacobian = self.points(phi), self.jacobians(phi)
        except (RuntimeError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"curve: the surface's z(φ) does not evaluate: "
                             f"{str(exc).splitlines()[0]}") from None
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(jacobian))):
            raise ValueError("curve: the surface's z(φ) or its Jacobian is not finite")
        singular = np.linalg.svd(jacobian, compute_uv=False)
        if np.any(singular[:, 1] <= 1e-9 * singular[:, 0]):
            raise ValueError("curve: the surface's Jacobian ∂z/∂φ has rank < 2 at some of "
                             "its points: not a parametrised surface")


def _frame(axes: np.ndarray | None) -> np.ndarray:
    """Three orthonormal rows (default the identity), or ValueError naming ``axes``."""
    frame = np.eye(3) if axes is None else np.asarray(axes, float)
    if frame.shape != (3, 3) or not np.all(np.isfinite(frame)) \
            or not np.allclose(frame @ frame.T, np.eye(3), atol=1e-12):
        raise ValueError("axes: must be three orthonormal rows of length 3")
    return frame


#: The default chart pole of an ellipsoid, in its frame: off every symmetry axis and plane.
DEFAULT_POLE = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)


def _chart(pole: np.ndarray | None) -> np.ndarray:
    """Orthonormal rows (3, 3), the last along ``pole`` (default :data:`DEFAULT_POLE`)."""
    pole = DEFAULT_POLE if pole is None else np.asarray(pole, float)
    if pole.shape != (3,) or not np.all(np.isfinite(pole)) or not np.any(pole):
        raise ValueError("pole: must be a nonzero direction of 3 finite entries")
    pole = pole / np.linalg.norm(pole)
    first = np.cross(pole, np.eye(3)[np.argmin(np.abs(pole))])
    first /= np.linalg.norm(first)
    return np.array([first, np.cross(pole, first), pole])


@dataclass(frozen=True, eq=False, kw_only=True)
class EllipsoidSurface(Surface):
    """center + Σ_k a_k e_k axes[k]: semi-axes ``semi_axes`` (3,) along the rows of ``axes``
    (3 × 3 orthonormal, default the coordinate axes), about ``center`` (3,); e the unit
    vector with polar angle φ_1 and azimuth φ_2 about ``pole`` (default
    :data:`DEFAULT_POLE`), e = Cᵀ (sin φ_1 cos φ_2, sin φ_1 sin φ_2, cos φ_1), C the chart's
    orthonormal rows with the pole last."""

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    semi_axes: tuple[float, float, float] = (1.0, 1.0, 1.0)
    axes: np.ndarray | None = None
    pole: np.ndarray | None = None
    frame: np.ndarray = field(init=False, repr=False)
    chart: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        center = np.asarray(self.center, float)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"center: needs 3 finite entries, got {np.ravel(center).tolist()}")
        semi = np.asarray(self.semi_axes, float)
        if semi.shape != (3,) or not np.all(np.isfinite(semi) & (semi > 0)):
            raise ValueError(f"semi_axes: must be 3 positive numbers, got {self.semi_axes}")
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "semi_axes", tuple(float(a) for a in semi))
        object.__setattr__(self, "frame", _frame(self.axes))
        object.__setattr__(self, "chart", _chart(self.pole))
        self.check()

    def point(self, phi: ca.SX | ca.MX) -> ca.SX | ca.MX:
        polar, azimuth = phi[0], phi[1]
        unit = ca.mtimes(ca.DM(self.chart.T), ca.vertcat(
            ca.sin(polar) * ca.cos(azimuth), ca.sin(polar) * ca.sin(azimuth), ca.cos(polar)))
        return ca.DM(self.center) + ca.mtimes(ca.DM(self.frame.T),
                                              ca.DM(self.semi_axes) * unit)

    def parameters_toward(self, directions: np.ndarray) -> np.ndarray:
        """The parameters of e(φ) ∝ the directions in the ellipsoid's scaled frame."""
        local = (np.asarray(directions, float) @ self.frame.T) / np.array(self.semi_axes)
        local = local / np.linalg.norm(local, axis=1, keepdims=True) @ self.chart.T
        return np.column_stack([np.arccos(np.clip(local[:, 2], -1, 1)),
                                np.arctan2(local[:, 1], local[:, 0])])


@dataclass(frozen=True, eq=False, kw_only=True)
class SphereSurface(EllipsoidSurface):
    """The sphere of ``radius`` about ``center`` (parameters as :class:`EllipsoidSurface`)."""

    radius: float = 1.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius: must be a positive number, got {self.radius}")
        object.__setattr__(self, "semi_axes", (float(self.radius),) * 3)
        super().__post_init__()

    @property
    def length_scale(self) -> float:
        """The radius, exactly."""
        return float(self.radius)


@dataclass(frozen=True, eq=False)
class ParametricSurface(Surface):
    """Any surface given by ``z``: a Python function of a CasADi (2, 1) symbol φ returning the
    column z(φ) (3, 1), built from CasADi operations. ``directions`` maps unit directions
    (n, 3) to parameters (n, 2) for the initial layout (default: the nearest of
    :data:`SAMPLES` points of a grid in φ ∈ [0, π] × [−π, π) seen from their centroid)."""

    z: Callable[[ca.SX], ca.SX]
    name: str = "surface"
    directions: Callable[[np.ndarray], np.ndarray] | None = None

    def __post_init__(self) -> None:
        if not callable(self.z):
            raise ValueError(f"curve: z must be callable (φ ↦ z(φ)), got {type(self.z).__name__}")
        try:
            value = ca.vertcat(self.z(ca.SX.sym("phi", PARAMETERS)))
        except Exception as exc:  # a user's function: any failure means "does not evaluate"
            raise ValueError(f"curve: the surface's z(φ) does not evaluate on a CasADi (2, 1) "
                             f"symbol: {type(exc).__name__}: "
                             f"{str(exc).splitlines()[0] if str(exc) else ''}") from None
        if value.shape != (3, 1):
            raise ValueError(f"curve: the surface's z(φ) must be a column of 3, got shape "
                             f"{value.shape}")
        self.check()

    def point(self, phi: ca.SX | ca.MX) -> ca.SX | ca.MX:
        return ca.vertcat(self.z(phi))

    def parameters_toward(self, directions: np.ndarray) -> np.ndarray:
        if self.directions is not None:
            return np.asarray(self.directions(directions), float).reshape(-1, PARAMETERS)
        side = int(np.sqrt(SAMPLES))
        grid = np.stack(np.meshgrid(np.linspace(0.02, np.pi - 0.02, side),
                                    np.linspace(-np.pi, np.pi, side, endpoint=False)),
                        axis=-1).reshape(-1, PARAMETERS)
        z = self.points(grid)
        seen = z - z.mean(axis=0)
        seen /= np.maximum(np.linalg.norm(seen, axis=1, keepdims=True), 1e-300)
        return grid[np.argmax(np.asarray(directions, float) @ seen.T, axis=1)]
