"""Goddard's ascent from a flat, airless body (the MACS paper's eq. 17–18).

Nondimensional units. State x = (x, v_x, y, v_y): horizontal position, horizontal velocity,
altitude, vertical velocity; control u = thrust angle (rad) above the horizontal:

    ẋ = v_x,   v̇_x = a cos u,   ẏ = v_y,   v̇_y = −g + a sin u

with constant gravity g and thrust acceleration a. The paper starts at rest at the origin and
ends at y = ``height`` with v_y = 0; its objectives (t_f, −v_x(t_f)) are Mayer-type, so the
running cost is 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np


@dataclass(frozen=True)
class GoddardAscent:
    """The ascent dynamics: gravity ``g``, thrust acceleration ``a``, target ``height``."""

    #: The thrust angle's unit (for plots: :func:`ocpar.plotting.components`).
    control_units: ClassVar[str] = "rad"

    g: float = 1.6e-3
    a: float = 4e-3
    height: float = 10.0

    @property
    def nx(self) -> int:
        return 4

    @property
    def nu(self) -> int:
        return 1

    def rhs(self, x, u):
        return ca.vertcat(x[1], self.a * ca.cos(u[0]), x[3], -self.g + self.a * ca.sin(u[0]))

    def running_cost(self, x, u):
        """0: the paper's objectives are Mayer-type."""
        return ca.SX(0)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(4, -np.inf), np.full(4, np.inf)
