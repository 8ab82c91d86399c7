"""The formation paper's first example (§VI, Fig. 3): unit point masses at rest, uniformly
spread on the x-axis over [−30, 30], to a circle about (100, 100), at rest, t ∈ [0, 1], N = 10
DMOC intervals (nondimensional units)."""

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.models import PointMass


def make(agents: int = 60, radius: float = 10.0, intervals: int = 10,
         duration: float = 1.0) -> FormationProblem:
    """``agents`` point masses onto the circle of ``radius`` about (100, 100), DMOC with
    ``intervals`` intervals over [0, ``duration``] (the paper's: 10 over [0, 1])."""
    return FormationProblem(
        name="point-mass-plane",
        shape=DmocShape(PointMass(dim=2, mass=1.0), intervals=intervals, duration=duration),
        curve=Circle(radius=radius, center=np.array([100.0, 100.0])),
        starts=np.column_stack([np.linspace(-30.0, 30.0, agents), np.zeros(agents)]),
    )
