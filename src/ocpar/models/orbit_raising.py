"""Maximum-energy orbit raising (the MACS paper's eq. 20–21).

Canonical units (μ = 1, length of the reference radius, time such that the circular orbit of
radius 1 has period 2π). State x = (r, v_r, θ, v_t): radius, radial velocity, longitude (rad),
transversal velocity; control u = thrust angle (rad) from the radial direction:

    ṙ = v_r,   v̇_r = v_t²/r − 1/r² + a cos u,   θ̇ = v_t/r,   v̇_t = −v_t v_r/r + a sin u

with constant thrust acceleration a. The paper starts on the circular orbit r = 1.1; its
objectives (t_f, −final energy) are Mayer-type, so the running cost is 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np


@dataclass(frozen=True)
class OrbitRaising:
    """The orbit-raising dynamics: thrust acceleration ``a``; ``min_radius`` bounds the NLPs
    away from the singularity at r = 0."""

    #: The thrust angle's unit (for plots: :func:`ocpar.plotting.components`).
    control_units: ClassVar[str] = "rad"

    a: float = 1e-2
    min_radius: float = 0.1

    @property
    def nx(self) -> int:
        return 4

    @property
    def nu(self) -> int:
        return 1

    def rhs(self, x, u):
        r, vr, vt = x[0], x[1], x[3]
        return ca.vertcat(
            vr,
            vt**2 / r - 1 / r**2 + self.a * ca.cos(u[0]),
            vt / r,
            -vt * vr / r + self.a * ca.sin(u[0]),
        )

    def running_cost(self, x, u):
        """0: the paper's objectives are Mayer-type."""
        return ca.SX(0)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower = np.array([self.min_radius, -np.inf, -np.inf, -np.inf])
        return lower, np.full(4, np.inf)

    def circular_speed(self, radius: float) -> float:
        """Transversal speed of the circular orbit of ``radius``, 1/√r."""
        return float(1 / np.sqrt(radius))
