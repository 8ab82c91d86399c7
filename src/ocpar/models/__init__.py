"""Models: mechanical systems (Lagrangians, for DMOC) and controlled ODEs (for multiple
shooting), as small hashable value objects."""

from ocpar.models.mechanical import MechanicalSystem
from ocpar.models.ode import OdeModel
from ocpar.models.orbit_transfer import OrbitTransfer
from ocpar.models.point_mass import PointMass

__all__ = ["MechanicalSystem", "OdeModel", "OrbitTransfer", "PointMass"]
