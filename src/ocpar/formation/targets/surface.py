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

Every surface also maps back, :meth:`Surface.locate` (points to parameters: the inverse
chart, closed form on an ellipsoid, Gauss–Newton on a parametric surface), and gives its unit
normals at points (:meth:`Surface.normals`), so that a configuration can be moved in space
(a rotation applied to the points) and checked there without the chart. An ellipsoid can
also be re-charted, :meth:`EllipsoidSurface.charted_away`: the same surface with its pole far
from given points.

Each is checked when built (finite data, orthonormal axes, z evaluates to 3 finite entries
with a Jacobian of rank 2 away from the poles): one ValueError naming the field.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

#: Parameters per agent on a surface.
PARAMETERS = 2

#: Directions sampled for checks, the length scale and the nearest parameters of a point.
SAMPLES = 2048

#: Gauss–Newton iterations of :meth:`Surface.locate` on a parametric surface, at most.
LOCATE_ITERATIONS = 50

#: Candidate poles (spread directions) :meth:`EllipsoidSurface.charted_away` chooses from.
POLE_CANDIDATES = 256
#: :meth:`EllipsoidSurface.charted_away` keeps a chart while every point's unit vector e has
#: 1 − |pole · e| ≥ this (18° or more from either pole).
POLE_MARGIN = 0.05


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

    def locate(self, points: np.ndarray) -> np.ndarray:
        """Parameters (n, 2) (rad) of ``points`` (n, 3) on the surface (the inverse chart):
        here the closest point by Gauss–Newton on |z(φ) − p|² from the nearest of
        :data:`SAMPLES` spread points, to rounding (at most :data:`LOCATE_ITERATIONS`)."""
        points = np.asarray(points, float).reshape(-1, 3)
        spread = self.parameters_toward(fibonacci_directions(SAMPLES))
        nearest = np.argmin(np.sum((points[:, None] - self.points(spread)[None]) ** 2, axis=-1),
                            axis=1)
        phi = spread[nearest]
        for _ in range(LOCATE_ITERATIONS):
            miss = self.points(phi) - points
            step = np.stack([np.linalg.lstsq(j, -m, rcond=None)[0]
                             for j, m in zip(self.jacobians(phi), miss, strict=True)])
            phi = phi + step
            if np.max(np.abs(step)) <= 1e-15 * (1 + np.max(np.abs(phi))):
                break
        return phi

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Unit normals (n, 3) at ``points`` (n, 3) on the surface: here the cross product of
        ∂z/∂φ's columns at :meth:`locate`'s parameters (undefined where the chart is
        singular)."""
        jacobian = self.jacobians(self.locate(points))
        normal = np.cross(jacobian[:, :, 0], jacobian[:, :, 1])
        return normal / np.linalg.norm(normal, axis=1, keepdims=True)

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

    def _unit(self, points: np.ndarray) -> np.ndarray:
        """The unit vectors e (n, 3) of ``points`` (n, 3), in the ellipsoid's frame."""
        local = (np.asarray(points, float).reshape(-1, 3) - self.center) @ self.frame.T
        local = local / np.array(self.semi_axes)
        return local / np.linalg.norm(local, axis=1, keepdims=True)

    def locate(self, points: np.ndarray) -> np.ndarray:
        """The parameters (n, 2) of ``points`` (n, 3), closed form (the points seen from the
        centre, :meth:`parameters_toward`)."""
        return self.parameters_toward(np.asarray(points, float).reshape(-1, 3) - self.center)

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Unit normals (n, 3), closed form: ∝ the gradient of Σ_k (axes[k]·(p − c))²/a_k²."""
        normal = (self._unit(points) / np.array(self.semi_axes)) @ self.frame
        return normal / np.linalg.norm(normal, axis=1, keepdims=True)

    @property
    def symmetry_axes(self) -> np.ndarray:
        """Unit axes (k, 3) through ``center`` whose rotations map the surface onto itself
        (an orthonormal basis of them): all three on a sphere, the odd axis of an ellipsoid
        of revolution, none (0, 3) otherwise."""
        a = np.array(self.semi_axes)
        equal = np.isclose(a[:, None], a[None], rtol=1e-12, atol=0)
        if np.all(equal):
            return np.eye(3)
        odd = np.flatnonzero(equal.sum(axis=1) == 1)
        return self.frame[odd] if len(odd) == 1 else np.zeros((0, 3))

    def pole_distance(self, points: np.ndarray) -> float:
        """min_i (1 − |pole · e_i|) ∈ [0, 1] over ``points`` (n, 3): 0 with a point on a pole
        of the chart (e_i the points' unit vectors in the ellipsoid's frame)."""
        return float(np.min(1 - np.abs(self._unit(points) @ self.chart[2])))

    def charted_away(self, points: np.ndarray) -> EllipsoidSurface:
        """The same surface with the chart's pole the one of :data:`POLE_CANDIDATES` spread
        directions farthest from every one of ``points`` (n, 3) (the largest
        :meth:`pole_distance`); ``self`` while every point keeps :data:`POLE_MARGIN` from its
        own poles. Each re-charted surface is built once (its CasADi functions with it)."""
        if self.pole_distance(points) >= POLE_MARGIN:
            return self
        poles = fibonacci_directions(POLE_CANDIDATES)
        best = int(np.argmax(np.min(1 - np.abs(self._unit(points) @ poles.T), axis=0)))
        charts = self.__dict__.setdefault("_charts", {})
        if best not in charts:
            charts[best] = dataclasses.replace(self, pole=poles[best])
        return charts[best]


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
