"""Where a thrust-limited point mass can go: the exact reach set of its DMOC transcription.

A :class:`~ocpar.models.PointMass` (L = ½ m |q̇|², force u) at rest at both ends of [0, T]
moves by Δ = q_N − q_0. DMOC's equations (:mod:`ocpar.ocp.dmoc`) are linear in the inner
nodes, the controls and q_N, and decouple by axis, so the displacements it can reach are

* under a box limit lo_j ≤ u_k[j] ≤ hi_j (``DmocShape.control_bounds``): the box
  Δ_j ∈ [reach(lo_j, hi_j) below, reach above] per axis;
* under a norm limit |u_k| ≤ a (one path constraint c |u|² ≤ b of ``u`` alone, a = √(b/c)):
  the disc |Δ| ≤ r, r the one-axis reach under |u_k| ≤ a (zeroing the controls across a
  direction keeps a move along it feasible, and the limit is rotation invariant).

Each one-axis reach is a small linear programme on the transcription's own equations (max
and min of q_N under the bounds; :func:`scipy.optimize.linprog`), solved once per (mass, N,
T, bounds) in a process. Other models, other constraints, both limits at once or keep-out
slots: no exact set (:func:`rest_to_rest_reach` returns None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from ocpar.models import PointMass
from ocpar.ocp.dmoc import DmocShape, DmocTranscription
from ocpar.ocp.linear_quadratic import is_linear_quadratic
from ocpar.ocp.ms_endpoint import MsEndpointShape

#: A path constraint reads as c |u|² when its Hessian in u is c·2I to this relative tolerance.
QUADRATIC_RTOL = 1e-12


@dataclass(frozen=True)
class Reach:
    """The displacements Δ (d,) a rest-to-rest move reaches (the model's length unit): the box
    ``lower`` ≤ Δ ≤ ``upper`` (each (d,)) where ``radius`` is None, else the disc
    |Δ| ≤ ``radius``. ``limit`` names the constraint that bounds it (for messages)."""

    lower: np.ndarray
    upper: np.ndarray
    radius: float | None
    limit: str

    def excess(self, displacement: np.ndarray) -> np.ndarray:
        """How far displacements (..., d) lie outside the set (length unit; ≤ 0 inside, the
        distance to the set's boundary for the disc, the largest axis gap for the box: both
        1-Lipschitz): shape (...)."""
        displacement = np.asarray(displacement, float)
        if self.radius is not None:
            return np.linalg.norm(displacement, axis=-1) - self.radius
        return np.max(np.maximum(displacement - self.upper, self.lower - displacement),
                      axis=-1)

    def need(self, displacement: np.ndarray, slack: float = 0.0) -> np.ndarray:
        """The least factor s (...) by which the limit must be scaled for the set to hold a
        displacement within ``slack`` (length unit) of ``displacement`` (..., d) (the reach
        scales linearly with the limit): ≤ 1 where one is inside."""
        displacement = np.asarray(displacement, float)
        if self.radius is not None:
            return np.maximum(np.linalg.norm(displacement, axis=-1) - slack, 0) / self.radius
        shrunk = np.sign(displacement) * np.maximum(np.abs(displacement) - slack, 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            up = np.where(shrunk > 0, shrunk / self.upper, 0.0)
            down = np.where(shrunk < 0, shrunk / self.lower, 0.0)
        return np.max(np.maximum(up, down), axis=-1)


def rest_to_rest_reach(shape: DmocShape) -> Reach | None:
    """The exact reach set of ``shape`` at rest at both ends (module docstring), or None
    where it is not known exactly (not a point mass, no limit, both limits, other path
    constraints, keep-out slots). ValueError if the limits let it not come to rest at all
    (0 outside lo_j ≤ u ≤ hi_j)."""
    model = shape.model
    if not isinstance(model, PointMass) or shape.keep_out_slots:
        return None
    if shape.control_bounds is not None:
        if shape.path_constraints:
            return None
        bounds = [(float(lo), float(hi)) for lo, hi in shape.control_bounds]
        ends = np.array([_axis_reach(model.mass, shape.intervals, shape.duration, lo, hi)
                         for lo, hi in bounds])
        return Reach(ends[:, 0], ends[:, 1], None, "control_bounds")
    if len(shape.path_constraints) != 1:
        return None
    limit = _norm_limit(shape.path_constraints[0], model.nu)
    if limit is None:
        return None
    _, high = _axis_reach(model.mass, shape.intervals, shape.duration, -limit, limit)
    d = model.dim
    return Reach(np.full(d, -high), np.full(d, high), high,
                 f"path_constraints[0] ({shape.path_constraints[0].name})")


def _norm_limit(constraint: object, nu: int) -> float | None:
    """a if the compiled path constraint is c |u|² ≤ b of ``u`` alone (c > 0, lower ≤ 0, one
    row): |u| ≤ a = √(b/c); else None."""
    if constraint.arguments != ("u",) or constraint.rows != 1 or constraint.lower[0] > 0:
        return None
    u = ca.SX.sym("u", nu)
    expr = constraint.function(u)
    hessian, gradient = ca.hessian(expr, u)
    if ca.depends_on(hessian, u):
        return None
    h = np.asarray(ca.evalf(hessian))
    c = h[0, 0] / 2
    at_zero = ca.Function("at0", [u], [expr, gradient])(np.zeros(nu))
    if not (c > 0 and np.allclose(h, 2 * c * np.eye(nu), rtol=QUADRATIC_RTOL, atol=0)
            and float(at_zero[0]) == 0 and not np.any(np.asarray(at_zero[1]))):
        return None
    return math.sqrt(constraint.upper[0] / c)


#: :func:`end_cost_convexity`'s answers: J*(q_N) a convex quadratic, or convex.
QUADRATIC, CONVEX = "quadratic", "convex"


def end_cost_convexity(shape: DmocShape | MsEndpointShape) -> str | None:
    """Whether the optimal cost J* of ``shape``'s inner NLP is convex in its boundary data p
    (so in the end position): :data:`QUADRATIC` where J* is a convex quadratic of p,
    :data:`CONVEX` where it is convex, None where nothing is claimed.

    * DMOC (:class:`~ocpar.ocp.DmocShape`): ``"quadratic"`` for a point mass without
      inequalities (linear equations, cost h Σ|u_k|²: J* is a convex quadratic of p),
      ``"convex"`` for a point mass whose only inequalities are control bounds (a box) and
      norm limits c |u|² ≤ b of ``u`` alone; None for other models, a running cost, keep-out
      slots, obstacles (non-convex) or other path constraints (not claimed).
    * Multiple shooting between two states (:class:`~ocpar.ocp.MsEndpointShape`): a
      linear–quadratic model (:func:`~ocpar.ocp.linear_quadratic.is_linear_quadratic`:
      ẋ = A x + B u + c, a convex quadratic running cost bounded below; e.g.
      :class:`~ocpar.models.ClohessyWiltshire`) makes the NLP a convex quadratic programme in
      (w, p) jointly, its rows affine in both. Without inequalities ``"quadratic"``: J*(p) is
      the minimum over w of a convex quadratic bounded below on an affine set that moves
      affinely with p, attained, with the KKT conditions linear in (w, λ, p), so a convex
      quadratic of p (where the end is reachable at all; +∞ elsewhere). With control bounds
      and norm limits c |u|² ≤ b of ``u`` alone ``"convex"``; None for a nonlinear model
      (e.g. :class:`~ocpar.models.Unicycle`) or any other path constraint.

    Convex: J* is the minimum of a convex function of (w, p) over a convex set in (w, p)
    (the equations affine, each limit a convex set of w), so convex in p, and a solve's
    dJ*/dp is a subgradient: J*(p) ≥ J*(p₀) + dJ*/dp(p₀)·(p − p₀) wherever J* is finite."""
    if isinstance(shape, MsEndpointShape):
        nu = shape.model.nu
        if not is_linear_quadratic(shape.model) \
                or any(_norm_limit(c, nu) is None for c in shape.path_constraints):
            return None
        return CONVEX if shape.has_inequalities else QUADRATIC
    if not isinstance(shape.model, PointMass) or shape.running_cost is not None \
            or shape.keep_out_slots or shape.obstacles:
        return None
    if any(_norm_limit(c, shape.model.nu) is None for c in shape.path_constraints):
        return None
    if shape.control_bounds is None and not shape.path_constraints:
        return QUADRATIC
    return CONVEX


def thrust_limit(shape: DmocShape) -> tuple[str, float] | None:
    """``shape``'s thrust limit as (kind, u_max) in the force unit: ``("box", u)`` for control
    bounds −u ≤ u_j ≤ u on every entry, ``("norm", a)`` for a sole path constraint
    c |u|² ≤ b of ``u`` alone (a = √(b/c)); None without a limit or for any other one."""
    if shape.control_bounds is not None:
        highs = {float(hi) for _, hi in shape.control_bounds}
        symmetric = all(float(lo) == -float(hi) for lo, hi in shape.control_bounds)
        return ("box", highs.pop()) if symmetric and len(highs) == 1 else None
    if len(shape.path_constraints) == 1:
        limit = _norm_limit(shape.path_constraints[0], shape.model.nu)
        return None if limit is None else ("norm", limit)
    return None


@lru_cache(maxsize=256)
def _axis_reach(mass: float, intervals: int, duration: float, lo: float, hi: float
                ) -> tuple[float, float]:
    """(min, max) of q_N − q_0 of a one-axis point mass of ``mass`` at rest at both ends of
    its DMOC transcription (N = ``intervals`` over T = ``duration``) under lo ≤ u_k ≤ hi:
    two linear programmes on the transcription's equations (±inf on an unbounded side)."""
    from scipy.optimize import linprog
    if not lo <= 0 <= hi:
        raise ValueError(f"control bounds ({lo:g}, {hi:g}) exclude 0: the agent cannot stay "
                         "at rest")
    dmoc = DmocTranscription(DmocShape(PointMass(dim=1, mass=mass), intervals, duration))
    w, end = ca.SX.sym("w", dmoc.nw), ca.SX.sym("end")
    z = ca.vertcat(w, end)
    g = dmoc.constraints(w, ca.vertcat(0, 0, end, 0))
    linear = ca.Function("g", [z], [g, ca.jacobian(g, z)])
    value, jacobian = linear(np.zeros(z.numel()))
    a_eq, b_eq = np.asarray(ca.DM(jacobian)), -np.asarray(value).ravel()
    n = intervals
    bounds = [(None, None)] * (n - 1) + [(lo, hi)] * n + [(None, None)]
    ends = []
    for sign, limit in ((1.0, lo), (-1.0, hi)):
        if math.isinf(limit):   # unbounded on that side: the reach is too
            ends.append(-sign * math.inf)
            continue
        cost = np.zeros(z.numel())
        cost[-1] = sign
        result = linprog(cost, A_eq=a_eq, b_eq=b_eq, bounds=bounds, method="highs")
        if result.status != 0:
            raise ValueError(f"the reach of a point mass (mass {mass:g}) under control "
                             f"bounds ({lo:g}, {hi:g}): {result.message}")
        ends.append(float(result.x[-1]))
    return ends[0], ends[1]
