"""Planar low-thrust orbit transfer (the local-pursuit paper's eq. 15, in a calibrated form).

Units: length Mm (1000 km), mass t (1000 kg), time min. State x = (r, ṙ, θ̇, μ): radius,
radial velocity, angular rate (rad/min), mass; the longitude θ does not enter the dynamics and
is left out. Control u = (u1, u2) = I (sin φ, cos φ):

    r̈ = θ̇² r − u_E / r² + A u1 / μ
    d(θ̇)/dt = −2 θ̇ ṙ / r + A u2 / (μ r)
    μ̇ = −B (u1² + u2²)

The paper's eq. 15 is not dimensionally consistent as printed; A and B are calibrated so that
its guess controls (eq. 16) bring the spacecraft to r(T) = 12.7778 Mm burning 53.5 kg, as the
paper reports. u_E = 3.98e14 m³/s² = 1.4328 Mm³/min².
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

KG_PER_T = 1e3
M_PER_MM = 1e6


@dataclass(frozen=True)
class OrbitTransfer:
    """The orbit transfer dynamics; ``min_radius`` (Mm) and ``min_mass`` (t) bound the NLPs
    away from the singularities at r = 0 and μ = 0."""

    mu_earth: float = 1.4328
    thrust_gain: float = 0.071871
    mass_flow: float = 2.00185
    min_radius: float = 1.0
    min_mass: float = 0.05

    #: The components' names and units (for plots: :func:`ocpar.plotting.components`); the
    #: thrust's unit is the one A and B are calibrated for.
    state_names: ClassVar[tuple[str, ...]] = ("$r$", r"$\dot r$", r"$\dot\theta$", r"$\mu$")
    state_units: ClassVar[tuple[str, ...]] = ("Mm", "Mm/min", "rad/min", "t")
    control_units: ClassVar[str] = "calibrated thrust unit"
    time_units: ClassVar[str] = "min"

    @property
    def nx(self) -> int:
        return 4

    @property
    def nu(self) -> int:
        return 2

    def rhs(self, x, u):
        r, rdot, thdot, mass = x[0], x[1], x[2], x[3]
        a, b = self.thrust_gain, self.mass_flow
        return ca.vertcat(
            rdot,
            thdot**2 * r - self.mu_earth / r**2 + a * u[0] / mass,
            -2 * thdot * rdot / r + a * u[1] / (mass * r),
            -b * (u[0] ** 2 + u[1] ** 2),
        )

    def running_cost(self, x, u):
        """Fuel burn rate, kg/min."""
        return KG_PER_T * self.mass_flow * (u[0] ** 2 + u[1] ** 2)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower = np.array([self.min_radius, -np.inf, -np.inf, self.min_mass])
        return lower, np.full(4, np.inf)

    def circular_rate(self, radius: float) -> float:
        """Angular rate of the circular orbit of ``radius`` Mm, rad/min."""
        return float(np.sqrt(self.mu_earth / radius**3))
