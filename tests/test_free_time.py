"""Free and minimum final time (ocpar.formation.final_time, DmocShape.free_duration): the
derivatives in T against closed forms and finite differences, the free common T of the 60
point masses against T* = (3 J_1 / w)^(1/4), the minimum time of 10 thrust-limited point
masses against a bottleneck over the rotation and the assignment computed here (its reach
from a linear programme on DMOC's equations written here), bitwise the same on 2 MPI ranks."""

from __future__ import annotations

import dataclasses
import json
import math

import casadi as ca
import netCDF4
import numpy as np
import pytest
from conftest import run_cli
from scipy.optimize import linear_sum_assignment, linprog, minimize_scalar

from ocpar.examples import formation_minimum_time, formation_point_masses
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.feasibility import SLACK_TOL, elastic_shape
from ocpar.formation.final_time import at_duration, closest_across_horizons
from ocpar.formation.keep_out.separation import closest_approach
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, transcription
from ocpar.ocp.constraints import PathConstraint

WEIGHT = 1e3


@pytest.fixture(scope="module")
def fleet():
    """The 60 point masses and J_1, their optimum at T = 1 (a fixed-time run)."""
    problem = formation_point_masses.make()
    assert problem.common_shape.duration == 1.0
    fixed = solve_formation(problem)
    assert fixed.converged
    return problem, fixed.total_cost


def _solution(shape: DmocShape, params: np.ndarray, batched: bool):
    nlp = transcription(shape)
    if batched:
        return nlp.solve_batch(params[None], [None], [None]).items()[0]
    return nlp.solve(params)


