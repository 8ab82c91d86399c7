"""Closed curves z(φ) in 2-D or 3-D on which a formation ends: φ ↦ z(φ), period 2π in φ.

A curve is defined once, symbolically: :meth:`Curve.point` maps a scalar CasADi symbol φ to
the column z(φ) (d entries, d = 2 or 3, in the model's length unit). Everything else comes from
it by CasADi's automatic differentiation: the tangent z′(φ) (for the outer gradient
dĴ_i/dφ_i = dJ*_i/dq_N · z′(φ_i)) and z″(φ) (for the coupling's Jacobian), evaluated on numpy
arrays of angles.

* :class:`Circle` and :class:`Ellipse`: the classic shapes, in the plane spanned by two
  orthonormal rows ``axes`` (2, d) about ``center`` (a tilted plane in 3-D).
* :class:`PlaneCurve`: any closed profile φ ↦ (x(φ), y(φ)) placed in such a plane.
* :class:`ParametricCurve`: any closed curve φ ↦ z(φ), as a Python function of a CasADi
  symbol or a :class:`casadi.Function` of one scalar input.

Each is checked when built (finite data, orthonormal axes, z evaluates to d finite entries,
z(φ + 2π) = z(φ), nonzero length): one ValueError naming the field.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

#: Angles at which a curve is sampled for its checks, its length and its frame.
SAMPLES = 1024

#: z(φ + 2π) must equal z(φ) to this fraction of the curve's size.
CLOSURE_RTOL = 1e-9

#: Newton steps of :meth:`Curve.locate` at most (from a hint on the curve: one or two).
LOCATE_STEPS = 8

#: Equal panels of [0, 2π) and Gauss–Legendre nodes per panel of the arc length s(φ)
#: (:meth:`Curve.arc_lengths`): ~1e-15 relative on an ellipse of axis ratio 2.
ARC_PANELS, ARC_NODES = 16, 16

Expression = ca.SX | ca.MX


class Curve(ABC):
    """A closed curve z(φ) ∈ R^d, d = 2 or 3, with z(φ + 2π) = z(φ)."""

    @property
    @abstractmethod
    def dim(self) -> int:
        """d, the number of position entries the curve fixes (2 or 3)."""

    @abstractmethod
    def point(self, phi: Expression) -> Expression:
        """z(φ) as a CasADi column (d, 1) of the scalar symbol φ (rad)."""

    @cached_property
    def _derivatives(self) -> ca.Function:
        """φ ↦ (z, z′, z″), compiled once; called with a row of angles it maps over them."""
        phi = ca.SX.sym("phi")
        z = self.point(phi)
        dz = ca.jacobian(z, phi)
        return ca.Function("curve", [phi], [z, dz, ca.jacobian(dz, phi)])

    @cached_property
    def evaluator(self) -> CurveEvaluator | CircleEvaluator:
        """z, z′, z″ of the curve, picklable (built once): what a worker evaluates its
        agents' targets with, and what :meth:`points`, :meth:`tangents` and
        :meth:`curvatures` call, so that both give the same bits."""
        return CurveEvaluator(self._derivatives, self.dim)

    @cached_property
    def arc_evaluator(self) -> CurveEvaluator:
        """The curve's arc length s(φ) and length ℓ with z, z′, z″, picklable (built on first
        use): what :meth:`arc_lengths` and :meth:`at_arc_lengths` call."""
        arc = self._arc_length
        length = float(np.asarray(arc(np.array([[2 * np.pi]]))[0]).ravel()[0])
        return CurveEvaluator(self._derivatives, self.dim, arc, length)

    def points(self, phi: np.ndarray) -> np.ndarray:
        """z(φ) for angles φ (n,) rad: shape (n, d)."""
        return self.evaluator.evaluate(phi, 0)

    def tangents(self, phi: np.ndarray) -> np.ndarray:
        """z′(φ) = dz/dφ for angles φ (n,): shape (n, d), length unit per rad."""
        return self.evaluator.evaluate(phi, 1)

    def curvatures(self, phi: np.ndarray) -> np.ndarray:
        """z″(φ) = d²z/dφ² for angles φ (n,): shape (n, d), length unit per rad²."""
        return self.evaluator.evaluate(phi, 2)

    @cached_property
    def _arc_length(self) -> ca.Function:
        """φ ↦ (s, s′, s″), s(φ) = ∫_0^φ |z′(t)| dt, compiled once (maps over a row).

        On [0, 2π) a composite Gauss–Legendre rule with :data:`ARC_PANELS` panels of
        [0, φ] and :data:`ARC_NODES` nodes each (smooth in φ); beyond, s(φ + 2πk) = s(φ) + kℓ
        with ℓ the same rule at 2π, so s is continuous and s(φ + 2π) − s(φ) = ℓ exactly."""
        phi, t = ca.SX.sym("phi"), ca.SX.sym("t")
        speed = ca.Function("speed", [t], [ca.norm_2(ca.jacobian(self.point(t), t))])
        nodes, weights = np.polynomial.legendre.leggauss(ARC_NODES)
        fractions = ((np.arange(ARC_PANELS)[:, None] + (nodes[None, :] + 1) / 2)
                     / ARC_PANELS).ravel()
        weights = np.tile(weights / (2 * ARC_PANELS), ARC_PANELS)

        def rule(upper: ca.SX) -> ca.SX:
            return upper * ca.dot(ca.DM(weights), ca.vec(speed(upper * ca.DM(fractions).T)))

        turns = ca.floor(phi / (2 * np.pi))
        s = turns * rule(ca.SX(2 * np.pi)) + rule(phi - 2 * np.pi * turns)
        ds = ca.jacobian(s, phi)
        return ca.Function("arc_length", [phi], [s, ds, ca.jacobian(ds, phi)])

    def arc_length_expr(self, phi: Expression) -> Expression:
        """s(φ) for a CasADi column of angles ``phi`` (n, 1): a column (n, 1)."""
        return self._arc_length(phi.T)[0].T

    def arc_lengths(self, phi: np.ndarray, which: int = 0) -> np.ndarray:
        """s(φ) (length unit), or its first or second derivative in φ (``which`` 1, 2), at
        the angles φ (n,): shape (n,). See :attr:`length` for ℓ = s(2π)."""
        return self.arc_evaluator.arc_lengths(phi, which)

    @property
    def length(self) -> float:
        """ℓ = s(2π), the curve's length by the rule of :meth:`arc_lengths` (length unit)."""
        return self.arc_evaluator.length

    def at_arc_lengths(self, s: np.ndarray) -> np.ndarray:
        """The angles φ (n,) rad with s(φ) = ``s`` (n,) (:meth:`CurveEvaluator.at_arc_lengths`)."""
        return self.arc_evaluator.at_arc_lengths(s)

    def locate(self, points: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`points`: for ``points`` (n, d) the angles φ (n,) rad of the
        nearest points of the curve, by Newton's method on the closest-point condition
        z′(φ)·(z(φ) − x) = 0 from ``hint`` (n,) (at most :data:`LOCATE_STEPS` steps;
        Gauss–Newton where the squared distance is not convex), and the distances
        |z(φ) − x| (n,), length unit."""
        x = np.asarray(points, float)
        phi = np.array(hint, float).ravel()
        for _ in range(LOCATE_STEPS):
            z, dz, d2z = (np.asarray(v).reshape(self.dim, -1).T
                          for v in self._derivatives(phi[None, :]))
            gap = z - x
            speed_sq = np.sum(dz * dz, axis=1)
            curvature = speed_sq + np.sum(d2z * gap, axis=1)
            step = np.sum(dz * gap, axis=1) / np.where(curvature > 0, curvature, speed_sq)
            phi = phi - step
            if not np.max(np.abs(step), initial=0.0) > 1e-15 * (1 + np.max(np.abs(phi),
                                                                          initial=0.0)):
                break
        return phi, np.linalg.norm(self.points(phi) - x, axis=1)

    @property
    def rotation_invariant(self) -> bool:
        """True if a common shift of all φ moves the curve onto itself (a circle): then the
        potential G cannot tell rotated formations apart."""
        return False

    @cached_property
    def length_scale(self) -> float:
        """ℓ/(2π), ℓ the curve's length (the radius of a circle), by the trapezoidal rule on
        :data:`SAMPLES` angles (spectrally accurate on a smooth closed curve)."""
        phi = np.arange(SAMPLES) * 2 * np.pi / SAMPLES
        return float(np.mean(np.linalg.norm(self.tangents(phi), axis=1)))

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(centre (d,), axes (2, d)): the point the curve surrounds and two orthonormal rows
        spanning its plane (best fit for a non-planar curve), oriented so that φ runs
        counter-clockwise. Here: the centroid of :data:`SAMPLES` points equally spaced in φ
        and their principal directions; planar curves know theirs exactly."""
        phi = np.arange(SAMPLES) * 2 * np.pi / SAMPLES
        z = self.points(phi)
        centre = z.mean(axis=0)
        axes = np.linalg.svd(z - centre)[2][:2]
        xy = (z - centre) @ axes.T
        signed_area = np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
        if signed_area < 0:
            axes = axes[::-1]
        return centre, axes

    def parameter_at(self, angle: float) -> float:
        """The φ (rad) whose point is seen at the polar ``angle`` (rad) from the frame's centre,
        in its plane: here the nearest of :data:`SAMPLES` angles equally spaced in φ (an
        initial guess needs no more)."""
        centre, axes = self.frame()
        phi = np.arange(SAMPLES) * 2 * np.pi / SAMPLES
        xy = (self.points(phi) - centre) @ axes.T
        off = np.angle(np.exp(1j * (np.arctan2(xy[:, 1], xy[:, 0]) - angle)))
        return float(phi[np.argmin(np.abs(off))])

    def spread(self, phi_c: float, fractions: np.ndarray) -> np.ndarray:
        """The angles (rad) of the points ``fractions`` (n,) of the curve's length on from the
        point at ``phi_c`` (negative: before it): equidistant in arc length, by linear
        interpolation of the cumulative length on :data:`SAMPLES` angles."""
        grid = phi_c + np.arange(SAMPLES + 1) * 2 * np.pi / SAMPLES
        speed = np.linalg.norm(self.tangents(grid), axis=1)
        length = np.concatenate([[0.0], np.cumsum((speed[1:] + speed[:-1]) / 2)])
        fractions = np.asarray(fractions, float)
        turns = np.floor(fractions)
        return np.interp((fractions - turns) * length[-1], length, grid) + 2 * np.pi * turns

    def check(self) -> None:
        """Raise ValueError (naming the curve) unless z evaluates to d finite entries, is
        closed with period 2π and has nonzero length."""
        if self.dim not in (2, 3):
            raise ValueError(f"curve: a formation curve lies in 2-D or 3-D, got dim {self.dim}")
        try:
            phi = np.arange(SAMPLES) * 2 * np.pi / SAMPLES
            z, shifted, tangents = self.points(phi), self.points(phi + 2 * np.pi), \
                self.tangents(phi)
        except (RuntimeError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"curve: z(φ) does not evaluate: {str(exc).splitlines()[0]}") \
                from None
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(tangents))):
            raise ValueError("curve: z(φ) or z′(φ) is not finite for some φ in [0, 2π)")
        size = float(np.max(np.abs(z - z.mean(axis=0))))
        if size == 0 or not np.any(tangents):
            raise ValueError("curve: z(φ) is a single point (zero length)")
        gap = float(np.max(np.abs(shifted - z)))
        if gap > CLOSURE_RTOL * size:
            raise ValueError(f"curve: not closed with period 2π: |z(φ + 2π) − z(φ)| up to "
                             f"{gap:.1e}, size {size:.1e}")


