"""A controlled van der Pol oscillator brought to rest at the origin (in none of the papers):

    ẋ1 = x2,   ẋ2 = μ (1 − x1²) x2 − x1 + u,   |u| ≤ u_max,
    min ∫_0^T (x1² + x2² + u²) dt,   x(0) = (1, 0),   x(T) = (0, 0).

Agent 0 flies a control law of t found from the flat output x1: along the cubic
x1(t) = 1 − 3s² + 2s³ (s = t/T), which leaves (1, 0) and stops at the origin, the control is
u = ẍ1 − μ (1 − x1²) ẋ1 + x1. The headline is the cost Σ h g (the default).

:func:`make_speed_limited` adds the state constraint x2(t) ≥ v_min (a path constraint, met at
every sample): the free optimum swings back at x2 ≈ −0.51, agent 0's plan at −0.375, so
v_min = −0.4 is active on the optimum and met by the plan.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial

import casadi as ca
import numpy as np

from ocpar.ocp.constraints import PathConstraint
from ocpar.pursuit import ControlLaw, PursuitProblem


@dataclass(frozen=True)
class VanDerPol:
    """The controlled van der Pol oscillator, an :class:`ocpar.models.OdeModel`."""

    mu: float = 1.0
    u_max: float = 1.0

    @property
    def nx(self) -> int:
        return 2

    @property
    def nu(self) -> int:
        return 1

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.vertcat(x[1], self.mu * (1 - x[0] ** 2) * x[1] - x[0] + u[0])

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return x[0] ** 2 + x[1] ** 2 + u[0] ** 2

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(2, -np.inf), np.full(2, np.inf)

    def control_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([-self.u_max]), np.array([self.u_max])


def flat_law(model: VanDerPol, duration: float, t: float) -> np.ndarray:
    """u(t) along x1 = 1 − 3s² + 2s³, s = t/T. Shape (1,)."""
    s = t / duration
    x1, v, a = 1 - 3 * s**2 + 2 * s**3, 6 * (s**2 - s) / duration, 6 * (2 * s - 1) / duration**2
    return np.array([a - model.mu * (1 - x1**2) * v + x1])


def make(samples: int = 41, duration: float = 4.0, integrator: str = "rk4") -> PursuitProblem:
    """The oscillator over T = ``duration`` with ``samples`` samples (h = T/(N−1))."""
    model = VanDerPol()
    return PursuitProblem(
        name="van-der-pol", model=model, duration=duration, samples=samples,
        initial_state=np.array([1.0, 0.0]), target_components=(0, 1), target=np.zeros(2),
        plan=ControlLaw(partial(flat_law, model, duration)), integrator=integrator,
    )


def make_speed_limited(samples: int = 41, duration: float = 4.0, integrator: str = "rk4",
                       min_velocity: float = -0.4) -> PursuitProblem:
    """:func:`make` with x2(t) ≥ ``min_velocity`` at every sample."""
    floor = PathConstraint(lambda x: x[1], lower=min_velocity, upper=np.inf,
                           name="velocity floor")
    return dataclasses.replace(make(samples, duration, integrator), name="van-der-pol-floor",
                               path_constraints=(floor,))