@pytest.mark.parametrize("batched", [True, False], ids=["batch", "ipopt"])
def test_free_duration_derivatives_are_the_closed_forms(batched):
    """Point mass from rest to rest: J(q_N, T) = J(q_N, 1) / T³, so dJ/dT = −3J/T,
    d²J/dT² = 12J/T², d²J/dT dq_N = −3/T dJ/dq_N; one compiled solver for every T."""
    model = PointMass(dim=2, mass=1.0)
    params = np.array([0.0, 0.0, 0.0, 0.0, 3.0, 4.0, 0.0, 0.0])
    at_one = transcription(DmocShape(model, duration=1.0)).solve(params)
    free = DmocShape(model, duration=2.5, free_duration=True)
    assert free.n_params == 9 and transcription(free) is transcription(free.with_duration(7.0))
    for t in (0.5, 2.0):
        sol = _solution(free, np.append(params, t), batched)
        assert sol.success
        cost = at_one.cost / t**3
        assert sol.cost == pytest.approx(cost, rel=1e-12)
        assert sol.cost_gradient[-1] == pytest.approx(-3 * cost / t, rel=1e-10)
        assert sol.end_hessian.shape == (3, 3)
        assert sol.end_hessian[-1, -1] == pytest.approx(12 * cost / t**2, rel=1e-10)
        np.testing.assert_allclose(sol.end_hessian[-1, :2],
                                   -3 / t**4 * at_one.cost_gradient[4:6], rtol=1e-10)
        np.testing.assert_allclose(sol.end_hessian[:2, :2], at_one.end_hessian / t**3,
                                   rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("solver", ["sqpmethod", "ipopt"])
def test_a_task_of_free_time_is_the_closed_form(solver):
    """T a variable of the task (time_bounds, time_weight w): with J = c/T³ (c the cost at
    T = 1, ½ Δᵀ H₁ Δ) the optimum is T = (3c/w)^¼ and J̃ = (4/3) w T = k c^¼; its gradient
    (k/4) c^(−3/4) ∇c and Hessian (k/4) c^(−3/4) H₁ − (3k/16) c^(−7/4) ∇c ∇cᵀ (the
    Schur complement of T's block, from the KKT system)."""
    model, weight = PointMass(dim=2, mass=1.0), 50.0
    params = np.array([0.0, 0.0, 0.0, 0.0, 3.0, 4.0, 0.0, 0.0])
    one = transcription(DmocShape(model)).solve(params)
    c, h1, g1 = one.cost, one.end_hessian, one.cost_gradient[4:6]
    k = 4 / 3 * weight**0.75 * 3**0.25
    shape = DmocShape(model, time_weight=weight, time_bounds=(0.1, 100.0), solver=solver)
    nlp = transcription(shape)
    for sol in (nlp.solve(params), *([nlp.solve_batch(params[None], [None], [None]).items()[0]]
                                     if nlp.batches else [])):
        assert sol.success
        assert sol.duration == pytest.approx((3 * c / weight) ** 0.25, rel=1e-12)
        assert sol.cost == pytest.approx(k * c**0.25, rel=1e-12)
        np.testing.assert_allclose(sol.cost_gradient[4:6], k / 4 * c**-0.75 * g1, rtol=1e-12)
        np.testing.assert_allclose(
            sol.end_hessian, k / 4 * c**-0.75 * h1 - 3 * k / 16 * c**-1.75 * np.outer(g1, g1),
            rtol=1e-10, atol=1e-12)
    bound = transcription(dataclasses.replace(shape, time_bounds=(0.1, 1.0))).solve(params)
    assert bound.duration == pytest.approx(1.0, rel=1e-14)
    assert bound.cost == pytest.approx(c + weight, rel=1e-12)


def test_free_duration_derivatives_under_an_active_thrust_limit():
    """With |u| ≤ 1.2 binding, J is no power of T: dJ/dT and d²J/dT² (the active set's KKT
    system) against central differences of fixed-T solves."""
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=1.2**2, name="thrust")
    base = DmocShape(PointMass(dim=2, mass=1.0), intervals=10, path_constraints=(thrust,))
    params = np.array([0.0, 0.0, 0.0, 0.0, 0.15, 0.2, 0.0, 0.0])
    t, step = 1.0, 1e-4
    sol = transcription(dataclasses.replace(base, free_duration=True)).solve(
        np.append(params, t))
    assert sol.success and np.max(np.linalg.norm(sol.u, axis=1)) == pytest.approx(1.2, rel=1e-8)

    def cost(duration: float) -> float:
        solved = transcription(base.with_duration(duration)).solve(params)
        assert solved.success
        return solved.cost

    def slope(duration: float) -> float:
        solved = transcription(dataclasses.replace(base, free_duration=True)).solve(
            np.append(params, duration))
        return solved.cost_gradient[-1]

    assert sol.cost == pytest.approx(cost(t), rel=1e-10)
    assert sol.cost_gradient[-1] == pytest.approx((cost(t + step) - cost(t - step)) / (2 * step),
                                                  rel=1e-6)
    assert sol.end_hessian[-1, -1] == pytest.approx(
        (slope(t + step) - slope(t - step)) / (2 * step), rel=1e-5)


def test_a_fleet_of_free_duration_shapes_solves_as_a_fixed_one(fleet):
    """Shapes with T a parameter in a formation: T (their duration) is in the boundary
    data; the same optimum as the fixed-duration shapes."""
    problem, j1 = fleet
    free = problem.with_shapes(lambda s: dataclasses.replace(s, free_duration=True,
                                                             duration=2.0))
    assert free.boundary_params_rows(np.arange(2), np.zeros(2)).shape == (2, 9)
    result = solve_formation(free)
    assert result.converged
    assert result.total_cost == pytest.approx(j1 / 8, rel=1e-12)


def test_free_common_time_is_the_closed_form(fleet):
    """min over T of Σ J_i + w T with J ∝ 1/T³: T* = (3 J_1 / w)^(1/4), to 1e-9."""
    problem, j1 = fleet
    expected = (3 * j1 / WEIGHT) ** 0.25
    result = solve_formation(problem, options=FormationOptions(
        final_time="free", time_bounds=(0.5, 100.0), time_weight=WEIGHT, time_tol=1e-10))
    assert result.converged, result.message
    t = result.final_time["T"]
    assert abs(t - expected) <= 1e-9 * expected
    assert result.fleet.duration == t
    assert result.total_cost == pytest.approx(j1 / expected**3, rel=1e-9)
    assert result.final_time["objective"] == pytest.approx(4 / 3 * WEIGHT * expected, rel=1e-9)
    assert result.final_time["at_bound"] is None


