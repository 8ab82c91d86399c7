"""Every returned formation verified as returned (:mod:`ocpar.formation.verify`): a converged
run passes from its own end points and paths; a corrupted answer fails on exactly what was
broken, naming the agent; a run that did not reach its answer reports no headline figure;
a near-collision is said."""

from __future__ import annotations

import dataclasses
import json
import math

import casadi as ca
import numpy as np
import pytest
from conftest import assert_no_sentinel
from scipy.optimize import minimize_scalar

from ocpar.examples.formation_mixed_fleet import make as make_fleet
from ocpar.examples.formation_point_masses import make as make_masses
from ocpar.formation import (
    Circle,
    DmocShape,
    Ellipse,
    FormationOptions,
    FormationProblem,
    Sphere,
    solve_formation,
)
from ocpar.formation.plot import plot_formation
from ocpar.formation.solve import _verified
from ocpar.formation.targets.surface import SphereSurface
from ocpar.formation.verify import (
    NEAR_COLLISION_FRACTION,
    formation_spacing,
    verify_formation,
)
from ocpar.models import PointMass
from ocpar.ocp.columns_eval import evaluate_columns
from ocpar.result_files import write_result

CENTRE, RADIUS = np.array([100.0, 100.0]), 10.0


@pytest.fixture(scope="module")
def six():
    problem = make_masses(6)
    return problem, solve_formation(problem)


