"""The minimum separation for ODE agents (:class:`~ocpar.ocp.MsEndpointShape`): four unicycles
that start rolling towards one another (their free paths cross) kept ≥ D apart by the
separation rounds (keep-out rows on the polyline through the RK4 sub-step states), checked
here on the agents' own paths re-integrated by a numpy RK4 at 64 steps per interval (not the
package's code); the cost above the free one; and one agent's keep-out rows held at every RK4
sub-step state (steps = 3)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ocpar.examples.formation_unicycles import make
from ocpar.formation import FormationOptions, solve_formation
from ocpar.models import Unicycle
from ocpar.ocp import MsEndpointShape, transcription

AGENTS, DURATION, INTERVALS, DISTANCE = 4, 6.0, 20, 0.5
#: RK4 steps per interval of the test's own re-integration.
FINE = 64


def crossing_problem():
    """Four unicycles on the line, the left two rolling right and the right two rolling left
    at 0.5, onto the circle of radius 3."""
    problem = make(agents=AGENTS, duration=DURATION, intervals=INTERVALS)
    starts = problem.starts.copy()
    starts[:2, 2], starts[2:, 2], starts[:, 3] = 0.0, np.pi, 0.5
    return dataclasses.replace(problem, starts=starts)


def _rk4_step(x: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """One classical RK4 step of ẋ = (v cos ψ, v sin ψ, ω, a) for states (m, 4)."""
    def f(s: np.ndarray) -> np.ndarray:
        return np.column_stack([s[:, 3] * np.cos(s[:, 2]), s[:, 3] * np.sin(s[:, 2]),
                                u[:, 1], u[:, 0]])
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def smallest_distance(q: np.ndarray, u: np.ndarray) -> float:
    """The smallest distance of any two agents at the common times of their paths re-integrated
    from each returned node x_k (n, N+1, 4) under its control u_k (n, N, 2) by FINE RK4
    steps per interval."""
    n = len(q)
    states = q[:, :-1].reshape(-1, 4)
    controls = u.reshape(-1, 2)
    samples = [states[:, :2]]
    for _ in range(FINE):
        states = _rk4_step(states, controls, DURATION / INTERVALS / FINE)
        samples.append(states[:, :2])
    positions = np.stack(samples, axis=1).reshape(n, -1, 2)        # (n, N (FINE+1), 2)
    gaps = [np.linalg.norm(positions[i] - positions[j], axis=1).min()
            for i in range(n) for j in range(i + 1, n)]
    return float(min(gaps))


@pytest.fixture(scope="module")
def free_and_separated():
    problem = crossing_problem()
    return solve_formation(problem), solve_formation(problem, options=FormationOptions(
        min_separation=DISTANCE, separation="rounds"))


def test_separated_on_the_reintegrated_paths(free_and_separated):
    free, separated = free_and_separated
    assert free.status == "converged"
    assert smallest_distance(free.trajectories, free.controls) < 0.1   # the free paths cross
    assert separated.status == "converged", separated.message
    assert separated.verification.checks["separation"].passed
    assert smallest_distance(separated.trajectories, separated.controls) \
        >= DISTANCE * (1 - 1e-9)
    assert separated.separation.distance >= DISTANCE * (1 - 1e-9)


def test_cost_above_the_free_one(free_and_separated):
    free, separated = free_and_separated
    assert separated.unconstrained_cost == pytest.approx(free.total_cost, rel=1e-9)
    assert separated.total_cost > free.total_cost
    assert separated.total_cost == pytest.approx(float(np.sum(separated.agent_costs)),
                                                 rel=1e-12)


def test_keep_out_fields_checked():
    with pytest.raises(ValueError, match="keep_out_positions needs keep_out_slots"):
        MsEndpointShape(Unicycle(), keep_out_positions=(0, 1))
    with pytest.raises(ValueError, match="not with free_duration"):
        MsEndpointShape(Unicycle(), keep_out_slots=2, keep_out_positions=(0, 1),
                        free_duration=True)


def test_half_spaces_hold_at_every_sub_step_state():
    """One unicycle from rest at the origin to (3, 0), told y ≥ 0.3 on intervals 3–6 by one
    keep-out slot (three RK4 steps per interval): every sub-step state of those intervals, by
    the test's own RK4 from the returned nodes, meets it, the row is active, and the returned
    cost is h Σ |u_k|² (the penalty left out)."""
    steps, intervals, duration = 3, 10, 3.0
    shape = MsEndpointShape(Unicycle(), intervals=intervals, duration=duration, steps=steps,
                            free_end=(2,), keep_out_slots=1, keep_out_positions=(0, 1),
                            solver="ipopt")
    data = np.zeros((intervals, 4))
    data[:, 2:] = -1.0
    data[3:7] = (0.0, 1.0, 0.3, 0.3)
    params = np.concatenate([[0.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0], data.ravel(), [100.0]])
    sol = transcription(shape).solve(params)
    assert sol.success, sol.status
    h = duration / intervals
    states, points = sol.q[3:7], []
    for _ in range(steps + 1):
        points.append(states[:, 1])
        states = _rk4_step(states, sol.u[3:7], h / steps)
    lowest = np.min(points)
    assert lowest >= 0.3 - 1e-8
    assert lowest == pytest.approx(0.3, abs=1e-8)
    assert sol.cost == pytest.approx(h * np.sum(sol.u**2), rel=1e-10)
