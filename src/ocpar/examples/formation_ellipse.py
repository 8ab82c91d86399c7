"""A new worked example (in none of the papers): 3-D point masses onto an ellipse in a tilted
plane. ``agents`` unit point masses start at rest on a line along x1 and end at rest on the
ellipse with semi-axes 6 and 3 about (0, 0, 10), its plane tilted by ``tilt`` rad about x1,
after t = 1 (N = 10 DMOC intervals), minimising Σ∫|u|² dt, their final angles coupled by
``coupling``: the formation paper's potential on the ellipse (``potential``, isolated
formations) or equal spacing in arc length with a free common shift (``equal-arc-length``)."""

import numpy as np

from ocpar.formation import DmocShape, Ellipse, FormationProblem
from ocpar.formation.couplings.coupling import EqualArcLength, PotentialCoupling
from ocpar.models import PointMass

#: The couplings this example offers, by name.
COUPLINGS = {"potential": PotentialCoupling, "equal-arc-length": EqualArcLength}


def make(agents: int = 10, tilt: float = np.pi / 6,
         coupling: str = "potential") -> FormationProblem:
    """``agents`` point masses onto the ellipse tilted by ``tilt`` (rad) about x1, coupled by
    ``coupling`` (a name of :data:`COUPLINGS`)."""
    if coupling not in COUPLINGS:
        raise ValueError(f"coupling: unknown {coupling!r}; choose one of "
                         f"{', '.join(COUPLINGS)}")
    plane = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(tilt), np.sin(tilt)]])
    starts = np.zeros((agents, 3))
    starts[:, 0] = np.linspace(-5.0, 5.0, agents)
    return FormationProblem(
        name="point-mass-ellipse",
        shape=DmocShape(PointMass(dim=3, mass=1.0), intervals=10, duration=1.0),
        curve=Ellipse(semi_axes=(6.0, 3.0), center=np.array([0.0, 0.0, 10.0]), axes=plane),
        starts=starts,
        coupling=COUPLINGS[coupling](),
    )
