"""Spacecraft near a target in low Earth orbit (Clohessy–Wiltshire): from a train parked on
the V-bar onto a ring of hold points about the target, in half an orbit.

The chasers start at rest on the V-bar (the target's along-track line, x = z = 0: an
equilibrium of the Clohessy–Wiltshire equations, where a rendezvous parks its vehicles),
behind the target at y = −300 m, −350 m, … (50 m apart), and must arrive after half an orbit
(T = π/n = 46.3 min at n = 0.06786 rad/min, about 400 km up) at rest relative to the target on
the circle of ``radius`` about it in the radial/along-track (x–y) plane: a ring of hold
points from which they could, e.g., inspect the target together (off the V-bar a hold point
takes thrust to keep, as an R-bar hold does). Which chaser takes which hold point, and the
ring's rotation, are the formation's choice (``--ordering optimal`` proves the best; the
inner cost ∫|u|² dt is a convex quadratic of the end state:
:func:`~ocpar.ocp.reach.end_cost_convexity`). Units: m and min (the thrust acceleration in
m/min², 1 m/min² = 2.78e-4 m/s²; the cost in m²/min³: in seconds the outer search's
gradients are noisier than its tolerance, :class:`~ocpar.models.ClohessyWiltshire`).
Multiple shooting with RK4, N = ``intervals`` intervals.
"""

import numpy as np

from ocpar.formation import Circle, FormationProblem
from ocpar.models import ClohessyWiltshire
from ocpar.models.clohessy_wiltshire import LEO_MEAN_MOTION
from ocpar.ocp import MsEndpointShape

#: The target's mean motion (rad/min): a circular orbit about 400 km up.
MEAN_MOTION = 60 * LEO_MEAN_MOTION

#: The first chaser's distance behind the target on the V-bar, and the train's spacing (m).
FIRST_BEHIND, SPACING = 300.0, 50.0


def v_bar_train(agents: int) -> np.ndarray:
    """Start states (agents, 6) at rest on the V-bar, :data:`FIRST_BEHIND` m behind the
    target and :data:`SPACING` m apart (m, m/min)."""
    starts = np.zeros((agents, 6))
    starts[:, 1] = -FIRST_BEHIND - SPACING * np.arange(agents)
    return starts


def make(agents: int = 6, radius: float = 100.0, mean_motion: float = MEAN_MOTION,
         orbits: float = 0.5, intervals: int = 20,
         starts: np.ndarray | None = None, duration: float | None = None) -> FormationProblem:
    """``agents`` Clohessy–Wiltshire spacecraft (target mean motion ``mean_motion``, rad/min)
    from ``starts`` (agents, 6) (m, m/min; default :func:`v_bar_train`) onto hold points on
    the circle of ``radius`` (m) about the target in the radial/along-track plane, at rest,
    after ``orbits`` of the target's period (T = 2π ``orbits`` / n min), or after
    ``duration`` min where given."""
    model = ClohessyWiltshire(mean_motion, time_unit="min")
    if not (np.isfinite(orbits) and orbits > 0):
        raise ValueError(f"orbits: must be a positive number, got {orbits!r}")
    return FormationProblem(
        name="cw-ring",
        shape=MsEndpointShape(model, intervals=intervals,
                              duration=(2 * np.pi * orbits / model.mean_motion
                                        if duration is None else duration)),
        curve=Circle(radius=radius, center=np.zeros(3), axes=np.eye(2, 3)),
        starts=v_bar_train(agents) if starts is None else starts,
    )
