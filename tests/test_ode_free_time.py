"""A free final time for ODE agents (MsEndpointShape ``free_duration``, ``time_bounds``):
the double integrator (ẋ = v, v̇ = u, cost |u|²) from rest to rest, whose RK4 optimum with
piecewise-constant controls is J(Δ, T) = α |Δ|² / T³ (RK4 is exact on this linear system
with u constant, and the discrete problem scales as the continuous one), α from a fixed-T
solve here: dJ/dT, d²J/dT² and the common and per-agent T against their closed forms; the
unicycles (a nonlinear model; a fleet mixed with point masses too): dJ/dT and the T column
of the end Hessian, the free common T and each agent's T_i against finite differences of fixed-T
runs; serial and mpirun -n 2 bitwise the same."""

from __future__ import annotations

import dataclasses
import json

import casadi as ca
import netCDF4
import numpy as np
import pytest
from conftest import run_cli

from ocpar.examples import formation_unicycles
from ocpar.formation import Circle, FormationOptions, FormationProblem, solve_formation
from ocpar.formation.final_time import at_duration
from ocpar.formation.verify import agent_checks
from ocpar.models.expressions import ode_model
from ocpar.ocp import MsEndpointShape, transcription

WEIGHT = 100.0
AGENTS = 8


def _double_integrator():
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    return ode_model(x, u, [x[2], x[3], u[0], u[1]], ca.sumsqr(u), position_indices=[0, 1])


MODEL = _double_integrator()
#: From rest at the origin to rest at (3, 4): |Δ|² = 25.
PARAMS = np.array([0.0, 0.0, 0.0, 0.0, 3.0, 4.0, 0.0, 0.0])


def _shape(**fields) -> MsEndpointShape:
    return MsEndpointShape(MODEL, intervals=10, **fields)


@pytest.fixture(scope="module")
def alpha() -> float:
    """J at T = 1 of a unit displacement (a fixed-T solve)."""
    sol = transcription(_shape(duration=1.0)).solve(np.array([0, 0, 0, 0, 1.0, 0, 0, 0]))
    assert sol.success
    return sol.cost


def _solution(shape: MsEndpointShape, params: np.ndarray, batched: bool):
    nlp = transcription(shape)
    if batched:
        return nlp.solve_batch(params[None], [None], [None]).items()[0]
    return nlp.solve(params)


def _end_gradient(duration: float, params: np.ndarray = PARAMS) -> np.ndarray:
    """dJ*/dx̄_N of a fixed-T solve."""
    sol = transcription(_shape(duration=duration)).solve(params)
    assert sol.success
    return sol.cost_gradient[4:8]