def test_free_time_per_agent_is_each_agents_closed_form(fleet):
    """Each agent its own T_i, cost J_i + w T_i: from rest to rest J_i(T) = α |Δ_i|² / T³
    (α from one DMOC solve here), so T_i = (3 α |Δ_i|² / w)^¼ and the formation's rotation
    θ minimises Σ_i (4/3) w^¾ (3 α |Δ_i(θ)|²)^¼: a 1-D search here."""
    problem, _ = fleet
    result = solve_formation(problem, options=FormationOptions(
        final_time="free_per_agent", time_bounds=(0.5, 100.0), time_weight=WEIGHT))
    assert result.converged, result.message
    unit = transcription(problem.common_shape).solve(np.array([0.0] * 4 + [1.0, 0.0, 0, 0]))
    alpha = unit.cost   # J at T = 1 of a unit displacement
    starts = problem.positions(problem.starts)
    offsets = result.phi - result.phi[0]

    def squared(theta: float) -> np.ndarray:
        return np.sum((problem.final_positions(theta + offsets) - starts) ** 2, axis=1)

    def total(theta: float) -> float:
        return float(np.sum(4 / 3 * WEIGHT**0.75 * (3 * alpha * squared(theta)) ** 0.25))

    best = minimize_scalar(total, bounds=(result.phi[0] - 0.1, result.phi[0] + 0.1),
                           method="bounded", options={"xatol": 1e-12})
    # the rotation: the test's search's (to its accuracy on a flat minimum), no worse
    assert abs(best.x - result.phi[0]) <= 1e-6
    assert total(result.phi[0]) <= best.fun * (1 + 1e-13)
    # each agent's T_i: its closed form at its target
    expected = (3 * alpha * squared(result.phi[0]) / WEIGHT) ** 0.25
    np.testing.assert_allclose(result.durations, expected, rtol=1e-9)
    assert result.total_cost == pytest.approx(total(result.phi[0]), rel=1e-12)
    assert result.final_time["T"] == np.max(result.durations)
    assert 0 < result.separation.distance < math.inf   # across the agents' own horizons
    arrays = result.arrays()
    np.testing.assert_array_equal(arrays["duration"][1], result.durations)


def test_closest_approach_across_horizons_is_the_sampled_minimum():
    """Paths at their own times k T_i/N, held after T_i: the exact minimum over the union of
    node times against a dense sampling of t (never above it, within its resolution), and
    the common-horizon closest approach where every T_i is equal."""
    rng = np.random.default_rng(1)
    positions = rng.normal(size=(5, 11, 2))
    same, common = (closest_across_horizons(positions, np.full(5, 3.0)),
                    closest_approach(positions, 3.0))
    assert (same.distance, same.agents) == (common.distance, common.agents)
    assert same.time == pytest.approx(common.time, rel=1e-14)
    durations = np.array([1.0, 2.0, 1.5, 3.0, 2.5])
    found = closest_across_horizons(positions, durations)
    times = np.linspace(0.0, 3.0, 300_001)
    paths = np.stack([np.stack([np.interp(times, durations[i] * np.linspace(0, 1, 11),
                                          positions[i, :, a]) for a in range(2)], axis=-1)
                      for i in range(5)])
    sampled = min((float(np.min(np.linalg.norm(paths[i] - paths[j], axis=1))), (i, j))
                  for i in range(5) for j in range(i + 1, 5))
    assert found.agents == sampled[1]
    assert found.distance <= sampled[0] <= found.distance + 1e-6
    here = np.stack([np.interp(found.time, durations[i] * np.linspace(0, 1, 11),
                               positions[i, :, :].T[a]) for i in found.agents for a in range(2)])
    assert np.linalg.norm(here[:2] - here[2:]) == pytest.approx(found.distance, rel=1e-9)


def test_free_time_stops_at_its_bound(fleet):
    """T_max below T*: F' + w < 0 there, T = T_max (a bound's KKT point)."""
    problem, j1 = fleet
    result = solve_formation(problem, options=FormationOptions(
        final_time="free", time_bounds=(0.5, 10.0), time_weight=WEIGHT))
    assert result.converged and result.final_time["at_bound"] == "T_max"
    assert result.final_time["T"] == 10.0
    assert result.final_time["dF_dT_plus_w"] == pytest.approx(WEIGHT - 3 * j1 / 10.0**4,
                                                              rel=1e-9)


