"""A new worked example (in none of the papers): a fleet of ground robots with unicycle
kinematics (:class:`~ocpar.models.Unicycle`: state (x, y, ψ, v), controls acceleration a and
turn rate ω, cost ∫ a² + ω² dt) from a line onto a circle, or onto slots on it, stopping there.

The robots start at rest on the line y = −(radius + 2), spaced 1 apart and shifted by
``offset`` along it, facing +y (ψ = π/2); they end after T = ``duration`` (N = ``intervals``
RK4 multiple-shooting intervals) on the circle of ``radius`` about the origin at speed 0,
their heading free. With ``slots`` the targets are ``slots`` points evenly spaced on the circle
(only the assignment is free). ``acceleration_limit``: |a| ≤ that bound on every interval.
With ``mixed``, every second agent is a planar point mass of mass 2 instead (a DMOC agent,
N and T the same, at rest at both ends, under |u_j| ≤ ``acceleration_limit`` · 2 where
given): a fleet of DMOC and ODE agents.
"""

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, MsEndpointShape, Slots
from ocpar.models import PointMass, Unicycle


def make(agents: int = 6, radius: float = 3.0, duration: float = 6.0, intervals: int = 20,
         offset: float = 0.4, slots: int = 0, acceleration_limit: float = 0.0,
         mixed: bool = False) -> FormationProblem:
    """``agents`` unicycles onto the circle of ``radius`` (or onto ``slots`` > 0 points on it)
    in ``duration``; ``acceleration_limit`` > 0 bounds |a| (0: unbounded); ``mixed``: every
    second agent a point mass."""
    x = np.arange(agents) - (agents - 1) / 2 + offset
    starts = np.column_stack([x, np.full(agents, -(radius + 2.0)),
                              np.full(agents, np.pi / 2), np.zeros(agents)])
    bounds = (((-acceleration_limit, acceleration_limit), (-np.inf, np.inf))
              if acceleration_limit > 0 else None)
    shape = MsEndpointShape(Unicycle(), intervals=intervals, duration=duration,
                            free_end=(2,), control_bounds=bounds)
    fleet: MsEndpointShape | tuple[MsEndpointShape | DmocShape, ...] = shape
    if mixed:
        mass = DmocShape(PointMass(dim=2, mass=2.0), intervals=intervals, duration=duration,
                         control_bounds=None if bounds is None
                         else ((-2 * acceleration_limit, 2 * acceleration_limit),) * 2)
        fleet = tuple(mass if i % 2 == 0 else shape for i in range(agents))
        starts[::2, 2:] = np.nan   # a point mass's start is its position
    if slots:
        angles = 2 * np.pi * np.arange(slots) / slots
        target = Slots(radius * np.column_stack([np.cos(angles), np.sin(angles)]))
    else:
        target = Circle(radius=radius)
    return FormationProblem(name="unicycles", shape=fleet, curve=target, starts=starts,
                            final_state=np.array([np.nan, 0.0]))
