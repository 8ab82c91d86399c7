"""Multiple shooting on the orbit transfer: the paper's MS optimum and the integrators."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import golden
from scipy.integrate import solve_ivp

from ocpar.examples.pursuit_orbit_transfer import make as orbit_transfer
from ocpar.models import OrbitTransfer
from ocpar.models.ode import ode_functions
from ocpar.ocp import MsShape, OcpTask, ms_problem, solve_task
from ocpar.pursuit import PursuitProblem


def full_horizon(problem: PursuitProblem, integrator: str):
    x0, u0 = problem.feasible_trajectory()
    shape = MsShape(problem.model, problem.samples - 1, problem.step, problem.target_components,
                    integrator)
    guess = np.concatenate([x0[1:].ravel(), u0.ravel()])
    params = np.concatenate([problem.initial_state, problem.target])
    return solve_task(OcpTask(shape, params, guess))


def test_euler_ms_reproduces_the_paper_case_1():
    problem = orbit_transfer(case=1, samples=301)
    sol = full_horizon(problem, "euler")
    assert sol.success, sol.status
    assert sol.x[-1, 3] * 1e3 == golden("pursuit-case1.paper_ms_final_mass_kg").approx()
    assert sol.x[-1, 3] * 1e3 == golden("pursuit-case1.ms_final_mass_kg").approx()
    np.testing.assert_allclose(sol.x[-1, :3], problem.target, atol=1e-10)
    assert sol.constraint_violation < 1e-12
    assert sol.x[-1, 3] * 1e3 > 523.9  # the optimum burns ~1 kg, the guess 53.5 kg


def test_rk4_steps_match_an_accurate_integration_and_euler_does_not():
    """Each NLP step must be the integrator's step with u held: RK4 agrees with an adaptive
    integration of its own controls to ~h⁴, Euler only to ~h."""
    problem = orbit_transfer(case=1, samples=101)
    f, _ = ode_functions(problem.model)
    errors = {}
    for integrator in ("euler", "rk4"):
        sol = full_horizon(problem, integrator)
        assert sol.success, sol.status
        x = problem.initial_state
        for uj in sol.u:
            x = solve_ivp(lambda _t, y, uj=uj: np.asarray(f(y, uj)).ravel(), (0, problem.step), x,
                          rtol=1e-12, atol=1e-13).y[:, -1]
        errors[integrator] = abs(x[0] - sol.x[-1, 0])  # final radius, Mm
    assert errors["rk4"] < 1e-5
    assert errors["euler"] > 1e3 * errors["rk4"]


def test_target_set_leaves_mass_free_and_solver_is_cached():
    model = OrbitTransfer()
    shape = MsShape(model, 20, 1.0, (0, 1, 2))
    problem = ms_problem(shape)
    assert ms_problem(MsShape(model, 20, 1.0, (0, 1, 2))) is problem
    x0 = np.array([9.6, 0.0, model.circular_rate(9.6), 0.525])
    target = np.array([9.65, 0.0, model.circular_rate(9.65)])
    sol = problem.solve(np.concatenate([x0, target]))
    assert sol.success, sol.status
    np.testing.assert_allclose(sol.x[-1, :3], target, atol=1e-10)
    assert sol.x[-1, 3] < x0[3]  # burning fuel is the only way up
    assert sol.cost == pytest.approx((x0[3] - sol.x[-1, 3]) * 1e3, rel=1e-9)


def test_bad_shapes_are_refused():
    model = OrbitTransfer()
    with pytest.raises(ValueError, match="integrator"):
        MsShape(model, 10, 1.0, (0,), "rk45")
    with pytest.raises(ValueError, match="terminal"):
        MsShape(model, 10, 1.0, (7,))
    with pytest.raises(ValueError, match="interval"):
        MsShape(model, 0, 1.0, (0,))
