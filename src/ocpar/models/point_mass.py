"""A point mass in R^dim pushed by a force: L = ½ m |q̇|², generalised force = u."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca


@dataclass(frozen=True)
class PointMass:
    """Point mass of ``mass`` (mass units) moving in ``dim`` dimensions, force u in R^dim."""

    dim: int = 2
    mass: float = 1.0

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
    def position_indices(self) -> tuple[int, ...]:
        """All of q is the position."""
        return tuple(range(self.dim))

    def lagrangian(self, q: ca.SX, qdot: ca.SX, interval: int = 0) -> ca.SX:
        return 0.5 * self.mass * ca.dot(qdot, qdot)

    def generalized_force(self, q: ca.SX, u: ca.SX) -> ca.SX:
        return u