def test_free_time_under_thrust_limits_is_stationary():
    """The thrust-limited example (limits active, φ* moving with T): at the returned T,
    d/dT of the fixed-T formation optimum (central differences of two fixed-T runs) is −w."""
    problem, weight = formation_minimum_time.make(), 100.0
    result = solve_formation(problem, options=FormationOptions(
        final_time="free", time_bounds=(7.26, 100.0), time_weight=weight))
    assert result.converged, result.message
    t, step = result.final_time["T"], 1e-4
    assert np.max(result.peak_thrust) == pytest.approx(formation_minimum_time.U_MAX, rel=1e-9)

    def optimum(duration: float) -> float:
        fixed = solve_formation(at_duration(problem, duration), phi0=result.phi)
        assert fixed.converged
        return fixed.total_cost

    slope = (optimum(t + step) - optimum(t - step)) / (2 * step)
    assert slope == pytest.approx(-weight, rel=1e-5)


@pytest.mark.parametrize("mode", ["free", "free_per_agent"])
def test_free_time_is_bitwise_the_same_on_two_mpi_ranks(tmp_path, mode):
    args = ["-m", "ocpar.formation", "--agents", "20", "--final-time", mode,
            "--time-bounds", "0.5,100", "--time-weight", "1000", "--quiet"]
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
    if mode == "free_per_agent":   # each agent's T_i, in the array file
        durations = [netCDF4.Dataset(tmp_path / f"ranks-{r}" / "result.nc")["duration"][:]
                     for r in (None, 2)]
        np.testing.assert_array_equal(durations[0], durations[1])


def _dmoc_reach_at_one(mass: float, intervals: int, limit: float) -> float:
    """The farthest a 1-D point mass of DMOC (midpoint rule) goes from rest to rest in
    T = 1 under |u_k| ≤ ``limit``: max q_N subject to the discrete Euler–Lagrange equations
    written here (variables q_1..q_N, u_0..u_{N−1}; q_0 = 0)."""
    n, h = intervals, 1.0 / intervals
    a = np.zeros((n + 1, 2 * n))

    def q(k: int) -> int:
        return k - 1   # column of q_k, k ≥ 1 (q_0 = 0 is not a variable)

    def add(row: int, k: int, coefficient: float) -> None:
        if k >= 1:
            a[row, q(k)] += coefficient

    for row in range(n + 1):   # momentum balance at node `row`
        if row < n:            # D1 L_d(q_row, q_row+1) + h/2 u_row
            add(row, row + 1, -mass / h)
            add(row, row, mass / h)
            a[row, n + row] += h / 2
        if row > 0:            # D2 L_d(q_row−1, q_row) + h/2 u_row−1
            add(row, row, mass / h)
            add(row, row - 1, -mass / h)
            a[row, n + row - 1] += h / 2
    cost = np.zeros(2 * n)
    cost[q(n)] = -1.0
    bounds = [(None, None)] * n + [(-limit, limit)] * n
    solved = linprog(cost, A_eq=a, b_eq=np.zeros(n + 1), bounds=bounds, method="highs")
    assert solved.status == 0
    return -solved.fun


def _bottleneck(costs: np.ndarray) -> float:
    """The least t with a perfect matching of entries ≤ t (assignments of zero cost)."""
    values = np.unique(costs)
    lo, hi = 0, len(values) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        over = (costs > values[mid]).astype(float)
        rows, cols = linear_sum_assignment(over)
        if over[rows, cols].sum() == 0:
            hi = mid
        else:
            lo = mid + 1
    return float(values[lo])


