"""Hierarchical formation reconfiguration (Junge, Marsden, Ober-Blöbaum et al., DMOC).

Any number of agents, each any Lagrangian mechanical system, move from their own start
states to a final formation on a closed curve z(φ) (a :class:`Circle`, an :class:`Ellipse`, a
:class:`PlaneCurve` in a tilted plane or any :class:`ParametricCurve`), on a surface with two
parameters per agent (a :class:`SphereSurface`, an :class:`EllipsoidSurface` or any
:class:`ParametricSurface`) or onto given :class:`Slots`, subject to a
coupling g(φ) = 0: the paper's potential dG/dφ = 0 (:class:`PotentialCoupling`, the
default), equal arc-length spacing (:class:`EqualArcLength`) or the user's own
(:class:`UserCoupling`). The outer problem chooses the final
angles φ_i; each inner problem moves one agent by DMOC to its point, and all inner problems of
one outer evaluation run in one superstep. Every returned formation is checked as returned
(:func:`verify_formation`).

>>> import numpy as np
>>> from ocpar.formation import Circle, DmocShape, FormationProblem, solve_formation
>>> from ocpar.models import PointMass
>>> problem = FormationProblem(name="six", shape=DmocShape(PointMass(dim=2), 10, 1.0),
...                            curve=Circle(radius=10.0, center=np.array([100.0, 100.0])),
...                            starts=np.column_stack([np.linspace(-30, 30, 6), np.zeros(6)]))
>>> solve_formation(problem).converged   # serial backend by default
True

The paper's examples are built the same way in :mod:`ocpar.examples`
(``formation_point_masses``, ``formation_halo``; ``formation_ellipse`` is a new one).
"""

from ocpar.formation.couplings.coupling import (
    Coupling,
    EqualArcLength,
    PotentialCoupling,
    UserCoupling,
)
from ocpar.formation.keep_out.obstacles import Ellipsoid, HalfSpace, Sphere
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import FormationResult
from ocpar.formation.solve import MODES, FormationOptions, solve_formation
from ocpar.formation.targets.curve import Circle, Curve, Ellipse, ParametricCurve, PlaneCurve
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import (
    EllipsoidSurface,
    ParametricSurface,
    SphereSurface,
    Surface,
)
from ocpar.formation.verify import Verification, verify_formation
from ocpar.ocp import DmocShape, MsEndpointShape

__all__ = [
    "MODES",
    "Circle",
    "Coupling",
    "Curve",
    "DmocShape",
    "Ellipse",
    "Ellipsoid",
    "EllipsoidSurface",
    "EqualArcLength",
    "FormationOptions",
    "FormationProblem",
    "FormationResult",
    "HalfSpace",
    "MsEndpointShape",
    "ParametricCurve",
    "ParametricSurface",
    "PlaneCurve",
    "PotentialCoupling",
    "Slots",
    "Sphere",
    "SphereSurface",
    "Surface",
    "UserCoupling",
    "Verification",
    "solve_formation",
    "verify_formation",
]

