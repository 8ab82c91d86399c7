"""Models: mechanical systems (Lagrangians, for DMOC) and controlled ODEs (for multiple
shooting), as small hashable value objects."""

from ocpar.models.goddard import GoddardAscent
from ocpar.models.mechanical import MechanicalSystem
from ocpar.models.ode import OdeModel
from ocpar.models.orbit_raising import OrbitRaising
from ocpar.models.orbit_transfer import OrbitTransfer
from ocpar.models.point_mass import PointMass

__all__ = [
    "GoddardAscent",
    "MechanicalSystem",
    "OdeModel",
    "OrbitRaising",
    "OrbitTransfer",
    "PointMass",
]