def test_minimum_time_is_the_bottleneck_over_rotation_and_assignment():
    """10 point masses under |u| ≤ 2, free rotation and assignment: T*² = min_θ min_σ max_i
    |z_σ(i)(θ) − s_i| / r_1 (r_1 the reach at T = 1, scaling as T²), searched here on a
    grid and polished; the run's bracket holds it, the paths are verified at T*, phase 1 is
    infeasible at T*(1 − 1e-6)."""
    problem = formation_minimum_time.make()
    n, u_max = problem.agents, formation_minimum_time.U_MAX
    r1 = _dmoc_reach_at_one(1.0, problem.common_shape.intervals, u_max)
    starts = problem.positions(problem.starts)
    spacing = 2 * math.pi / n

    def need(theta: float) -> float:
        points = problem.final_positions(theta + spacing * np.arange(n))
        return _bottleneck(np.linalg.norm(points[None] - starts[:, None], axis=2) / r1)

    grid = np.linspace(0.0, spacing, 2001)
    best = int(np.argmin([need(t) for t in grid]))
    polished = minimize_scalar(need, bounds=(grid[max(best - 1, 0)], grid[min(best + 1, 2000)]),
                               method="bounded", options={"xatol": 1e-13})
    expected = math.sqrt(min(polished.fun, need(grid[best])))

    tol = 1e-6
    result = solve_formation(problem, options=FormationOptions(final_time="minimum",
                                                               time_tol=tol))
    assert result.converged, result.message
    low, high = result.final_time["bracket"]
    t = result.final_time["T"]
    assert t == high and high * (1 - tol) <= low
    assert low * (1 - 1e-12) <= expected <= high * (1 + 1e-12)
    assert abs(t - expected) <= tol * expected
    # feasible at T*: the verified paths keep the limit and reach the equidistant formation
    assert result.fleet.duration == t
    assert np.max(result.peak_thrust) <= u_max * (1 + 1e-9)
    assert result.equidistance_error <= 1e-12
    # infeasible at T*(1 − 1e-6): phase 1 (the elastic problem) of the returned targets
    shape = elastic_shape(problem.common_shape.with_duration(t * (1 - tol)))
    params = problem.boundary_params_rows(np.arange(n), result.phi)
    slacks = [transcription(shape).solve(row) for row in params]
    assert all(s.success for s in slacks)
    assert sum(s.cost for s in slacks) > SLACK_TOL


@pytest.mark.slow
def test_minimum_time_by_phase_one_brackets_the_exact_one():
    """Without an exact reach set (the same limit written |u|⁴ ≤ 16, which the reach module
    does not read as a norm), bisection with phase 1 gives a bracket that holds the exact
    minimum time of |u|² ≤ 4 (4 agents, tol 1e-2)."""
    problem = formation_minimum_time.make(agents=4)
    exact = solve_formation(problem, options=FormationOptions(final_time="minimum"))
    assert exact.converged and exact.final_time["proven"]
    quartic = PathConstraint(lambda u: ca.sumsqr(u) ** 2, upper=16.0, name="thrust")
    other = problem.with_shapes(lambda s: dataclasses.replace(s, path_constraints=(quartic,)))
    result = solve_formation(other, options=FormationOptions(
        final_time="minimum", time_bounds=(5.0, 10.0), time_tol=1e-2))
    assert result.converged, result.message
    low, high = result.final_time["bracket"]
    assert result.final_time["method"] == "phase 1" and not result.final_time["proven"]
    assert high * (1 - 1e-2) <= low <= exact.final_time["T"] <= high
    assert result.final_time["phase_one_slack"] > SLACK_TOL


@pytest.mark.parametrize(("options", "words"), [
    ({"final_time": "free", "time_weight": 1.0}, "needs time_bounds"),
    ({"final_time": "free", "time_bounds": (1.0, 2.0)}, "needs a time_weight"),
    ({"final_time": "minimum"}, "needs time_bounds \\(T_min, T_max\\) to bisect"),
    ({"final_time": "free", "time_bounds": (1.0, 2.0), "time_weight": 1.0,
      "mode": "monolithic"}, "applies to the hierarchical mode"),
])
def test_final_time_refusals_are_one_line(options, words):
    problem = formation_point_masses.make(agents=4)
    with pytest.raises(ValueError, match=words) as caught:
        solve_formation(problem, options=FormationOptions(**options))
    assert "\n" not in str(caught.value)


def test_time_bounds_must_be_an_interval():
    with pytest.raises(ValueError, match="time_bounds: needs T_min,T_max"):
        FormationOptions(time_bounds=(3.0, 1.0))
