"""Zermelo's boat crossing a jet: minimum time against minimum control energy, with the boat's
speed through the water limited in norm (a MACS example in none of the papers).

A boat crosses a channel of width H from (0, −H/2) to (0, H/2) against a jet flowing along x,
w(y) = w0 (1 − (2y/H)²) (zero at the banks, w0 in the middle):

    ẋ = u_x + w(y),   ẏ = u_y,   |u|₂ ≤ V,   J1 = t_f ∈ [2, 8],   J2 = ∫|u|² dt,

with Cartesian controls u = (u_x, u_y) (:func:`make`; the speed limit a
:class:`~ocpar.ocp.constraints.PathConstraint`) or polar ones, speed s ∈ [0, V] and heading
θ ∈ [−π, π] from the crossing direction, positive upstream (:func:`make_polar`; a periodic
angle whose seam ±π, heading back to the start bank, no crossing uses). The jet carries the
boat downstream while it crosses and the boat steers back upstream; the slower the crossing,
the longer the jet pushes, so the least energy falls ever more slowly with t_f (defaults
H = 2, w0 = 1, V = 2, 8 elements of order 4 with linear controls: J2 ≈ 1.19 at t_f = 8, and
the speed limit binds at t_f = 2). No front in closed form: the problem has no reference
front.
"""

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.macs import MacsProblem, Objective
from ocpar.ocp.constraints import PathConstraint


@dataclass(frozen=True)
class JetBoat:
    """ẋ = u_x + w0 (1 − (2y/H)²), ẏ = u_y (``polar``: u = s (−sin θ, cos θ), θ from the
    crossing direction +y, positive upstream); state (x, y), control (u_x, u_y) or (s, θ)."""

    jet: float = 1.0
    width: float = 2.0
    polar: bool = False
    nx: int = 2
    nu: int = 2

    def velocity(self, u):
        """The boat's velocity through the water (2,) from the control."""
        if self.polar:
            return -u[0] * ca.sin(u[1]), u[0] * ca.cos(u[1])
        return u[0], u[1]

    def rhs(self, x, u):
        vx, vy = self.velocity(u)
        return ca.vertcat(vx + self.jet * (1 - (2 * x[1] / self.width) ** 2), vy)

    def state_bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)


def _problem(model: JetBoat, t_min: float, t_max: float, elements: int,
             **controls) -> MacsProblem:
    half = model.width / 2
    energy = ((lambda x, u: u[0] ** 2) if model.polar else (lambda x, u: ca.sumsqr(u)))
    return MacsProblem(
        name="zermelo-polar" if model.polar else "zermelo",
        model=model,
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=energy, name="∫|u|² dt")),
        initial_state=(0.0, -half),
        final_time=(t_min, t_max),
        final_state={0: 0.0, 1: half},
        elements=elements, order=4, control_order=1, **controls,
    )


def make(jet: float = 1.0, width: float = 2.0, speed: float = 2.0, t_min: float = 2.0,
         t_max: float = 8.0, elements: int = 8) -> MacsProblem:
    """Cartesian controls u ∈ [−V, V]², |u|² ≤ V² (``speed`` V) as a path constraint;
    t_f ∈ [``t_min``, ``t_max``]; the jet's peak ``jet`` w0 and the channel's ``width`` H."""
    return _problem(JetBoat(jet, width), t_min, t_max, elements,
                    control_bounds=((-speed, speed), (-speed, speed)),
                    path_constraints=(PathConstraint(lambda u: ca.sumsqr(u), upper=speed**2,
                                                     name="speed"),))


def make_polar(jet: float = 1.0, width: float = 2.0, speed: float = 2.0, t_min: float = 2.0,
               t_max: float = 8.0, elements: int = 8) -> MacsProblem:
    """The same crossing with polar controls: speed s ∈ [0, V], heading θ ∈ [−π, π] from the
    crossing direction (periodic)."""
    return _problem(JetBoat(jet, width, polar=True), t_min, t_max, elements,
                    control_bounds=((0.0, speed), (-np.pi, np.pi)),
                    periodic_controls=(False, True))
