"""Problems for tests/test_phase_one.py, importable by reference from a config
(``phase_one_problems:unassignable``)."""

from __future__ import annotations

import numpy as np

from ocpar.formation import DmocShape, FormationProblem, Slots
from ocpar.models import PointMass

#: Slot problems: a light (mass 1) and a heavy (mass 3) planar point mass, box thrust limit U,
#: T = 2, N = 10: reach U T²/(4m) per axis, 0.5 and 1/6.
U, DURATION, INTERVALS = 0.5, 2.0, 10
STARTS = np.array([[0.7, 0.0], [1.0, 0.0]])
MASSES = (1.0, 3.0)


def slots(points) -> FormationProblem:
    shapes = tuple(DmocShape(PointMass(dim=2, mass=m), INTERVALS, DURATION,
                             control_bounds=((-U, U), (-U, U))) for m in MASSES)
    return FormationProblem(name="two-slots", shape=shapes, curve=Slots(np.array(points)),
                            starts=STARTS)


def reassignable() -> FormationProblem:
    """The nearest assignment (Σ|d|²) sends the heavy agent 0.2 up, beyond its reach."""
    return slots([[0.85, 0.0], [1.0, 0.2], [0.4, 0.0]])


def unassignable() -> FormationProblem:
    """Each agent reaches slot 0 alone; the light one misses slots 1 and 2 by 0.1 along x."""
    return slots([[0.85, 0.0], [1.3, 0.2], [0.1, 0.0]])
