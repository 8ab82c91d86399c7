"""A ground robot with unicycle kinematics: state (x, y, ψ, v), controls (a, ω)."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np


@dataclass(frozen=True)
class Unicycle:
    """ẋ = v cos ψ, ẏ = v sin ψ, ψ̇ = ω, v̇ = a, running cost a² + ω² (an
    :class:`~ocpar.models.OdeModel`). State (x, y, ψ, v): position (length unit), heading
    (rad), speed; controls (a, ω): acceleration and turn rate; nondimensional (a² + ω² adds
    quantities of different units unless length and time are scaled to 1), the heading in
    rad. ``position_indices`` (0, 1): the entries a formation places on its target."""

    @property
    def nx(self) -> int:
        return 4

    @property
    def nu(self) -> int:
        return 2

    @property
    def position_indices(self) -> tuple[int, ...]:
        """x and y are the position."""
        return (0, 1)

    @property
    def state_names(self) -> tuple[str, ...]:
        return ("x", "y", "heading", "speed")

    @property
    def state_units(self) -> tuple[str, ...]:
        return ("1", "1", "rad", "1")

    @property
    def control_names(self) -> tuple[str, ...]:
        return ("acceleration", "turn_rate")

    @property
    def control_units(self) -> tuple[str, ...]:
        return ("1", "rad")

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.vertcat(x[3] * ca.cos(x[2]), x[3] * ca.sin(x[2]), u[1], u[0])

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.sumsqr(u)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(4, -np.inf), np.full(4, np.inf)
