"""A new worked example (in none of the papers): point masses in 3-D onto a sphere or an
ellipsoid, each agent with two parameters (:mod:`ocpar.formation.targets.surface`). ``agents`` unit
point masses start at rest on a slanted line below the target and end at rest on it after
t = 2 (N = 10 DMOC intervals), minimising Σ∫|u|² dt, their final points coupled by the
formation paper's potential G = Σ 1/|z_i − z_j|² on the surface: ``surface`` ``sphere``
(radius 3 about (0.5, −0.5, 1): the critical sets of G, each free up to a rotation that the
cost chooses) or ``ellipsoid`` (semi-axes 4, 3, 2 about the origin: isolated sets)."""

import numpy as np

from ocpar.formation import DmocShape, FormationProblem
from ocpar.formation.targets.surface import EllipsoidSurface, SphereSurface
from ocpar.models import PointMass

#: The targets this example offers, by name.
SURFACES = {
    "sphere": lambda: SphereSurface(radius=3.0, center=np.array([0.5, -0.5, 1.0])),
    "ellipsoid": lambda: EllipsoidSurface(semi_axes=(4.0, 3.0, 2.0), center=np.zeros(3)),
}


def make(agents: int = 8, surface: str = "sphere") -> FormationProblem:
    """``agents`` point masses onto the ``surface`` (a name of :data:`SURFACES`)."""
    if surface not in SURFACES:
        raise ValueError(f"surface: unknown {surface!r}; choose one of {', '.join(SURFACES)}")
    starts = np.column_stack([np.linspace(-6.0, 6.0, agents), np.full(agents, -8.0),
                              np.linspace(-1.0, 1.0, agents)])
    return FormationProblem(name=f"point-mass-{surface}",
                            shape=DmocShape(PointMass(dim=3, mass=1.0), 10, 2.0),
                            curve=SURFACES[surface](), starts=starts)
