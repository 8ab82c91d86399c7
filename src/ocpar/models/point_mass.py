"""A point mass in R^dim pushed by a force: L = ½ m |q̇|², generalised force = u."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca

from ocpar.models.labels import derived


@dataclass(frozen=True)
class PointMass:
    """Point mass of ``mass`` (mass units) moving in ``dim`` dimensions, force u in R^dim.
    Its results' units (:mod:`ocpar.models.labels`): ``length_unit``, ``mass_unit`` and
    ``time_unit`` (strings a unit library parses, e.g. 'm', 'kg', 's'; '1' nondimensional,
    the default), the force's and the cost's derived from them."""

    dim: int = 2
    mass: float = 1.0
    length_unit: str = "1"
    mass_unit: str = "1"
    time_unit: str = "1"

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise ValueError(f"PointMass.dim must be >= 1, got {self.dim}")
        if not self.mass > 0:
            raise ValueError(f"PointMass.mass must be > 0, got {self.mass}")

    @property
    def nq(self) -> int:
        return self.dim

    @property
    def nu(self) -> int:
        return self.dim

    @property
    def state_units(self) -> str:
        """The configuration's unit: the length unit."""
        return self.length_unit

    @property
    def control_units(self) -> str:
        """The force's unit, mass · length / time² ('1' nondimensional)."""
        return derived((self.mass_unit, 1), (self.length_unit, 1), (self.time_unit, -2))

    @property
    def cost_unit(self) -> str:
        """The unit of the cost ∫|u|² dt: force² · time."""
        return derived((self.control_units, 2), (self.time_unit, 1))

    @property
    def position_indices(self) -> tuple[int, ...]:
        """All of q is the position."""
        return tuple(range(self.dim))

    def lagrangian(self, q: ca.SX, qdot: ca.SX, interval: int = 0) -> ca.SX:
        return 0.5 * self.mass * ca.dot(qdot, qdot)

    def generalized_force(self, q: ca.SX, u: ca.SX) -> ca.SX:
        return u
