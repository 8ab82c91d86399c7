"""Relative motion near a target on a circular orbit: the Clohessy–Wiltshire (Hill) equations.

State (x, y, z, ẋ, ẏ, ż) in the target's LVLH frame (e.g. m, m/s): x radial (away from
the Earth), y along-track (the direction of flight), z cross-track (along the orbit
normal); control u (3,) the thrust acceleration (e.g. m/s²) in the same axes; mean motion n
(rad per time unit) of the target's orbit:

    ẍ = 3 n² x + 2 n ẏ + u_x,   ÿ = −2 n ẋ + u_y,   z̈ = −n² z + u_z,

running cost |u|² (so J = ∫|u|² dt, e.g. in m²/s³: the quadratic-cost proxy of Δv). The
dynamics are linear, ẋ = A x + B u, and the cost a convex quadratic: the formation's inner
optimal cost is a convex quadratic in the boundary states
(:func:`~ocpar.ocp.reach.end_cost_convexity`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

#: A low Earth orbit's mean motion (rad/s): a circular orbit about 400 km up (92.6 min).
LEO_MEAN_MOTION = 1.131e-3


@dataclass(frozen=True)
class ClohessyWiltshire:
    """The Clohessy–Wiltshire equations (module docstring) about a target of mean motion
    ``mean_motion`` n (rad per time unit, > 0); an :class:`~ocpar.models.OdeModel` whose
    position is (x, y, z) (``position_indices`` (0, 1, 2)). The equations fix no unit:
    ``length_unit`` and ``time_unit`` (default m and s; n in rad/``time_unit``) only name
    them in results (velocity length/time, control length/time², cost length²/time³). A
    half-orbit transfer solves better conditioned in minutes than in seconds (N = 20: the
    outer gradient's relative noise ~1e-11 in s, below the outer tolerance in min)."""

    mean_motion: float = LEO_MEAN_MOTION
    length_unit: str = "m"
    time_unit: str = "s"

    state_names: ClassVar[tuple[str, ...]] = ("x", "y", "z", "vx", "vy", "vz")
    control_names: ClassVar[tuple[str, ...]] = ("ax", "ay", "az")

    @property
    def state_units(self) -> tuple[str, ...]:
        velocity = f"{self.length_unit}/{self.time_unit}"
        return (self.length_unit,) * 3 + (velocity,) * 3

    @property
    def control_units(self) -> str:
        return f"{self.length_unit}/{self.time_unit}^2"

    @property
    def cost_unit(self) -> str:
        return f"{self.length_unit}^2/{self.time_unit}^3"

    def __post_init__(self) -> None:
        n = self.mean_motion
        if isinstance(n, bool) or not isinstance(n, int | float | np.floating | np.integer) \
                or not (np.isfinite(n) and n > 0):
            raise ValueError(f"mean_motion: must be a positive number (rad per time unit), "
                             f"got {n!r}")
        object.__setattr__(self, "mean_motion", float(n))
        for name in ("length_unit", "time_unit"):
            unit = getattr(self, name)
            if not isinstance(unit, str) or not unit.isidentifier():
                raise ValueError(f"{name}: must be a unit's name (e.g. m, km, s, min), got "
                                 f"{unit!r}")

    @property
    def nx(self) -> int:
        return 6

    @property
    def nu(self) -> int:
        return 3

    @property
    def position_indices(self) -> tuple[int, ...]:
        """x, y and z are the position."""
        return (0, 1, 2)

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        n = self.mean_motion
        return ca.vertcat(x[3], x[4], x[5],
                          3 * n**2 * x[0] + 2 * n * x[4] + u[0],
                          -2 * n * x[3] + u[1],
                          -n**2 * x[2] + u[2])

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.sumsqr(u)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(6, -np.inf), np.full(6, np.inf)
