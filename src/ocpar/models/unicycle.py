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

    def guess(self, starts: np.ndarray, ends: np.ndarray, times: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """A first guess from starts (k, 4) to end positions ``ends`` (k, 4; their heading
        and speed not read) at ``times`` (N+1,) from 0 to T: along the straight line, heading
        along it, speed 6 D s (1 − s) / T (s = t/T: a double integrator's least-effort
        profile over the distance D), a = dv/dt at each interval's start, ω = 0; states
        (k, N+1, 4), controls (k, N, 2). At rest the unicycle's linearisation cannot move
        sideways: a Newton step from a guess at rest meets a singular KKT matrix."""
        total = times[-1]
        s = times / total
        delta = ends[:, :2] - starts[:, :2]
        distance = np.linalg.norm(delta, axis=1)
        along = (3 * s**2 - 2 * s**3)[None, :, None] * delta[:, None]
        heading = np.arctan2(delta[:, 1], delta[:, 0])
        speed = 6 * distance[:, None] * (s * (1 - s))[None] / total
        states = np.concatenate([starts[:, None, :2] + along,
                                 np.broadcast_to(heading[:, None, None], (*along.shape[:2], 1)),
                                 speed[..., None]], axis=2)
        accel = 6 * distance[:, None] * (1 - 2 * s[:-1])[None] / total**2
        controls = np.stack([accel, np.zeros_like(accel)], axis=2)
        return states, controls
