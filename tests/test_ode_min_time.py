"""The minimum final time of a fleet of ODE agents (:class:`~ocpar.ocp.MsEndpointShape`):
four double integrators (ẋ = v, v̇ = u, |u_j| ≤ U) from rest onto a circle at rest, the
bracket by phase-1 bisection against the same discretisation's minimum time computed here
independently: piecewise-constant u on N intervals under RK4 is exact for this linear
system, so the end state is linear in u and "displacement d reachable in T" is an LP per
axis (scipy's linprog), bisected in T for the rotation and assignment the run returns."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import linprog

from ocpar.formation import Circle, FormationOptions, FormationProblem, solve_formation
from ocpar.models.expressions import ode_model
from ocpar.ocp import MsEndpointShape

LIMIT = 1.0
INTERVALS = 8
RADIUS = 2.0
TOL = 1e-2
STARTS = np.array([[-1.5, -4.0, 0, 0], [-0.5, -4.2, 0, 0], [0.6, -3.9, 0, 0],
                   [1.4, -4.1, 0, 0]])


def _double_integrator():
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    return ode_model(x, u, [x[2], x[3], u[0], u[1]], ca.sumsqr(u), position_indices=[0, 1])


def _reachable(d: float, duration: float) -> bool:
    """An axis moved by ``d`` from rest to rest in ``duration`` under |u| ≤ LIMIT: the exact
    discrete end state v_N = h Σ u_k = 0, p_N = h² Σ (N − k − ½) u_k = d, as an LP."""
    h = duration / INTERVALS
    k = np.arange(INTERVALS)
    a_eq = np.vstack([np.full(INTERVALS, h), h**2 * (INTERVALS - k - 0.5)])
    lp = linprog(np.zeros(INTERVALS), A_eq=a_eq, b_eq=[0.0, d],
                 bounds=[(-LIMIT, LIMIT)] * INTERVALS, method="highs")
    return lp.status == 0


def _least_time(d: float) -> float:
    """The least T at which ``d`` is reachable on one axis (bisection to 1e-9 relative)."""
    low, high = 1e-3, 100.0
    assert _reachable(d, high)
    while high - low > 1e-9 * high:
        middle = 0.5 * (low + high)
        low, high = (low, middle) if _reachable(d, middle) else (middle, high)
    return high


@pytest.fixture(scope="module")
def result():
    shape = MsEndpointShape(_double_integrator(), intervals=INTERVALS, duration=4.0,
                            control_bounds=((-LIMIT, LIMIT),) * 2)
    problem = FormationProblem(name="double integrators", shape=shape,
                               curve=Circle(radius=RADIUS), starts=STARTS,
                               final_state=np.zeros(2))
    options = FormationOptions(final_time="minimum", time_bounds=(2.0, 8.0), time_tol=TOL)
    return solve_formation(problem, options=options)


def test_bracket_holds_the_discrete_minimum_time(result):
    """T_lo ≤ T*(returned formation) ≤ T_hi, T* the LP bisection's bottleneck over agents
    and axes; the bracket as narrow as asked; solved and verified at T_hi."""
    assert result.status == "converged", result.message
    low, high = result.final_time["bracket"]
    assert high * (1 - TOL) <= low <= high
    assert result.final_time["method"] == "phase 1" and not result.final_time["proven"]
    phi = np.asarray(result.phi, float)
    ends = RADIUS * np.column_stack([np.cos(phi), np.sin(phi)])
    needed = max(_least_time(abs(d)) for d in (ends - STARTS[:, :2]).ravel())
    assert low * (1 - 1e-6) <= needed <= high * (1 + 1e-6)
    assert result.final_time["T"] == high
    assert result.fleet.duration == high
    assert result.verification is not None and result.verification.passed
    assert np.allclose(result.trajectories[:, -1, :2], ends, atol=1e-6)
    assert np.max(np.abs(result.controls)) <= LIMIT * (1 + 1e-6)
