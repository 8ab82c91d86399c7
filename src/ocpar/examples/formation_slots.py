"""A new worked example (in none of the papers): point masses onto given slots, where only the
assignment is free (the problem concurrent assignment and planning, CAPT, solves).

``agents`` unit point masses start at rest at seeded random positions in a square below the
slots and end at rest, after t = 1 (N = 10 DMOC intervals), on ``slots`` points of a square
lattice of spacing 1 (the first ``slots`` points, row by row), minimising Σ∫|u|² dt. For
identical double integrators from rest to rest Ĵ_i = 12 |Δ_i|² / T³ exactly (DMOC too), so
the optimal assignment is CAPT's, min Σ|Δ_i|², whose straight synchronised paths keep any
two agents at least as far apart as the nearer of their two starts and their two slots.
"""

import numpy as np

from ocpar.formation import DmocShape, FormationProblem, Slots
from ocpar.models import PointMass


def make(agents: int = 200, slots: int | None = None, seed: int = 0) -> FormationProblem:
    """``agents`` point masses onto ``slots`` (default: as many as agents) lattice points."""
    slots = agents if slots is None else slots
    side = int(np.ceil(np.sqrt(slots)))
    lattice = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)
    rng = np.random.default_rng(seed)
    width = np.sqrt(agents)
    starts = rng.uniform(0.0, width, (agents, 2)) - np.array([0.0, width + 2.0])
    return FormationProblem(
        name="point-mass-slots",
        shape=DmocShape(PointMass(dim=2, mass=1.0), intervals=10, duration=1.0),
        curve=Slots(lattice[:slots].astype(float)),
        starts=starts,
    )
