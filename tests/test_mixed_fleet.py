"""A mixed fleet with thrust limits (``ocpar.examples.formation_mixed_fleet``): 12 planar point
masses of masses 0.5, 1 and 1.5 onto a circle, each with a box or a norm thrust limit that
binds at the optimum. The hierarchical scheme (outer Newton on the inner sensitivities from
the active set) against the monolithic NLP of the same discretisation, and across backends.
"""

from __future__ import annotations

import dataclasses
import json
import re

import casadi as ca
import numpy as np
import pytest
from conftest import run_cli

import ocpar
from ocpar.bsp import open_backend
from ocpar.examples.formation_mixed_fleet import make
from ocpar.formation import (
    DmocShape,
    Ellipsoid,
    FormationOptions,
    FormationProblem,
    HalfSpace,
    Sphere,
    solve_formation,
)
from ocpar.models import PointMass
from ocpar.ocp.constraints import NormSquared, PathConstraint

U_MAX = 2.7


@pytest.fixture(scope="module")
def free():
    return solve_formation(make(limit=None))


@pytest.mark.parametrize("limit", ["box", "norm"])
def test_thrust_limited_fleet_hierarchical_equals_monolithic(limit, free):
    """Measured: box 63.2814391059 (6 supersteps), norm 63.2995712603 (5), free 63.0311212078
    (4); hierarchical and monolithic agree to ~1.6e-14, the coupling to ~2e-16."""
    problem = make(limit=limit)
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.status == monolithic.status == "converged", hierarchical.message
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-7)
    assert hierarchical.coupling_residual <= 1e-9
    assert len(hierarchical.trace) <= len(free.trace) + 3
    size = (np.max(np.abs(hierarchical.controls), axis=2) if limit == "box"
            else np.linalg.norm(hierarchical.controls, axis=2))
    assert np.max(size) <= U_MAX * (1 + 1e-9)
    binding = np.max(size, axis=1) >= U_MAX * (1 - 1e-7)
    assert binding.sum() >= 2 and not binding.all()  # the heaviest agents' limits bind
    assert free.total_cost < hierarchical.total_cost < free.total_cost * 1.01
    assert np.max(free.peak_thrust) > U_MAX  # without limits they would be broken


def test_agents_with_equal_shapes_share_a_solver_and_the_fleet_is_checked():
    problem = make(limit="box")
    assert len(set(problem.shapes)) == 3  # three masses: three compiled solvers
    with pytest.raises(ValueError, match="one shape per agent: 11 shapes for 12 agents"):
        FormationProblem("short", problem.shape[:-1], problem.curve, problem.starts)
    other = DmocShape(problem.shape[0].model, intervals=10, duration=5.0)
    message = r"shape\[1\]: intervals 10 differs from shape\[0\]'s 20"
    with pytest.raises(ValueError, match=message):
        FormationProblem("mixed-N", (problem.shape[0], other, *problem.shape[2:]),
                         problem.curve, problem.starts)