@dataclass(frozen=True, eq=False)
class CurveEvaluator:
    """A curve's numbers as CasADi Functions, picklable: what a worker needs to place its
    agents on the curve (:mod:`ocpar.formation.outer_step`), and what the curve itself
    evaluates with, so that both compute the same bits. ``derivatives`` maps a row of angles
    φ to (z, z′, z″); ``dim`` d; with an arc length, ``arc`` maps φ to (s, s′, s″) and
    ``length`` is ℓ = s(2π) (length unit)."""

    derivatives: ca.Function
    dim: int
    arc: ca.Function | None = None
    length: float = float("nan")

    def evaluate(self, phi: np.ndarray, which: int) -> np.ndarray:
        """z (``which`` 0), z′ (1) or z″ (2) at the angles φ (n,) rad: shape (n, d)."""
        phi = np.atleast_1d(np.asarray(phi, float)).ravel()
        return np.asarray(self.derivatives(phi[None, :])[which]).reshape(self.dim, -1).T

    def arc_lengths(self, phi: np.ndarray, which: int = 0) -> np.ndarray:
        """s(φ) (length unit), or its first or second derivative in φ (``which`` 1, 2), at
        the angles φ (n,): shape (n,)."""
        phi = np.atleast_1d(np.asarray(phi, float)).ravel()
        return np.asarray(self.arc(phi[None, :])[which]).ravel()  # type: ignore[misc]

    def at_arc_lengths(self, s: np.ndarray) -> np.ndarray:
        """The angles φ (n,) rad with s(φ) = ``s`` (n,): Newton's method from the angles of
        the same fractions of a circle, each to rounding (at most 50 iterations). Element by
        element: an angle does not depend on the others given with it (a worker computes its
        agents' own)."""
        s = np.asarray(s, float)
        phi = 2 * np.pi * s / self.length
        active = np.arange(phi.size)
        for _ in range(50):
            step = (self.arc_lengths(phi.ravel()[active]) - s.ravel()[active]) \
                / self.arc_lengths(phi.ravel()[active], 1)
            phi.ravel()[active] -= step
            active = active[np.abs(step) > 4e-16 * (1 + np.abs(phi.ravel()[active]))]
            if not active.size:
                break
        return phi