def _independent_coupling(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(r²/n³) dG/dφ_k, G = Σ_{i<j} 1/|z_i − z_j|², on the circle through ``points`` (n, 2)
    about ``centre``, with φ_k = atan2 of each point: written here from the formula."""
    rel = points - centre
    radius = np.linalg.norm(rel, axis=1).mean()
    phi = np.arctan2(rel[:, 1], rel[:, 0])
    z = radius * np.column_stack([np.cos(phi), np.sin(phi)])
    tangent = radius * np.column_stack([-np.sin(phi), np.cos(phi)])
    diff = z[:, None, :] - z[None, :, :]
    dist_sq = np.sum(diff**2, axis=2)
    np.fill_diagonal(dist_sq, np.inf)
    grad = -2.0 * np.sum(np.einsum("kjd,kd->kj", diff, tangent) / dist_sq**2, axis=1)
    n = len(points)
    return radius**2 / n**3 * grad


def test_a_converged_circle_verifies_from_its_end_points(six):
    _, result = six
    v = result.verification
    assert result.status == "converged" and v.passed and not v.failures
    ends = result.trajectories[:, -1, :2]
    # located angles = atan2 of the end points, computed here
    rel = ends - CENTRE
    np.testing.assert_allclose(np.mod(v.parameters, 2 * np.pi),
                               np.mod(np.arctan2(rel[:, 1], rel[:, 0]), 2 * np.pi),
                               atol=1e-12)
    independent = np.max(np.abs(_independent_coupling(ends, CENTRE)))
    assert v.coupling_residual <= 1e-8 and independent <= 1e-8
    assert v.checks["target"].value <= 1e-12
    assert v.checks["momentum"].value <= 1e-10
    assert v.checks["dynamics"].value <= 1e-10
    assert result.to_dict()["verification"]["passed"] is True


def test_an_inner_node_moved_breaks_the_interior_equations_only(six):
    """A unit point mass (L = |v|²/2, force u): DMOC's interior equation at node k is
    (q_k − q_{k−1})/h − (q_{k+1} − q_k)/h + h (u_{k−1} + u_k)/2 = 0, written here; moving q_5
    by δ breaks those of k = 4, 5, 6 and no boundary equation."""
    problem, result = six
    q, u = result.trajectories.copy(), result.controls
    q[2, 5, :2] += np.array([3e-4, -1e-4])
    v = verify_formation(problem, q, u, result.phi)
    failed = {name for name, c in v.checks.items() if not c.passed}
    assert failed == {"dynamics"} and v.checks["dynamics"].agent == 2
    h = problem.common_shape.duration / problem.common_shape.intervals
    worst = 0.0
    for k in range(1, problem.common_shape.intervals):
        terms = [(q[2, k] - q[2, k - 1]) / h, -(q[2, k + 1] - q[2, k]) / h,
                 h / 2 * u[2, k - 1], h / 2 * u[2, k]]
        worst = max(worst, np.linalg.norm(sum(terms))
                    / (1 + sum(np.linalg.norm(t) for t in terms)))
    assert worst > 1e-5   # far above the tolerance, 1e-7
    assert v.checks["dynamics"].value == pytest.approx(worst, rel=1e-9)
    assert "breaks its dynamics" in v.failures[0]


def test_an_end_point_moved_off_the_circle_is_named(six):
    problem, result = six
    q = result.trajectories.copy()
    radial = (q[3, -1, :2] - CENTRE) / RADIUS
    q[3, -1, :2] += 1e-3 * radial
    v = verify_formation(problem, q, result.controls, result.phi)
    failed = {name: c for name, c in v.checks.items() if not c.passed}
    # the end point is off the target, the path no longer meets its end velocity, and the
    # last inner node's equation (q_N is in it) breaks
    assert set(failed) == {"target", "momentum", "dynamics"}
    assert {c.agent for c in failed.values()} == {3}
    assert failed["target"].value == pytest.approx(1e-3 / RADIUS, rel=1e-6)
    assert v.failures[0].startswith("agent 3's end point lies 0.0001 (relative) off")
    # moved along the radius: the located angle, and with it the coupling, unchanged
    assert v.coupling_residual <= 1e-8
    # the solve's status follows: converged becomes failed, the first failure first
    _, status, message = _verified(v, "converged", result.message)
    assert status == "failed"
    assert message.startswith("the returned formation fails verification: agent 3's end "
                              "point") and "(and 2 more)" in message


@pytest.mark.parametrize("limit", ["box", "norm"])
def test_a_broken_thrust_limit_is_named(limit):
    problem = make_fleet(limit=limit)
    result = solve_formation(problem)
    assert result.status == "converged" and result.verification.passed
    u = result.controls.copy()
    u[5, 7] *= 1.001 * 2.7 / np.max(np.abs(u[5, 7]) if limit == "box"
                                    else np.linalg.norm(u[5, 7]))
    v = verify_formation(problem, result.trajectories, u, result.phi)
    failed = {name: c for name, c in v.checks.items() if not c.passed}
    name = "control_bounds" if limit == "box" else "path_constraints"
    # the scaled control no longer moves the returned path: the interior equations break too
    assert set(failed) == {name, "dynamics"}
    assert failed[name].agent == failed["dynamics"].agent == 5
    # box: 1e-3 of u_max = 2.7 over max(1, 2.7); norm: |u|² ≤ u_max² broken by ~2e-3 u_max²
    expected = 1e-3 if limit == "box" else (1.001**2 - 1) * 2.7**2 / 2.7**2
    assert failed[name].value == pytest.approx(expected, rel=1e-6)
    assert v.failures[0].startswith("agent 5's")


def test_locate_on_an_ellipse_and_a_sphere_against_a_direct_search():
    ellipse = Ellipse(center=np.array([1.0, -2.0]), semi_axes=(3.0, 1.5))
    rng = np.random.default_rng(3)
    phi = rng.uniform(-np.pi, np.pi, 7)
    normals = np.column_stack([1.5 * np.cos(phi), 3.0 * np.sin(phi)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = ellipse.points(phi) + 0.05 * normals     # off the curve along its normal
    located, distance = ellipse.locate(points, phi + 0.05)
    for x, found, gap in zip(points, located, distance, strict=True):
        best = minimize_scalar(lambda t, x=x: np.sum((ellipse.points(np.array([t]))[0]
                                                      - x) ** 2),
                               bounds=(found - 0.3, found + 0.3), method="bounded",
                               options={"xatol": 1e-12})
        assert gap == pytest.approx(np.sqrt(best.fun), abs=1e-9)
    np.testing.assert_allclose(distance, 0.05, rtol=1e-9)
    sphere = SphereSurface(radius=2.0)
    x = rng.normal(size=(5, 3))
    params = sphere.locate(x)
    distance = np.linalg.norm(sphere.points(params) - x, axis=1)
    np.testing.assert_allclose(sphere.points(params), 2.0 * x / np.linalg.norm(x, axis=1,
                                                                                keepdims=True),
                               atol=1e-12)
    np.testing.assert_allclose(distance, np.abs(np.linalg.norm(x, axis=1) - 2.0), atol=1e-12)


def test_a_failed_run_reports_no_cost_and_its_plot_says_why(tmp_path):
    """Inner solves that cannot finish (IPOPT with 2 iterations on a box-limited fleet):
    status failed, total_cost null in result.json, the plot's title says failed and why."""
    problem = make_fleet(limit="box").with_shapes(
        lambda shape: dataclasses.replace(shape, solver="ipopt", max_iter=2))
    result = solve_formation(problem)
    assert result.status == "failed"
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["status"] == "failed"
    assert data["total_cost"] is None and "agent_costs" not in data
    assert data["verification"]["passed"] is False
    assert "not reached (failed: " in result.summary()
    assert "total cost 0" not in result.summary()
    assert math.isnan(result.total_cost) and result.last_iterate["total_cost"] > 0
    # stopped by a failed inner solve: its outer iterations are not known, and said so
    assert result.outer_iterations is None and data["outer_iterations"] is None
    assert "outer iterations —" in result.summary()
    title = result.title()
    # the start scan (feasibility) finds every shift's solves failing: the why is in the title,
    # the solver's own words in the message
    assert title.startswith("failed: ") and "no feasible start" in title
    assert "Maximum_Iterations_Exceeded" in result.message
    assert "total cost" not in title
    assert plot_formation(problem, result, tmp_path / "formation.png").stat().st_size > 0


def test_a_run_stopped_at_its_iteration_limit_reports_no_cost():
    problem = make_masses(6)
    result = solve_formation(problem, options=FormationOptions(max_outer_iterations=1))
    assert result.status == "not_converged"
    data = result.to_dict()
    assert data["total_cost"] is None and "agent_costs" not in data
    assert data["unconstrained_cost"] is None
    assert result.title().startswith("not converged: ")


def crossing_pair(radius: float = 1.0) -> FormationProblem:
    """Two unit masses at (∓1, 0) moving at ±4 towards each other, to a circle of ``radius``
    about the origin at rest after T = 1: each one's best end point is start + v T/2 = (±2,
    0)-ward, so they swap sides along the x-axis and, mirror images of each other, meet at
    the origin at t where both are there."""
    return FormationProblem(
        name="crossing-pair",
        shape=DmocShape(PointMass(dim=2, mass=1.0), intervals=10, duration=1.0),
        curve=Circle(radius=radius, center=np.zeros(2)),
        starts=np.array([[-1.0, 0.0], [1.0, 0.0]]),
        start_velocities=np.array([[4.0, 0.0], [-4.0, 0.0]]))


def test_a_near_collision_is_said(tmp_path):
    problem = crossing_pair()
    result = solve_formation(problem)
    assert result.status == "converged" and result.verification.passed
    ends = result.trajectories[:, -1, :2]
    np.testing.assert_allclose(ends, [[1.0, 0.0], [-1.0, 0.0]], atol=1e-9)  # they swapped
    # the closest approach, sampled densely on the piecewise-linear paths here
    s = np.linspace(0, 1, 10001)[:, None, None, None]
    q = result.trajectories[:, :, :2]
    between = (1 - s) * q[:, :-1][None] + s * q[:, 1:][None]   # (samples, 2, N, 2)
    sampled = np.min(np.linalg.norm(between[:, 0] - between[:, 1], axis=-1))
    near = result.verification.near_collision
    assert near is not None and near["agents"] == [0, 1]
    assert near["spacing"] == pytest.approx(2.0, rel=1e-9)
    assert near["distance"] <= sampled + 1e-12 and sampled <= 2e-4 * 2.0
    assert near["fraction"] < NEAR_COLLISION_FRACTION
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["near_collision"]["agents"] == [0, 1]
    assert data["total_cost"] == pytest.approx(result.total_cost)
    assert "near-collision: agents 0 and 1" in result.message
    assert "--min-separation" in result.message
    assert "optimum without a separation requirement" in result.message


@pytest.mark.parametrize("dim", [2, 3])
def test_the_spacing_on_a_circle_is_the_all_pairs_minimum(dim):
    """Neighbours in angle give the smallest distance of points on a circle (in a plane of
    space too), as the distance matrix does."""
    rng = np.random.default_rng(dim)
    axes = np.eye(dim)[:2] if dim == 2 else np.linalg.qr(rng.normal(size=(3, 3)))[0][:, :2].T
    circle = Circle(center=np.arange(dim, dtype=float), axes=axes, radius=3.0)
    phi = rng.uniform(-10, 10, 300)
    points = circle.evaluator.evaluate(phi, 0)
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)

    class OnCircle:
        on_circle = True

    assert formation_spacing(OnCircle(), points, phi) == pytest.approx(
        gaps.min(), rel=1e-12)


