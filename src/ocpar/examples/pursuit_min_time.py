"""A double integrator brought to rest at the origin in free final time (in none of the papers):

    ẋ1 = x2,   ẋ2 = u,   |u| ≤ 1,   x(0) = (p, 0),   x(T) = (0, 0),
    min  T + c ∫_0^T u²/2 dt   over u and T ∈ [T_min, T_max].

With c = 0 it is the minimum-time problem: bang-bang, u = −sign(p) up to T/2 and +sign(p)
after, T* = 2 √|p|. With c > 0 and the bound not reached, for each T the least energy is
6 c p²/T³ (u linear in t, largest |u| = 6|p|/T² at the ends), so T* = (18 c p²)^{1/4} and the
optimum J* = 4 T*/3. RK4 is exact for this model under piecewise-constant controls, so the
transcription's only error is the controls': none for c = 0 when N − 1 is even (the switch
falls on a sample), O(h²) for c > 0 (``tests/test_pursuit_free_time.py`` checks both).

Agent 0 flies x1 = p (1 − 3s² + 2s³), s = t/D, over ``duration`` D (u = ẍ1, |u| ≤ 6|p|/D²: D ≥
√(6|p|) keeps it within the bound). The headline is the cost (time, plus energy with c > 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import casadi as ca
import numpy as np

from ocpar.pursuit import ControlLaw, PursuitProblem

#: Bounds (T_min, T_max) on the free final time.
FINAL_TIME = (0.1, 20.0)


@dataclass(frozen=True)
class DoubleIntegrator:
    """ẋ1 = x2, ẋ2 = u with |u| ≤ 1 and running cost c u²/2, an :class:`ocpar.models.OdeModel`."""

    energy: float = 0.0

    @property
    def nx(self) -> int:
        return 2

    @property
    def nu(self) -> int:
        return 1

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.vertcat(x[1], u[0])

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return self.energy * u[0] ** 2 / 2

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(2, -np.inf), np.full(2, np.inf)

    def control_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([-1.0]), np.array([1.0])


def rest_to_rest_law(position: float, duration: float, t: float) -> np.ndarray:
    """u(t) = ẍ1 along x1 = p (1 − 3s² + 2s³), s = t/D. Shape (1,)."""
    return np.array([6 * position * (2 * t / duration - 1) / duration**2])


def make(samples: int = 301, energy: float = 0.0, position: float = 1.0,
         duration: float | None = None, integrator: str = "rk4") -> PursuitProblem:
    """The problem from (``position``, 0) with energy weight c = ``energy`` ≥ 0, ``samples``
    N; agent 0's plan over ``duration`` (default 1.25 √(6|p|), within the control bound)."""
    if not (math.isfinite(energy) and energy >= 0):
        raise ValueError(f"energy: must be a finite number >= 0, got {energy!r}")
    if not (math.isfinite(position) and position != 0):
        raise ValueError(f"position: must be a finite nonzero number, got {position!r}")
    plan_duration = 1.25 * math.sqrt(6 * abs(position)) if duration is None else duration
    return PursuitProblem(
        name="min-time" if energy == 0 else "min-time-energy", model=DoubleIntegrator(energy),
        duration=plan_duration, samples=samples, initial_state=np.array([position, 0.0]),
        target_components=(0, 1), target=np.zeros(2),
        plan=ControlLaw(partial(rest_to_rest_law, position, plan_duration)),
        cost_name="time" if energy == 0 else "time and energy", integrator=integrator,
        final_time=FINAL_TIME, time_weight=1.0,
    )
