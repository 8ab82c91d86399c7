"""Mechanical models: Lagrangians and how controls enter, as small hashable value objects."""

from ocpar.models.mechanical import MechanicalSystem
from ocpar.models.point_mass import PointMass

__all__ = ["MechanicalSystem", "PointMass"]