def test_no_near_collision_where_paths_keep_apart(six):
    _, result = six
    v = result.verification
    assert v.near_collision is None and v.closest.distance > NEAR_COLLISION_FRACTION * v.spacing
    assert result.to_dict()["near_collision"] is None
    assert "near-collision" not in result.message


def test_a_path_through_an_obstacle_is_named():
    """An obstacle beside the paths: the run clears it; a node of agent 2 moved onto the
    ball's centre puts two of its segments through it, by the radius."""
    problem = dataclasses.replace(make_masses(6), obstacles=(Sphere((50.0, -20.0), 5.0),))
    result = solve_formation(problem)
    assert result.status == "converged" and result.verification.passed
    q = result.trajectories.copy()
    q[2, 5, :2] = (50.0, -20.0)
    v = verify_formation(problem, q, result.controls, result.phi)
    failed = {name: c for name, c in v.checks.items() if not c.passed}
    # the moved node breaks agent 2's interior equations too (its controls did not move it)
    assert set(failed) == {"obstacles", "dynamics"}
    assert failed["obstacles"].agent == failed["dynamics"].agent == 2
    assert failed["obstacles"].value == pytest.approx(5.0, rel=1e-12)
    assert any(f.startswith("agent 2's path enters obstacles[0] (sphere) by 5")
               for f in v.failures)


