"""Minimum time against minimum control energy for a planar point mass steered by polar
controls, a thrust magnitude s ∈ [0, a] and a heading θ ∈ [−π, π] (a periodic angle): a MACS
example whose parametrisation has stationary points off the Pareto front (in none of the
papers, with its front in closed form).

A unit mass moves rest to rest from the origin to a point at distance d, r̈ = s (cos θ, sin θ),
with J1 = t_f and J2 = ∫s² dt. Its front is that of the Cartesian move
(:mod:`ocpar.examples.macs_thrust_limited`); for t_f ≥ √(6d/a) the limit is inactive and
J2 = 12 d²/t_f³, reached by s linear in time from 6d/t_f² down to 0 at t_f/2 and back up, the
heading along the move in the first half and against it in the second: with an even number of
elements a DFET control of order 1 represents it exactly. But where s = 0 the heading has no
effect, and where θ points the wrong way the magnitude's best value is 0, so the transcription
has stationary points of min Σ w_i J_i that are not Pareto optimal (a member with a wasted
element, or a heading switching at the wrong node).
"""

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.examples.macs_thrust_limited import front
from ocpar.macs import MacsProblem, Objective


@dataclass(frozen=True)
class PolarPointMass:
    """ṙ = v, v̇ = s (cos θ, sin θ) in the plane; state (r_x, r_y, v_x, v_y), control (s, θ)."""

    nx: int = 4
    nu: int = 2

    def rhs(self, x, u):
        return ca.vertcat(x[2], x[3], u[0] * ca.cos(u[1]), u[0] * ca.sin(u[1]))

    def state_bounds(self):
        return np.full(4, -np.inf), np.full(4, np.inf)


def make(distance: float = 1.0, thrust: float = 1.0, heading_deg: float = 36.87,
         t_min: float = 2.6, t_max: float = 5.0, elements: int = 8) -> MacsProblem:
    """The problem on t_f ∈ [``t_min``, ``t_max``], moving ``distance`` along ``heading_deg``
    (default: to (0.8, 0.6) d), with its closed-form front."""
    if t_min >= t_max:
        raise ValueError("t_min must be below t_max")
    heading = np.radians(heading_deg)
    target = distance * np.array([np.cos(heading), np.sin(heading)])
    return MacsProblem(
        name="polar",
        model=PolarPointMass(),
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=lambda x, u: u[0] ** 2, name="∫s² dt")),
        initial_state=(0.0, 0.0, 0.0, 0.0),
        final_time=(t_min, t_max),
        control_bounds=((0.0, thrust), (-np.pi, np.pi)),
        periodic_controls=(False, True),
        final_state={0: target[0], 1: target[1], 2: 0.0, 3: 0.0},
        elements=elements, order=3, control_order=1,
        reference_front=front(np.linspace(t_min, t_max, 2000), distance, thrust),
    )
