"""A new worked example (in none of the papers): a formation that turns for an obstacle.
Six point masses (mass 1) start at rest on a line along x1 from −2.5 to 2.5 and end at rest
on the circle of radius 2 about (0, 6) after T = 1 (N = 10 DMOC intervals), minimising
Σ∫|u|² dt, their final angles coupled by the formation paper's potential. A disc of radius
``obstacle`` about (1, 3), off the problem's line of symmetry x1 = 0, lies across the paths
of the right-hand agents; every agent's inner problem keeps its whole continuous path out of
it (:mod:`ocpar.ocp.obstacles`), so that the outer solver turns the formation for it. With
the default radius 0.8 the best rotation moves by −0.383 rad and the cost rises from
2830.303 to 2859.206; agents 0–3 pass the disc with its centre on their right, 4 and 5 on
their left. With ``dim`` = 3 the same in space: the circle tilted by 0.3 rad about the x1
axis and lifted to x3 = 0.5, the obstacle a ball about (1, 3, 0.2).
"""

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, Sphere
from ocpar.models import PointMass

#: The tilt of the 3-D case's circle about the x1 axis (rad).
TILT = 0.3


def make(agents: int = 6, obstacle: float | None = 0.8, dim: int = 2) -> FormationProblem:
    """``agents`` point masses in ``dim`` (2 or 3) dimensions onto the circle, past a ball
    of radius ``obstacle`` (length unit; None: no obstacle)."""
    if dim not in (2, 3):
        raise ValueError(f"dim: must be 2 or 3, got {dim}")
    starts = np.zeros((agents, dim))
    starts[:, 0] = np.linspace(-2.5, 2.5, agents)
    if dim == 2:
        curve, centre = Circle(radius=2.0, center=np.array([0.0, 6.0])), (1.0, 3.0)
    else:
        axes = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(TILT), np.sin(TILT)]])
        curve = Circle(radius=2.0, center=np.array([0.0, 6.0, 0.5]), axes=axes)
        centre = (1.0, 3.0, 0.2)
    return FormationProblem(
        name=f"obstacle-{dim}d",
        shape=DmocShape(PointMass(dim=dim), intervals=10, duration=1.0),
        curve=curve,
        starts=starts,
        obstacles=() if obstacle is None else (Sphere(centre, obstacle, "disc"),),
    )
