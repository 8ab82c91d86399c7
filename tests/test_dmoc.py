"""DMOC specifics (the contract's convergence, warm start, failures and sensitivities are in
test_transcriptions.py): the path against the analytic minimum-energy double integrator."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from ocpar.examples.formation_halo import FINAL_ATTITUDE, START_ATTITUDE
from ocpar.examples.formation_halo import make as halo_spacecraft_example
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, OcpTask, cache_report, dmoc_problem, solve_task
from ocpar.ocp.constraints import PathConstraint

# boundary data p = (q0, v0, qN, vN) in the plane
PARAMS = np.array([0.0, 0.0, 1.0, 0.5, 3.0, 1.0, 0.0, -1.0])


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


def test_nonzero_mass_scales_cost():
    heavy = dmoc_problem(DmocShape(PointMass(mass=2.0), 10)).solve(PARAMS)
    light = dmoc_problem(DmocShape(PointMass(mass=1.0), 10)).solve(PARAMS)
    assert heavy.cost == pytest.approx(4 * light.cost, rel=1e-10)


def test_solver_is_built_once_per_shape():
    shape = DmocShape(PointMass(), 7)
    before = cache_report()
    for _ in range(3):
        solve_task(OcpTask(shape, PARAMS))
    after = cache_report()
    assert after["builds"] - before["builds"] == 1
    assert after["hits"] - before["hits"] == 2
    assert dmoc_problem(shape) is dmoc_problem(DmocShape(PointMass(), 7))


def test_a_previous_solution_without_multipliers_is_a_guess():
    """With holonomic constraints (a unit quaternion) w ends in λ; a guess of nodes and
    controls only, as a previous solution gives it, gets λ = 0."""
    shape = halo_spacecraft_example(agents=2, intervals=10).shape
    problem = dmoc_problem(shape)
    params = np.concatenate([np.zeros(3), START_ATTITUDE, np.zeros(7),
                             [0.3, -0.6, 0.7], FINAL_ATTITUDE, np.zeros(7)])
    sol = problem.solve(params)
    guess = problem.warm_start(sol)
    assert sol.success and guess.size == problem.nw - problem.nc * (shape.intervals + 1)
    again = problem.solve(params, guess)
    assert again.success and again.iterations <= sol.iterations
    assert again.cost == pytest.approx(sol.cost, rel=1e-9)


def test_bad_boundary_data_is_refused():
    with pytest.raises(ValueError, match="length 8"):
        dmoc_problem(DmocShape(PointMass(), 10)).solve(np.zeros(5))
    with pytest.raises(ValueError):
        DmocShape(PointMass(), 0)
    with pytest.raises(ValueError):
        PointMass(mass=-1.0)


def bounded_rest_to_rest(distance: float, duration: float, bound: float) -> float:
    """Closed-form min ∫u² for q̈ = u, rest to rest over ``distance`` in ``duration`` with
    |u| ≤ ``bound`` below the unconstrained peak 6 d/T²: u = ±bound on [0, τ] and
    [T − τ, T], linear in between (PMP: u is the saturated linear costate); τ from the
    displacement a (T τ − τ²) + (2a/3)(T/2 − τ)² = d."""
    from scipy.optimize import brentq

    half = duration / 2
    tau = brentq(lambda t: bound * (duration * t - t * t) + 2 * bound / 3 * (half - t) ** 2
                 - distance, 0.0, half)
    return 2 * bound**2 * (tau + (half - tau) / 3)


@pytest.mark.parametrize("solver", ["newton", "sqpmethod", "ipopt"])
def test_control_bounds_reach_the_closed_form_bounded_optimum_at_second_order(solver):
    from ocpar.ocp import solve_tasks

    distance, duration, bound = 1.0, 2.0, 1.2  # unconstrained peak 1.5: the bound is active
    exact = bounded_rest_to_rest(distance, duration, bound)
    errors = []
    for n in (20, 40, 80):
        shape = DmocShape(PointMass(dim=1), n, duration, solver=solver,
                          control_bounds=((-bound, bound),))
        solution = solve_tasks([OcpTask(shape, np.array([0.0, 0.0, distance, 0.0]))])[0]
        assert solution.success, solution.status
        assert np.max(np.abs(solution.u)) <= bound * (1 + 1e-12)
        assert np.isclose(np.max(np.abs(solution.u)), bound, rtol=1e-9)
        errors.append(solution.cost - exact)
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.array(errors) > 0) and np.all(np.abs(orders - 2) < 0.05), (errors, orders)


@pytest.mark.parametrize(("solver", "limit"), [
    ("newton", "box"), ("sqpmethod", "box"), ("ipopt", "box"), ("sqpmethod", "norm"),
    ("ipopt", "norm")])
def test_the_end_hessian_at_an_active_thrust_limit_is_that_of_the_active_set(solver, limit):
    """With thrust limits active on some intervals, d²J*/dq_N² from the active set's KKT
    system against second differences of the optimal cost (the active set does not change
    under the small steps), a box bound and a norm limit |u| ≤ 1.2 in the plane (a path
    constraint): the outer Newton step of the formation gets its curvature."""
    extra = ({"control_bounds": ((-1.2, 1.2),) * 2} if limit == "box" else
             {"path_constraints": (PathConstraint(lambda u: ca.sumsqr(u), upper=1.44),)})
    shape = DmocShape(PointMass(dim=2), 40, 2.0, solver=solver, **extra)
    params = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.6, 0.0, 0.0])  # free peak 1.5 |Δq|: active
    from ocpar.ocp import solve_tasks

    def solve(p):
        solution = solve_tasks([OcpTask(shape, p)])[0]
        assert solution.success, solution.status
        return solution

    centre, step = solve(params), 1e-4
    size = np.abs(centre.u[:, 0]) if limit == "box" else np.hypot(*centre.u.T)
    assert np.max(size) == pytest.approx(1.2, rel=1e-6)  # the limit binds
    fd = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            e_i, e_j = step * np.eye(8)[4 + i], step * np.eye(8)[4 + j]
            fd[i, j] = (solve(params + e_i + e_j).cost - solve(params + e_i - e_j).cost
                        - solve(params - e_i + e_j).cost + solve(params - e_i - e_j).cost
                        ) / (4 * step**2)
    np.testing.assert_allclose(centre.end_hessian, fd, rtol=1e-4, atol=1e-4)
    gradient = [(solve(params + step * np.eye(8)[4 + i]).cost
                 - solve(params - step * np.eye(8)[4 + i]).cost) / (2 * step) for i in range(2)]
    np.testing.assert_allclose(centre.cost_gradient[4:6], gradient, rtol=1e-6)


def test_inactive_control_bounds_leave_the_solution_and_its_hessian_unchanged():
    params = np.array([0.0, 0.0, 1.0, 0.5, 3.0, 1.0, 0.0, -1.0])
    free = dmoc_problem(DmocShape(PointMass(dim=2), 10, 2.0)).solve(params)
    loose = dmoc_problem(DmocShape(PointMass(dim=2), 10, 2.0,
                                   control_bounds=((-50.0, 50.0), (-50.0, 50.0)))).solve(params)
    assert loose.success and abs(loose.cost - free.cost) <= 1e-12 * free.cost
    np.testing.assert_allclose(loose.end_hessian, free.end_hessian, rtol=1e-9)


@pytest.mark.parametrize("bounds, message", [
    (((-1.0, 1.0),), "must be 2 pairs"),
    (((1.0, -1.0), (-1.0, 1.0)), "entry 0 needs lo <= hi"),
    (((float("nan"), 1.0), (-1.0, 1.0)), "entry 0 needs lo <= hi"),
    ("abc", "must be 2 pairs"),
])
def test_bad_control_bounds_are_refused_naming_the_field(bounds, message):
    with pytest.raises(ValueError, match=f"control_bounds: .*{message}"):
        DmocShape(PointMass(dim=2), 10, 1.0, control_bounds=bounds)


def weighted_velocity_optimum(distance: float, duration: float, weight: float) -> float:
    """min ∫ (u² + c² v²) dt for q̈ = u, rest to rest over ``distance`` in ``duration``
    (c = ``weight``): with y = v, ÿ = c² (y − B), y = A cosh(c(t − T/2)) + B, y(0) = 0 and
    ∫ y = d give J* = c² d² x cosh x / (T (x cosh x − sinh x)), x = cT/2 (12 d²/T³ as c → 0)."""
    x = weight * duration / 2
    return (weight**2 * distance**2 * x * np.cosh(x)
            / (duration * (x * np.cosh(x) - np.sinh(x))))


@pytest.mark.parametrize("solver", ["newton", "sqpmethod", "ipopt"])
def test_a_running_cost_of_velocity_and_control_reaches_its_closed_form_at_second_order(solver):
    """C(q, v, u) = |u|² + |v|² on the midpoint rule: rest to rest over 1 in T = 2 (exact
    e cosh(1)/2 = 2.0973...), errors at O(h²) on every solver; the gradient in the boundary
    data still comes from the multipliers and the Hessian from the KKT system."""
    exact = weighted_velocity_optimum(1.0, 2.0, 1.0)
    params = np.array([0.0, 0.0, 1.0, 0.0])
    errors = {}
    for n in (20, 80):
        shape = DmocShape(PointMass(dim=1), n, 2.0, solver=solver,
                          running_cost=lambda v, u: ca.sumsqr(u) + ca.sumsqr(v))
        sol = solve_task(OcpTask(shape, params))
        assert sol.success, sol.status
        errors[n] = abs(sol.cost - exact)
    assert np.log(errors[20] / errors[80]) / np.log(4) == pytest.approx(2.0, abs=0.05)
    nlp = dmoc_problem(shape)
    sol, step = nlp.solve(params), 1e-4
    costs = [nlp.solve(params + s * np.eye(4)[2]).cost for s in (-step, 0.0, step)]
    assert sol.cost_gradient[2] == pytest.approx((costs[2] - costs[0]) / (2 * step), rel=1e-6)
    second = (costs[2] - 2 * costs[1] + costs[0]) / step**2
    assert sol.end_hessian[0, 0] == pytest.approx(second, rel=1e-4)


def test_without_a_running_cost_the_nlp_is_the_control_energy_bit_for_bit():
    default = dmoc_problem(DmocShape(PointMass(), 12)).solve(PARAMS)
    explicit = dmoc_problem(DmocShape(PointMass(), 12, running_cost=lambda u: ca.sumsqr(u)))
    assert explicit.solve(PARAMS).cost == pytest.approx(default.cost, rel=1e-13)


@pytest.mark.parametrize(("cost", "message"), [
    (lambda w: w, "running_cost: function takes 'w'; it may take q"),
    (lambda u: u, "running_cost: must return a scalar"),
    (lambda u: u[5], "running_cost: does not evaluate"),
    ("u**2", "running_cost: function must be callable"),
])
def test_a_bad_running_cost_is_one_error_naming_the_field(cost, message):
    with pytest.raises(ValueError, match=message):
        DmocShape(PointMass(), 12, running_cost=cost)


def test_the_default_solver_is_chosen_from_the_shapes_constraints():
    """``solver="auto"`` (the default): newton for equalities only, sqpmethod once a path
    constraint is added (``dataclasses.replace`` keeps the choice automatic), and a thrust
    limit then binds; newton asked for explicitly is still refused with inequalities."""
    import dataclasses

    free = DmocShape(PointMass(), intervals=20)
    assert (free.solver, free.chosen_solver) == ("auto", "newton")
    limit = PathConstraint(lambda u: ca.sumsqr(u), upper=10.0**2, name="thrust")
    limited = dataclasses.replace(free, path_constraints=(limit,))
    assert (limited.solver, limited.chosen_solver) == ("auto", "sqpmethod")
    p = np.array([0, 0, 0, 0, 1, 0, 0, 0.0])   # rest to rest over 1 in T = 1
    unlimited = solve_task(OcpTask(free, p))
    assert unlimited.cost == pytest.approx(12.0, rel=1e-2)   # 12 d²/T³; peak |u| ≈ 6
    sol = solve_task(OcpTask(limited, p))
    assert sol.success and sol.cost == pytest.approx(unlimited.cost, rel=1e-9)  # 10 > 6
    tight = solve_task(OcpTask(dataclasses.replace(
        free, path_constraints=(PathConstraint(lambda u: ca.sumsqr(u), upper=5.0**2),)), p))
    assert tight.success and tight.cost > unlimited.cost + 1e-3   # the limit binds
    assert np.max(np.linalg.norm(tight.u, axis=-1)) == pytest.approx(5.0, abs=1e-6)
    with pytest.raises(ValueError, match="newton solver takes equalities only"):
        DmocShape(PointMass(), solver="newton", path_constraints=(limit,))


@pytest.mark.parametrize("free_duration", [False, True])
def test_default_guesses_are_the_cubic_hermite_paths_row_by_row(free_duration):
    """A batch's default guesses: node j of row i is the cubic Hermite point at s = j/N
    through (q0, T v0) and (qN, T vN), zero controls; a row is the one-task guess bit for
    bit (the batch is laid out agent-last, the one-task guess is a batch of one)."""
    shape = DmocShape(PointMass(), 5, duration=2.0, free_duration=free_duration)
    nlp = dmoc_problem(shape)
    rng = np.random.default_rng(7)
    params = rng.standard_normal((6, nlp.n_params))
    if free_duration:
        params[:, -1] = rng.uniform(0.5, 3.0, 6)
    guesses = nlp.default_guesses(params)
    for row, guess in zip(params, guesses, strict=True):
        q0, v0, qn, vn = row[:8].reshape(4, 2)
        t = row[-1] if free_duration else 2.0
        s = np.arange(1, 5)[:, None] / 5
        hermite = ((2 * s**3 - 3 * s**2 + 1) * q0 + (s**3 - 2 * s**2 + s) * t * v0
                   + (-2 * s**3 + 3 * s**2) * qn + (s**3 - s**2) * t * vn)
        np.testing.assert_allclose(guess[:8].reshape(4, 2), hermite, rtol=1e-14, atol=1e-14)
        assert not np.any(guess[8:])
        assert guess.tobytes() == nlp.default_guess(row).tobytes()