def test_columns_evaluated_with_numpy_equal_casadi():
    """:func:`evaluate_columns` walks an SX function's instructions in numpy: the same
    numbers as CasADi's own map, on a function using many operations; an MX function goes
    through the map."""
    x, y = ca.SX.sym("x", 3), ca.SX.sym("y")
    out = ca.vertcat(ca.sin(x[0]) * y + 3.0, ca.sqrt(ca.fabs(x[1])), ca.atan2(x[2], y),
                     ca.if_else(x[0] > 0, x[1] ** 3, ca.exp(-x[2])),
                     ca.fmin(x[0], y) / ca.cosh(x[1]), ca.norm_2(x), ca.power(ca.fabs(y), 0.7))
    f = ca.Function("f", [x, y], [out, ca.sumsqr(x) * y])
    rng = np.random.default_rng(0)
    xs, ys = rng.normal(size=(50, 3)), rng.normal(size=(50, 1))
    expected = [np.asarray(o).T for o in f.map(50)(xs.T, ys.T)]
    for got, want in zip(evaluate_columns(f, xs, ys), expected, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-15)
    mx = ca.MX.sym("x", 3)
    g = ca.Function("g", [mx], [ca.sin(mx) * 2])
    np.testing.assert_allclose(evaluate_columns(g, xs)[0], 2 * np.sin(xs), rtol=1e-15)


def test_pursuit_stopped_at_its_agent_budget_reports_no_final_mass():
    """The same mechanism (:class:`ocpar.results.RunResult`) in the pursuit scheme: a train
    stopped at ``max_agents`` (not converged) holds its final mass and fuel as NaN in Python
    (the train's last agent's, which it returned, kept apart as the last iterate's), writes
    them as null and says "not reached"; its per-agent history stays."""
    from ocpar.examples.pursuit_orbit_transfer import make
    from ocpar.pursuit import PursuitSettings, solve_pursuit

    result = solve_pursuit(make(case=1, samples=101),
                           PursuitSettings(window=32, update=16, max_agents=12,
                                           certify_samples=0),
                           reference=False)
    assert (result.status, result.stop_reason) == ("not_converged", "max_agents")
    assert np.isnan(result.headline) and np.isnan(result.cost)
    assert result.last_iterate["headline"] == result.train_headline == result.headlines[-1]
    assert result.last_iterate["cost"] == result.train_cost
    assert 400 < result.last_iterate["headline"] < 525   # a final mass (kg), below the start's
    data = result.to_dict()
    assert data["final_mass_kg"] is None and data["fuel_kg"] is None
    np.testing.assert_array_equal(result.dataset()["agent_headline"], result.headlines)
    summary = result.summary()
    assert "final mass — not reached (not_converged: " in summary
    assert_no_sentinel(summary)