@pytest.mark.parametrize("batched", [True, False], ids=["newton", "ipopt"])
def test_free_duration_derivatives_are_the_closed_forms(alpha, batched):
    """T the last parameter: J = 25 α / T³, dJ/dT = −3J/T, d²J/dT² = 12J/T², the cross
    block d²J/dx̄_N dT against central differences of fixed-T gradients; one compiled solver
    for every T."""
    free = _shape(duration=2.5, free_duration=True)
    assert free.n_params == 9 and transcription(free) is transcription(free.with_duration(7.0))
    for t in (0.7, 2.0):
        sol = _solution(free, np.append(PARAMS, t), batched)
        assert sol.success and sol.duration == t
        j = 25 * alpha / t**3
        assert sol.cost == pytest.approx(j, rel=1e-12)
        assert sol.cost_gradient[-1] == pytest.approx(-3 * j / t, rel=1e-10)
        assert sol.end_hessian.shape == (5, 5)
        assert sol.end_hessian[-1, -1] == pytest.approx(12 * j / t**2, rel=1e-10)
        step = 1e-5 * t
        cross = (_end_gradient(t + step) - _end_gradient(t - step)) / (2 * step)
        np.testing.assert_allclose(sol.end_hessian[:4, -1], cross, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(sol.end_hessian[-1, :4], sol.end_hessian[:4, -1], rtol=1e-12)
        np.testing.assert_allclose(sol.end_hessian[:4, :4],
                                   transcription(_shape(duration=t)).solve(PARAMS).end_hessian,
                                   rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("solver", ["sqpmethod", "ipopt"])
def test_a_task_of_free_time_is_the_closed_form(alpha, solver):
    """T a variable, cost J + w T: T* = (3 · 25 α / w)^¼; the end Hessian, that of
    min_T (J + w T), against central differences of the returned gradients."""
    shape = _shape(duration=1.0, time_bounds=(0.1, 10.0), time_weight=WEIGHT, solver=solver)
    sol = _solution(shape, PARAMS, solver == "sqpmethod")
    assert sol.success
    expected = (3 * 25 * alpha / WEIGHT) ** 0.25
    assert sol.duration == pytest.approx(expected, rel=1e-10)
    assert sol.cost == pytest.approx(4 / 3 * WEIGHT * expected, rel=1e-10)
    step, nlp = 1e-5, transcription(shape)
    for i in (4, 5):
        up, down = PARAMS.copy(), PARAMS.copy()
        up[i] += step
        down[i] -= step
        column = (nlp.solve(up).cost_gradient - nlp.solve(down).cost_gradient)[4:8] / (2 * step)
        np.testing.assert_allclose(sol.end_hessian[:, i - 4], column, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("limit", [0.0, 0.9], ids=["newton", "active-limit"])
def test_unicycle_free_duration_derivatives_are_the_finite_differences(limit):
    """A nonlinear agent (unicycle, T = 6; |a| ≤ 0.9 active, solved by sqpmethod): dJ*/dT
    against central differences of fixed-T costs, the end Hessian's T column against
    central differences in T of the returned gradients (the batched solve, as a formation
    makes it)."""
    problem = formation_unicycles.make(agents=4, acceleration_limit=limit)
    params = problem.boundary_params_rows(np.arange(4), problem.initial_phi())[0]
    shape = problem.common_shape
    free = dataclasses.replace(shape, free_duration=True)
    nlp, t, step = transcription(free), 6.0, 1e-5
    sol = _solution(free, np.append(params, t), batched=True)
    assert sol.success and free.chosen_solver == ("sqpmethod" if limit else "newton")
    if limit:
        assert np.max(np.abs(sol.u[:, 0])) == pytest.approx(limit, rel=1e-12)
    costs = [transcription(shape.with_duration(d)).solve(params).cost
             for d in (t + step, t - step)]
    assert sol.cost_gradient[-1] == pytest.approx((costs[0] - costs[1]) / (2 * step),
                                                  rel=1e-7)
    column = (nlp.solve(np.append(params, t + step)).cost_gradient
              - nlp.solve(np.append(params, t - step)).cost_gradient)[4:] / (2 * step)
    np.testing.assert_allclose(sol.end_hessian[:, -1], column, rtol=1e-6, atol=1e-7)


def _fleet(**fields) -> FormationProblem:
    starts = np.column_stack([np.arange(AGENTS) - (AGENTS - 1) / 2, np.full(AGENTS, -5.0),
                              np.zeros((AGENTS, 2))])
    return FormationProblem(name="double integrators", shape=_shape(duration=1.0, **fields),
                            curve=Circle(radius=3.0), starts=starts, final_state=np.zeros(2))


def test_free_common_time_is_the_closed_form():
    """min over T of Σ J_i + w T with F(T) = F(1) / T³ (F(1) a fixed-T run):
    T* = (3 F(1) / w)^¼ to 1e-9; the paths checked at T*."""
    problem = _fleet()
    fixed = solve_formation(problem)
    assert fixed.converged
    expected = (3 * fixed.total_cost / WEIGHT) ** 0.25
    result = solve_formation(problem, options=FormationOptions(
        final_time="free", time_bounds=(0.1, 100.0), time_weight=WEIGHT, time_tol=1e-10))
    assert result.converged, result.message
    t = result.final_time["T"]
    assert abs(t - expected) <= 1e-9 * expected
    assert result.fleet.duration == t
    assert result.total_cost == pytest.approx(fixed.total_cost / t**3, rel=1e-9)
    assert result.verification.passed


def test_free_time_per_agent_is_each_agents_closed_form(alpha):
    """Each agent its own T_i: T_i = (3 α |Δ_i|² / w)^¼ at its returned target; the
    verification re-integrates each agent with its own step T_i / N."""
    problem = _fleet()
    result = solve_formation(problem, options=FormationOptions(
        final_time="free_per_agent", time_bounds=(0.1, 100.0), time_weight=WEIGHT))
    assert result.converged, result.message
    squared = np.sum((problem.final_positions(result.phi)
                      - problem.positions(problem.starts)) ** 2, axis=1)
    expected = (3 * alpha * squared / WEIGHT) ** 0.25
    np.testing.assert_allclose(result.durations, expected, rtol=1e-9)
    assert np.ptp(result.durations) > 0.1   # the agents' own horizons differ
    assert result.verification.passed
    assert result.verification.checks["dynamics"].value <= 1e-9
    # the same paths re-integrated with the shape's one step T / N miss the dynamics
    arrays = result.arrays()
    q, u = arrays["configuration"][1], arrays["control"][1]
    params = problem.boundary_params_rows(np.arange(AGENTS), result.phi)
    shapes = list(problem.shapes)
    own = agent_checks(shapes, q, u, params, 2, 0, result.durations)
    common = agent_checks(shapes, q, u, params, 2)
    assert np.max(own.dynamics) <= 1e-9 < 1e-2 < np.min(common.dynamics)


@pytest.fixture(scope="module", params=[False, True], ids=["unicycles", "mixed"])
def unicycles(request):
    """4 unicycles, or every second one a DMOC point mass (``mixed``)."""
    return formation_unicycles.make(agents=4, mixed=request.param)


def test_unicycles_free_common_time_is_stationary(unicycles):
    """The unicycles (nonlinear; a mixed fleet too): at the returned T, d/dT of the fixed-T
    formation optimum (central differences of two fixed-T runs) is −w."""
    weight = 1.0
    result = solve_formation(unicycles, options=FormationOptions(
        final_time="free", time_bounds=(1.0, 50.0), time_weight=weight))
    assert result.converged, result.message
    assert result.final_time["at_bound"] is None and result.verification.passed
    t, step = result.final_time["T"], 1e-4

    def optimum(duration: float) -> float:
        fixed = solve_formation(at_duration(unicycles, duration), phi0=result.phi)
        assert fixed.converged
        return fixed.total_cost

    slope = (optimum(t + step) - optimum(t - step)) / (2 * step)
    assert slope == pytest.approx(-weight, rel=1e-6)


def test_unicycles_per_agent_times_are_each_stationary(unicycles):
    """Each agent's T_i: d/dT of its fixed-T inner optimum at its returned end (central
    differences of fixed-T solves of its own shape) is −w."""
    weight = 1.0
    result = solve_formation(unicycles, options=FormationOptions(
        final_time="free_per_agent", time_bounds=(1.0, 50.0), time_weight=weight))
    assert result.converged, result.message
    assert result.verification.passed
    params = unicycles.boundary_params_rows(np.arange(4), result.phi)
    step = 1e-4
    for i, t in enumerate(result.durations):
        costs = [transcription(unicycles.shapes[i].with_duration(d)).solve(params[i]).cost
                 for d in (t + step, t - step)]
        assert (costs[0] - costs[1]) / (2 * step) == pytest.approx(-weight, rel=1e-6)


@pytest.mark.parametrize("mode", ["free", "free_per_agent"])
def test_ode_free_time_is_bitwise_the_same_on_two_mpi_ranks(tmp_path, mode):
    args = ["-m", "ocpar.formation", "--problem", "unicycles", "--agents", "4",
            "--final-time", mode, "--time-bounds", "1,50", "--time-weight", "1", "--quiet",
            "--plot", "none"]
    out = {}
    for ranks in (None, 2):
        where = tmp_path / f"ranks-{ranks}"
        proc = run_cli(*args, "--output", str(where),
                       *(["--backend", "mpi"] if ranks else []), mpi_ranks=ranks)
        assert proc.returncode == 0, proc.stderr
        out[ranks] = json.loads((where / "result.json").read_text())
        assert out[ranks]["status"] == "converged"
    assert out[2]["workers"] == 2
    for key in ("final_time", "total_cost", "phi", "min_separation"):
        assert out[None][key] == out[2][key]
    if mode == "free_per_agent":   # each agent's own T_i, in the array file
        durations = [netCDF4.Dataset(tmp_path / f"ranks-{r}" / "result.nc")["duration"][:]
                     for r in (None, 2)]
        np.testing.assert_array_equal(durations[0], durations[1])
        assert np.ptp(durations[0]) > 0.1


@pytest.mark.parametrize(("fields", "words"), [
    ({"time_weight": 1.0}, "^time_weight: needs time_bounds"),
    ({"time_bounds": (2.0, 1.0)}, "^time_bounds: needs 0 < T_min <= T_max < inf"),
    ({"time_bounds": (1.0, 2.0), "free_duration": True}, "^time_bounds: not with free_duration"),
    ({"time_bounds": (1.0, 2.0), "solver": "newton"}, "^solver: .*time bounds.* are inequalities"),
    ({"time_weight": -1.0, "time_bounds": (1.0, 2.0)}, "^time_weight: must be a finite number"),
])
def test_bad_time_fields_are_refused_in_one_line(fields, words):
    with pytest.raises(ValueError, match=words) as caught:
        _shape(**fields)
    assert "\n" not in str(caught.value)