def segment_to_point(p0: np.ndarray, p1: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Distance from ``centre`` to each segment p0 → p1 (m, d), written here."""
    step = p1 - p0
    s = np.clip(np.sum((centre - p0) * step, axis=1) / np.sum(step * step, axis=1), 0, 1)
    return np.linalg.norm(p0 + s[:, None] * step - centre, axis=1)


@pytest.mark.parametrize("limit", [None, "box"])
def test_paths_keep_clear_of_a_ball_at_all_times(limit, free):
    """A ball of radius 2.5 about (0, 5) that the optimal paths cross, in every agent's inner
    problem: every segment of every path stays outside it (an independent segment-to-centre
    distance on the returned nodes), the formation turns for it, and the hierarchical scheme
    equals the monolithic NLP with the same planes. Measured: free 63.0311 -> 63.5748
    (+0.86 %), box-limited 63.2814 -> 63.9466 (+1.05 %)."""
    radius, centre = 2.5, np.array([0.0, 5.0])
    before = free if limit is None else solve_formation(make(limit=limit))
    nodes = before.trajectories
    assert np.min(segment_to_point(nodes[:, :-1].reshape(-1, 2), nodes[:, 1:].reshape(-1, 2),
                                   centre)) < radius - 0.5  # the free paths cross it
    result = solve_formation(make(limit=limit, obstacle=radius))
    assert result.status == "converged", result.message
    nodes = result.trajectories
    gaps = segment_to_point(nodes[:, :-1].reshape(-1, 2), nodes[:, 1:].reshape(-1, 2), centre)
    assert np.min(gaps) >= radius * (1 - 1e-8)
    assert result.obstacle_clearance.distance == pytest.approx(np.min(gaps) - radius, abs=1e-9)
    assert before.total_cost < result.total_cost < 1.03 * before.total_cost
    assert np.max(np.abs(result.phi - before.phi)) > 1e-3   # the formation turned
    assert result.coupling_residual <= 1e-9
    monolithic = solve_formation(make(limit=limit, obstacle=radius),
                                 options=FormationOptions(mode="monolithic"))
    assert monolithic.status == "converged", monolithic.message
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-10)
    np.testing.assert_allclose(result.phi, monolithic.phi, atol=1e-8)
    fields = result.scheme_fields()
    assert fields["min_obstacle_clearance"] == result.obstacle_clearance.distance
    assert fields["obstacle_index"] == 0 and "obstacle_sides" not in fields
    assert result.arrays()["obstacle_side"][1].shape == (12, 1)   # one ball, 12 agents


def pair_gaps(nodes: np.ndarray) -> np.ndarray:
    """Closest approach (pairs, N) of every pair of agents on every interval of the paths
    linear between the nodes (n, N+1, 2), written here: the distance of the segment their
    relative position traces to the origin."""
    i, j = np.triu_indices(len(nodes), 1)
    rel = nodes[i] - nodes[j]
    return segment_to_point(rel[:, :-1].reshape(-1, 2), rel[:, 1:].reshape(-1, 2),
                            np.zeros(2)).reshape(len(i), -1)


SEPARATION = 0.4


@pytest.fixture(scope="module")
def ball_alone():
    return solve_formation(make(obstacle=2.5))


def test_paths_keep_clear_of_a_ball_and_apart_at_all_times(ball_alone):
    """The ball (in the inner problems) and a minimum separation D = 0.4 (box limits, the
    separation rounds): D binds (the ball alone leaves agents 10 and 11 0.269 apart, pushed
    together round it); every pair stays ≥ D apart and every agent outside the ball at
    every time (independent segment distances), at a cost above each constraint's alone.
    Measured: free 63.2814, ball 63.9466, D 63.5329 (11 rounds), both 64.0548 (4 rounds, 108
    solves; 64.3502 in 21 rounds when obstacle rounds imposed tangent planes)."""
    radius, centre = 2.5, np.array([0.0, 5.0])
    assert ball_alone.separation.distance < SEPARATION - 0.05
    apart = solve_formation(make(), options=FormationOptions(min_separation=SEPARATION))
    result = solve_formation(make(obstacle=radius),
                             options=FormationOptions(min_separation=SEPARATION))
    assert result.status == "converged", result.message
    nodes = result.trajectories
    gaps = pair_gaps(nodes)
    assert np.min(gaps) >= SEPARATION * (1 - 1e-8)
    assert result.separation.distance == pytest.approx(np.min(gaps), abs=1e-9)
    clear = segment_to_point(nodes[:, :-1].reshape(-1, 2), nodes[:, 1:].reshape(-1, 2), centre)
    assert np.min(clear) >= radius * (1 - 1e-8)
    assert result.obstacle_clearance.distance == pytest.approx(np.min(clear) - radius, abs=1e-9)
    assert result.total_cost >= max(ball_alone.total_cost, apart.total_cost)
    assert result.unconstrained_cost == ball_alone.total_cost
    np.testing.assert_array_equal(result.phi, ball_alone.phi)
    assert result.separation_rounds >= 1
    fields = result.scheme_fields()
    assert fields["required_separation"] == SEPARATION
    assert fields["separation_rounds"] == result.separation_rounds
    assert fields["min_obstacle_clearance"] == result.obstacle_clearance.distance
    assert "separation 0.4 met after" in result.message
    assert "obstacles cleared" in result.message


def test_one_separation_round_leaves_the_ball_clear(ball_alone):
    """One separation round: whatever the rounds leave of D, the ball holds, being in every
    agent's inner problem (an independent segment distance)."""
    result = solve_formation(make(obstacle=2.5), options=FormationOptions(
        min_separation=SEPARATION, separation_rounds=1))
    assert result.status in ("converged", "separation_not_met"), result.message
    assert result.separation_rounds == 1
    nodes = result.trajectories
    clear = segment_to_point(nodes[:, :-1].reshape(-1, 2), nodes[:, 1:].reshape(-1, 2),
                             np.array([0.0, 5.0]))
    assert np.min(clear) >= 2.5 * (1 - 1e-8)
    assert result.obstacle_clearance.distance >= -1e-9


@pytest.mark.parametrize(("change", "message"), [
    ({"obstacles": (Sphere((0.0, 0.0), 0.5),)}, "starts: agent 6 lies inside obstacles[0]"),
    ({"obstacles": (Sphere((0.0, 5.0, 1.0), 1.0),)}, "obstacles[0] (sphere): lies in 3-D"),
    ({"obstacles": (Sphere((0.0, 5.0), 1.0), "ball")}, "obstacles[1]: must be a Sphere"),
    ({"obstacles": Sphere((0.0, 5.0), 1.0)}, "obstacles: must be a list"),
])
def test_bad_obstacles_are_one_error_naming_the_field(change, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        dataclasses.replace(make(), **change)


@pytest.mark.parametrize(("build", "message"), [
    (lambda: Sphere((0.0, 5.0), -1.0), "semi_axes must be > 0"),
    (lambda: Sphere((0.0, float("nan")), 1.0), "obstacle sphere: center must be d finite numbers"),
    (lambda: Ellipsoid((0.0, 0.0), (1.0, 2.0), axes=((1.0, 0.0), (1.0, 0.0))), "orthonormal"),
    (lambda: HalfSpace((0.0, 0.0), 1.0), "non-zero normal"),
])
def test_malformed_obstacles_are_refused(build, message):
    with pytest.raises(ValueError, match=message):
        build()


def test_obstacles_no_formation_can_avoid_are_refused():
    """A ball over the whole target circle: no rotation of the formation clears it, one
    line before any solve."""
    problem = dataclasses.replace(make(), obstacles=(Sphere((0.0, 6.0), 4.5),))
    with pytest.raises(ValueError, match=r"^final positions \(at the initial angles; no shift "
                                         r"of the formation avoids the obstacles\): agent \d+ "
                                         r"lies inside obstacles\[0\]"):
        solve_formation(problem)


@pytest.mark.slow
def test_mixed_fleet_on_mpi_and_dask_is_bitwise_the_serial_result(tmp_path):
    """Norm thrust limits, the ball and a separation of 0.4 in the same rounds: serial,
    2 Dask workers and mpirun -n 2 agree bit for bit."""
    options = FormationOptions(min_separation=0.4)
    serial = solve_formation(make(limit="norm", obstacle=2.5), options=options)
    assert serial.status == "converged" and serial.separation_rounds >= 1
    with open_backend("dask", workers=2) as backend:
        dask = solve_formation(make(limit="norm", obstacle=2.5), backend, options)
    assert dask.total_cost == serial.total_cost
    np.testing.assert_array_equal(dask.trajectories, serial.trajectories)
    proc = run_cli("-m", "ocpar.formation", "--problem",
                   "ocpar.examples.formation_mixed_fleet:make", "--problem-arg", "limit=norm",
                   "--problem-arg", "obstacle=2.5", "--min-separation", "0.4", "--output",
                   str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    mpi = json.loads((tmp_path / "result.json").read_text())
    assert mpi["total_cost"] == serial.total_cost
    arrays = ocpar.load(tmp_path).dataset
    assert arrays["configuration"].values.tolist() == serial.trajectories.tolist()
    assert arrays["peak_thrust"].values == pytest.approx(serial.peak_thrust, rel=1e-15)
    assert mpi["min_obstacle_clearance"] == serial.obstacle_clearance.distance
    assert mpi["min_separation"] == serial.separation.distance


def test_a_path_constraint_the_starts_break_or_that_is_not_finite_is_refused():
    problem = make(limit=None)
    above = PathConstraint(lambda q: q[1], lower=0.5, upper=np.inf, name="above")
    with pytest.raises(ValueError, match=r"starts: agent 0 breaks shape\[0\].path_constraints"
                                         r"\[0\] \(above\) by 0.5"):
        problem.with_shapes(lambda s: dataclasses.replace(s, solver="sqpmethod",
                                                          path_constraints=(above,)))
    singular = PathConstraint(lambda v, u: ca.sumsqr(u) / ca.sumsqr(v), upper=1.0,
                              name="ratio")
    with pytest.raises(ValueError, match=r"path_constraints\[0\] \(ratio\): not finite"):
        problem.with_shapes(lambda s: dataclasses.replace(s, solver="sqpmethod",
                                                          path_constraints=(singular,)))


@pytest.mark.parametrize("intervals", [4, 5, 10, 11])
def test_dmoc_reaches_no_farther_than_the_continuous_bang_bang_move(intervals):
    """The formation's reach check assumes DMOC's rest-to-rest move under |u| ≤ a covers at
    most the continuous T² a / (4 m): 0.1 % less thrust is infeasible, 20 % more is not."""
    from ocpar.ocp import OcpTask, solve_tasks

    mass, duration, distance = 1.5, 2.0, 1.0
    least = 4 * mass * distance / duration**2
    for factor, feasible in ((0.999, False), (1.2, True)):
        a = factor * least
        shape = DmocShape(PointMass(dim=1, mass=mass), intervals, duration, solver="ipopt",
                          control_bounds=((-a, a),))
        solution = solve_tasks([OcpTask(shape, np.array([0.0, 0.0, distance, 0.0]))])[0]
        assert (solution.success and np.max(np.abs(solution.u)) <= a * (1 + 1e-9)) == feasible


def test_a_box_thrust_limit_that_cannot_reach_the_curve_is_refused():
    """The least thrust any formation needs, computed here by brute force over 200,000
    points of the circle (per agent the nearest point in the bang–bang sense,
    max_j 4 m |Δ_j| / T², then the worst agent): 1 % below it the problem is refused,
    naming the agent's control_bounds; at 1.001 times it the check lets it through. The same
    for a norm limit (the disc), naming its path constraint."""
    problem = make()
    theta = np.linspace(0, 2 * np.pi, 200_000, endpoint=False)
    points = problem.curve.points(theta)
    duration = problem.common_shape.duration
    masses = np.array([shape.model.mass for shape in problem.shapes])
    need = [np.min(np.max(4 * m * np.abs(points - start), axis=1)) / duration**2
            for m, start in zip(masses, problem.starts, strict=True)]
    least = max(need)
    with pytest.raises(ValueError, match=rf"^shape\[{int(np.argmax(need))}\]\.control_bounds: "
                       r"agent \d+ \(mass 1\.5\) cannot reach any point of the curve"):
        make(u_max=0.99 * least)
    make(u_max=1.001 * least)
    # a norm limit |u| ≤ a reaches the disc |Δ| ≤ T² a / (4 m) (DMOC's reach on N = 20
    # intervals equals the continuous bang–bang move's, tests/test_feasibility.py)
    need = [np.min(4 * m * np.linalg.norm(points - start, axis=1)) / duration**2
            for m, start in zip(masses, problem.starts, strict=True)]
    least = max(need)
    with pytest.raises(ValueError, match=rf"^shape\[{int(np.argmax(need))}\]\.path_constraints"
                       r"\[0\] \(thrust\): agent \d+ \(mass 1\.5\) cannot reach any point"):
        make(limit="norm", u_max=0.99 * least)
    make(limit="norm", u_max=1.001 * least)


def test_a_thrust_limit_written_with_norm_2_reaches_the_squared_forms_optimum():
    """The fleet's |u| ≤ 2.7 written ``ca.norm_2(u) <= 2.7`` (no derivative at u = 0, where
    the inner solves start) is compiled as |u|² ≤ 2.7², saying so once per shape: the run
    converges to the squared form's total cost to 1e-8 (measured: equal, 63.2995712603)."""
    squared = make(limit="norm")
    norm = PathConstraint(lambda u: ca.norm_2(u), upper=2.7, name="thrust")
    with pytest.warns(NormSquared, match="thrust"):
        written = dataclasses.replace(squared, shape=tuple(
            dataclasses.replace(s, path_constraints=(norm,)) for s in squared.shape))
    a, b = solve_formation(written), solve_formation(squared)
    assert a.status == b.status == "converged"
    assert a.total_cost == pytest.approx(b.total_cost, abs=1e-8)
    assert a.total_cost > 63.0311212078 + 0.1   # the limit binds (free: 63.0311)
