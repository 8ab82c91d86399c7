"""The earliest formation: 10 unit point masses at rest on a line, each under the thrust
limit |u| ≤ 2 (a norm, as a path constraint), to a circle of radius 5 about (20, 10), at
rest, N = 10 DMOC intervals (nondimensional units). With ``final_time = "minimum"``
(:mod:`ocpar.formation.final_time`) the run finds the least common T at which some rotation
and assignment of the equidistant formation is reachable by every agent: T* = 7.25547 (run
``ocpar run formation-minimum-time``); ``duration`` 10 is only the horizon of a fixed-time
run of the same problem."""

import casadi as ca
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.models import PointMass
from ocpar.ocp.constraints import PathConstraint

#: The thrust limit |u| ≤ U_MAX (force unit).
U_MAX = 2.0


def make(agents: int = 10, radius: float = 5.0, intervals: int = 10,
         duration: float = 10.0) -> FormationProblem:
    """``agents`` point masses from the line y = ±1 (alternating), x in [−10, 10], onto the
    circle of ``radius`` about (20, 10), each with |u| ≤ :data:`U_MAX`; DMOC with
    ``intervals`` over ``duration`` (the first guess of T where the final time is free)."""
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=U_MAX**2, name="thrust")
    return FormationProblem(
        name="point-mass-minimum-time",
        shape=DmocShape(PointMass(dim=2, mass=1.0), intervals=intervals, duration=duration,
                        path_constraints=(thrust,)),
        curve=Circle(radius=radius, center=np.array([20.0, 10.0])),
        starts=np.column_stack([np.linspace(-10.0, 10.0, agents),
                                np.where(np.arange(agents) % 2 == 0, 1.0, -1.0)]),
    )
