"""Models: mechanical systems (Lagrangians, for DMOC) and controlled ODEs (for multiple
shooting), as small hashable value objects; :func:`ode_model` and :func:`lagrangian_model`
build either from CasADi expressions (:mod:`ocpar.models.expressions`)."""

from ocpar.models.clohessy_wiltshire import ClohessyWiltshire
from ocpar.models.crtbp import Crtbp, HaloOrbit, halo_orbit
from ocpar.models.expressions import (
    ExpressionLagrangian,
    ExpressionOde,
    lagrangian_model,
    ode_model,
)
from ocpar.models.goddard import GoddardAscent
from ocpar.models.mechanical import MechanicalSystem
from ocpar.models.ode import OdeModel
from ocpar.models.orbit_raising import OrbitRaising
from ocpar.models.orbit_transfer import OrbitTransfer
from ocpar.models.point_mass import PointMass
from ocpar.models.rigid_spacecraft import RelativeRigidSpacecraft
from ocpar.models.unicycle import Unicycle

__all__ = [
    "ClohessyWiltshire",
    "Crtbp",
    "ExpressionLagrangian",
    "ExpressionOde",
    "GoddardAscent",
    "HaloOrbit",
    "MechanicalSystem",
    "OdeModel",
    "OrbitRaising",
    "OrbitTransfer",
    "PointMass",
    "RelativeRigidSpacecraft",
    "Unicycle",
    "halo_orbit",
    "lagrangian_model",
    "ode_model",
]
