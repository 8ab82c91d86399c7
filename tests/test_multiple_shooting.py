"""Multiple shooting on the orbit transfer: the paper's MS optimum and the integrators; the
cost quadrature's order on smooth problems."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest
from conftest import golden
from scipy.integrate import solve_ivp

from ocpar.examples.pursuit_orbit_transfer import make as orbit_transfer
from ocpar.models import OrbitTransfer
from ocpar.models.ode import ode_functions
from ocpar.ocp import MsShape, OcpTask, ms_problem, solve_task
from ocpar.ocp.multiple_shooting import step_function
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


@dataclass(frozen=True)
class Pendulum:
    """θ̈ = −sin θ + u, running cost θ² + u² (a cost that depends on the state nonlinearly)."""

    nx = 2
    nu = 1

    def rhs(self, x, u):
        return ca.vertcat(x[1], -ca.sin(x[0]) + u[0])

    def running_cost(self, x, u):
        return x[0] ** 2 + u[0] ** 2

    def state_bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)


@dataclass(frozen=True)
class Integrator:
    """ẋ = u, running cost x² + u²: from x(0) = 1 to x(T) = 0 the optimum is coth T
    (x = sinh(T − t)/sinh T, J = −x ẋ at t = 0)."""

    nx = 1
    nu = 1

    def rhs(self, x, u):
        return u

    def running_cost(self, x, u):
        return x[0] ** 2 + u[0] ** 2

    def state_bounds(self):
        return np.full(1, -np.inf), np.full(1, np.inf)


def observed_order(errors: dict[int, float]) -> float:
    (coarse, e_coarse), (fine, e_fine) = sorted(errors.items())
    return float(np.log(e_coarse / e_fine) / np.log(fine / coarse))


@pytest.mark.parametrize(("integrator", "order"), [("euler", 1.0), ("rk4", 4.0)])
def test_the_cost_of_a_fixed_control_converges_at_the_integrators_order(integrator, order):
    """The cost of u = 1 on [0, 2] from θ = 0.5 at rest against its integral by an adaptive
    integration of the augmented system (cost as a state): the cost is integrated by the same
    rule as the path, RK4's to O(h⁴), Euler's left rectangle to O(h)."""
    model, duration, x0 = Pendulum(), 2.0, np.array([0.5, 0.0])
    f, g = ode_functions(model)
    errors = {}
    for n in (40, 80):
        h = duration / n
        u = np.ones((n, 1))
        y = np.concatenate([x0, [0.0]])
        for uj in u:
            y = solve_ivp(lambda _t, s, uj=uj: np.concatenate(
                [np.asarray(f(s[:2], uj)).ravel(), np.asarray(g(s[:2], uj)).ravel()]),
                (0, h), y, rtol=1e-13, atol=1e-14).y[:, -1]
        phi = step_function(model, h, integrator)
        x, cost = x0, 0.0
        for uj in u:
            nxt, rate = phi(x, uj)
            x, cost = np.asarray(nxt).ravel(), cost + h * float(rate)
        errors[n] = abs(cost - y[2])
    assert observed_order(errors) == pytest.approx(order, abs=0.15)


@pytest.mark.parametrize(("integrator", "order"), [("euler", 1.0), ("rk4", 2.0)])
def test_the_optimal_cost_converges_to_the_continuous_optimum(integrator, order):
    """ẋ = u, min ∫ (x² + u²) dt from 1 to 0 over T = 1 (exact coth 1): with RK4 and its cost
    quadrature the error is the O(h²) of piecewise-constant controls, with Euler O(h)."""
    errors = {}
    for n in (20, 80):
        shape = MsShape(Integrator(), n, 1.0 / n, (0,), integrator)
        sol = solve_task(OcpTask(shape, np.array([1.0, 0.0])))
        assert sol.success, sol.status
        errors[n] = abs(sol.cost - 1 / np.tanh(1.0))
    assert observed_order(errors) == pytest.approx(order, abs=0.1)


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