@dataclass(frozen=True, eq=False)
class CircleEvaluator:
    """A circle's z, z′, z″ in closed form, picklable (:attr:`Curve.evaluator`): ``center``
    (d,), ``plane`` (2, d) its orthonormal axes, ``radius``."""

    center: np.ndarray
    plane: np.ndarray
    radius: float

    @property
    def dim(self) -> int:
        return len(self.center)

    def evaluate(self, phi: np.ndarray, which: int) -> np.ndarray:
        """z, z′ or z″ (``which`` 0, 1, 2) at the angles φ (n,), (n, d): the k-th derivative
        of (cos φ, sin φ) is (cos, sin)(φ + kπ/2). Numpy: ~0.3 ms at 10,000 angles against
        ~7 ms through the compiled CasADi function (the outer solver asks every superstep)."""
        phi = np.atleast_1d(np.asarray(phi, float)).ravel() + which * np.pi / 2
        xy = self.radius * np.column_stack([np.cos(phi), np.sin(phi)])
        return (self.center if which == 0 else 0.0) + xy @ self.plane


def _numbers(name: str, value: object) -> np.ndarray:
    """``value`` as a float array, or ValueError naming the field."""
    try:
        return np.asarray(value, float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be numbers, got {value!r}") from None


def _plane_axes(center: np.ndarray, axes: np.ndarray | None) -> np.ndarray:
    """Check ``center`` (d,) and ``axes`` (2, d) orthonormal rows (default the x1–x2 plane)."""
    d = len(center)
    if center.ndim != 1 or d not in (2, 3) or not np.all(np.isfinite(center)):
        raise ValueError(f"center: needs 2 or 3 finite entries, got {center.tolist()}")
    plane = np.eye(2, d) if axes is None else _numbers("axes", axes)
    if plane.shape != (2, d) or not np.all(np.isfinite(plane)) \
            or not np.allclose(plane @ plane.T, np.eye(2), atol=1e-12):
        raise ValueError(f"axes: must be two orthonormal rows of length {d}")
    return plane


@dataclass(frozen=True, eq=False)
class PlaneCurve(Curve):
    """A closed plane curve center + x(φ) axes[0] + y(φ) axes[1].

    ``profile`` maps a scalar CasADi symbol φ to (x(φ), y(φ)) (two expressions, or a column
    of two, in the model's length unit); ``center`` (d,) with d = 2 or 3; ``axes`` (2, d)
    orthonormal rows spanning the plane (default: the x1–x2 plane; in 3-D any tilted plane).
    """

    profile: Callable[[Expression], Expression | tuple[Expression, Expression]]
    center: np.ndarray
    axes: np.ndarray | None = None
    plane: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        center = np.atleast_1d(_numbers("center", self.center))
        object.__setattr__(self, "center", center)
        object.__setattr__(self, "plane", _plane_axes(center, self.axes))
        self.check()

    @property
    def dim(self) -> int:
        return len(self.center)

    def point(self, phi: Expression) -> Expression:
        xy = self.profile(phi)
        x, y = (xy[0], xy[1])
        return ca.DM(self.center) + x * ca.DM(self.plane[0]) + y * ca.DM(self.plane[1])

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(``center``, the plane's axes): exact."""
        return self.center, self.plane


@dataclass(frozen=True, eq=False, kw_only=True)
class Circle(PlaneCurve):
    """The circle of ``radius`` about ``center`` in the plane of ``axes``:
    z(φ) = center + r (cos φ axes[0] + sin φ axes[1]); φ is the polar angle in the plane."""

    profile: Callable = field(init=False, repr=False)
    center: np.ndarray = field(default_factory=lambda: np.zeros(2))
    axes: np.ndarray | None = None
    radius: float = 1.0

    def __post_init__(self) -> None:
        radius = _numbers("radius", self.radius)
        if radius.shape != () or not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius: must be a positive number, got {self.radius}")
        object.__setattr__(self, "radius", float(radius))
        object.__setattr__(self, "profile", lambda phi: (self.radius * ca.cos(phi),
                                                         self.radius * ca.sin(phi)))
        super().__post_init__()

    @property
    def rotation_invariant(self) -> bool:
        return True

    @property
    def length_scale(self) -> float:
        """The radius, exactly."""
        return float(self.radius)

    def parameter_at(self, angle: float) -> float:
        """The polar angle is the parameter: ``angle`` itself."""
        return float(angle)

    def locate(self, points: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """In closed form: φ (n,) the polar angle of ``points`` (n, d) in the circle's plane
        frame (atan2), on the branch nearest ``hint`` (n,); and the distances (n,) of the
        points from the circle, length unit."""
        x = np.asarray(points, float) - self.center
        xy = x @ self.plane.T
        hint = np.asarray(hint, float).ravel()
        phi = np.arctan2(xy[:, 1], xy[:, 0])
        phi = hint + np.angle(np.exp(1j * (phi - hint)))
        off_plane = x - xy @ self.plane
        radial = np.hypot(xy[:, 0], xy[:, 1]) - self.radius
        return phi, np.sqrt(radial**2 + np.sum(off_plane**2, axis=1))

    @cached_property
    def evaluator(self) -> CircleEvaluator:
        """z, z′, z″ in closed form (:class:`CircleEvaluator`)."""
        return CircleEvaluator(self.center, self.plane, self.radius)

    def spread(self, phi_c: float, fractions: np.ndarray) -> np.ndarray:
        """Arc length is proportional to φ: φ_c + 2π ``fractions``, exactly."""
        return phi_c + 2 * np.pi * np.asarray(fractions, float)


@dataclass(frozen=True, eq=False, kw_only=True)
class Ellipse(PlaneCurve):
    """The ellipse with semi-axes ``semi_axes`` = (a, b) along the rows of ``axes`` about
    ``center``: z(φ) = center + a cos φ axes[0] + b sin φ axes[1] (φ the eccentric anomaly)."""

    profile: Callable = field(init=False, repr=False)
    center: np.ndarray = field(default_factory=lambda: np.zeros(2))
    axes: np.ndarray | None = None
    semi_axes: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self) -> None:
        a_b = _numbers("semi_axes", self.semi_axes)
        if a_b.shape != (2,) or not (np.all(np.isfinite(a_b)) and np.all(a_b > 0)):
            raise ValueError(f"semi_axes: must be two positive numbers, got {self.semi_axes}")
        a, b = (float(v) for v in a_b)
        object.__setattr__(self, "semi_axes", (a, b))
        object.__setattr__(self, "profile", lambda phi: (a * ca.cos(phi), b * ca.sin(phi)))
        super().__post_init__()


@dataclass(frozen=True, eq=False)
class ParametricCurve(Curve):
    """Any closed curve given by ``z``: a Python function of a scalar CasADi symbol φ returning
    the column z(φ) (d entries, 2 or 3, built from CasADi operations such as ``ca.cos``), or a
    :class:`casadi.Function` with one scalar input and one (d, 1) output. ``name`` labels it."""

    z: Callable[[Expression], Expression]
    name: str = "curve"
    size: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not callable(self.z):
            raise ValueError(f"curve: z must be callable (φ ↦ z(φ)), got {type(self.z).__name__}")
        try:
            value = ca.vertcat(self.z(ca.SX.sym("phi")))
        except Exception as exc:  # a user's function: any failure means "does not evaluate"
            raise ValueError(f"curve: z(φ) does not evaluate on a CasADi symbol: "
                             f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                             ) from None
        if value.shape[1] != 1:
            raise ValueError(f"curve: z(φ) must be a column, got shape {value.shape}")
        object.__setattr__(self, "size", value.shape[0])
        self.check()

    @property
    def dim(self) -> int:
        return self.size

    def point(self, phi: Expression) -> Expression:
        return ca.vertcat(self.z(phi))
