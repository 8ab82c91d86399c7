"""ODE agents (:class:`~ocpar.ocp.MsEndpointShape`) past an obstacle: unicycles whose free
paths cross a disc, kept out of it on the polyline through their RK4 sub-step states, against
one NLP of all agents with the same clearance rows written here (IPOPT, independent of the
package's code); the returned paths clear of the disc on a dense re-integration; an
infeasible start through phase 1 (the agents' elastic problems) equal to that NLP with the
acceleration bound; serial and mpirun -n 2 bit-identical."""

from __future__ import annotations

import dataclasses
import itertools

import casadi as ca
import numpy as np
import pytest
from conftest import computed, read_result, run_ocpar
from test_ode_agents import IPOPT, _rk4

from ocpar.examples.formation_unicycles import make
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.keep_out.obstacles import closest_obstacle, segment_clearance
from ocpar.formation.verify import checked_positions
from ocpar.ocp import MsEndpointShape, transcription
from ocpar.ocp.obstacles import HalfSpace, Sphere, segment_rows

AGENTS, DURATION, INTERVALS, STEPS = 4, 6.0, 20, 4
#: A disc the first agent's free path crosses (it passes x ≈ −1.4 at y ≈ −0.1).
CENTER, RADIUS = (-1.3, -0.5), 0.6


def obstacle_problem():
    """Four unicycles onto a circle past the disc, ``STEPS`` RK4 steps per interval."""
    problem = make(agents=AGENTS, duration=DURATION, intervals=INTERVALS)
    return dataclasses.replace(problem, shape=dataclasses.replace(problem.shape, steps=STEPS),
                               obstacles=(Sphere(CENTER, RADIUS),))


@pytest.fixture(scope="module")
def free_and_kept_out():
    free = make(agents=AGENTS, duration=DURATION, intervals=INTERVALS)
    problem = obstacle_problem()
    return free, solve_formation(free), problem, solve_formation(problem)


def _clearance_rows(points: list[ca.SX], disc=(CENTER, RADIUS)) -> list[ca.SX]:
    """|y*|² − 1 ≥ 0 per chord of the polyline ``points`` (positions), y* the chord's point
    nearest the centre of ``disc`` (centre, radius), scaled by its radius."""
    center, radius = disc
    rows = []
    for a, b in itertools.pairwise(points):
        ya, yb = (a - ca.DM(center)) / radius, (b - ca.DM(center)) / radius
        step = yb - ya
        s = ca.fmin(ca.fmax(-ca.dot(ya, step) / ca.dot(step, step), 0), 1)
        rows.append(ca.sumsqr(ya + s * step) - 1)
    return rows


def _agent(problem, i: int, end: ca.SX, duration: float | ca.SX = DURATION,
           disc=(CENTER, RADIUS)):
    """Agent i's part of an NLP over ``duration`` (a number or a variable): variables
    (x_1..x_N, u_0..u_{N−1}), their bounds (|a| ≤ the shape's bound), cost, equations (= 0:
    continuity by ``steps`` RK4 steps, the end position ``end`` and speed 0) and, with an
    obstacle, the clearance rows (≥ 0) of ``disc`` on the polyline through the RK4 sub-step
    states."""
    shape, h = problem.shapes[i], duration / INTERVALS
    xs = [ca.SX.sym(f"x{i}_{k}", 4) for k in range(INTERVALS)]
    us = [ca.SX.sym(f"u{i}_{k}", 2) for k in range(INTERVALS)]
    x, points = ca.DM(problem.starts[i]), [ca.DM(problem.starts[i][:2])]
    cost, equations = 0, []
    for k in range(INTERVALS):
        state = x
        for _ in range(shape.steps):
            state, c = _rk4(state, us[k], h / shape.steps)
            cost += c
            points.append(state[:2])
        equations.append(xs[k] - state)
        points[-1] = xs[k][:2]
        x = xs[k]
    equations += [x[:2] - end, x[3]]
    a = np.inf if shape.control_bounds is None else shape.control_bounds[0][1]
    lower = np.r_[np.full(4 * INTERVALS, -np.inf), np.tile([-a, -np.inf], INTERVALS)]
    upper = np.r_[np.full(4 * INTERVALS, np.inf), np.tile([a, np.inf], INTERVALS)]
    clear = _clearance_rows(points, disc) if problem.obstacles else []
    return xs + us, lower, upper, cost, equations, clear


def _ipopt(variables, lower, upper, cost, equations, clear, guess
           ) -> tuple[bool, float, np.ndarray]:
    """IPOPT on the NLP: (success, J*, the optimal variables)."""
    g = ca.vertcat(*equations, *clear)
    m = ca.vertcat(*equations).numel()
    solver = ca.nlpsol("reference", "ipopt", {"x": ca.vertcat(*variables), "f": cost, "g": g},
                       IPOPT)
    out = solver(x0=guess, lbx=lower, ubx=upper, lbg=np.zeros(g.numel()),
                 ubg=np.r_[np.zeros(m), np.full(g.numel() - m, np.inf)])
    return solver.stats()["success"], float(out["f"]), np.asarray(out["x"]).ravel()


def monolithic(problem, result) -> float:
    """All agents, the coupling (the potential's equidistant angles on the circle in the
    agents' order, rotation θ free), their bounds and (with the disc) their clearance rows
    in one IPOPT NLP, started at the run's answer; returns J*."""
    n, radius = problem.agents, problem.curve.radius
    rank = np.argsort(np.argsort(problem.starts[:, 0], kind="stable"))
    theta = ca.SX.sym("theta")
    phi = theta + 2 * np.pi * rank / n
    parts = [[theta], [-np.inf], [np.inf], 0, [], []]
    guess = [float(np.asarray(result.phi)[np.argmin(rank)])]
    for i in range(n):
        agent = _agent(problem, i, radius * ca.vertcat(ca.cos(phi[i]), ca.sin(phi[i])))
        for j in (0, 4, 5):
            parts[j] += agent[j]
        parts[1] = np.r_[parts[1], agent[1]]
        parts[2] = np.r_[parts[2], agent[2]]
        parts[3] += agent[3]
        guess += [result.trajectories[i, 1:].ravel(), result.controls[i].ravel()]
    success, value, _ = _ipopt(*parts, np.hstack([np.ravel(v) for v in guess]))
    assert success
    return value


def test_the_inner_derivatives_with_the_disc_binding_are_the_finite_differences():
    """One unicycle past a disc it must go round: dJ*/dx̄_N and the end Hessian (of the
    active set) against central differences; the batched sqpmethod solve is IPOPT's."""
    shape = MsEndpointShape(make(agents=2).shape.model, intervals=INTERVALS, duration=DURATION,
                            steps=STEPS, free_end=(2,), obstacles=(Sphere((-0.1, -0.5), 0.6),))
    inner = transcription(shape)
    params = np.array([0.0, -5.0, np.pi / 2, 0.0, 0.3, 2.5, 0.0, 0.0])
    solved = inner.solve(params)
    free = transcription(dataclasses.replace(shape, obstacles=(), obstacle_positions=())
                         ).solve(params)
    assert solved.success and solved.cost > free.cost + 0.05
    batch = inner.solve_batch(params[None], [None], [None])
    assert batch.column("success")[0]
    assert abs(batch.column("cost")[0] - solved.cost) <= 1e-10 * solved.cost
    for entry in (4, 5):
        step = np.zeros(8)
        step[entry] = 1e-5
        up, down = (inner.solve(params + sign * step, inner.warm_start(solved))
                    for sign in (1, -1))
        slope = (up.cost - down.cost) / 2e-5
        assert abs(solved.cost_gradient[entry] - slope) <= 1e-6 * (1 + abs(slope))
        column = (up.cost_gradient[4:6] - down.cost_gradient[4:6]) / 2e-5
        assert np.allclose(solved.end_hessian[entry - 4, :2], column, rtol=1e-5, atol=1e-6)


def test_both_sides_of_the_disc_are_tried_and_the_cheaper_kept():
    """A unicycle heading west at 0.5 whose straight-line guess passes the disc's east side:
    going round the west side is cheaper (4.28 against 6.27); the IPOPT and batched solves
    from the default guess both return the west side."""
    center = (-0.05, -1.0)
    shape = MsEndpointShape(make(agents=2).shape.model, intervals=INTERVALS, duration=DURATION,
                            steps=STEPS, free_end=(2,), obstacles=(Sphere(center, 1.0),))
    inner = transcription(shape)
    params = np.array([0.0, -5.0, np.pi, 0.5, 0.1, 3.0, 0.0, 0.0])
    east, west = (inner.solve(params, guess) for guess in inner.side_guesses(params[None])[0])
    assert east.success and west.success and west.cost < east.cost - 1.0

    def nearest_x(q: np.ndarray) -> float:
        return float(q[np.argmin(np.linalg.norm(q[:, :2] - center, axis=1)), 0])

    assert nearest_x(east.q) > center[0] > nearest_x(west.q)
    alone = inner.solve(params)
    batch = inner.solve_batch(np.stack([params, params]), [None, None], [None, None])
    for cost, q in ((alone.cost, alone.q), *zip(batch.column("cost"), batch.column("q"),
                                                strict=True)):
        assert abs(cost - west.cost) <= 1e-8 * west.cost and nearest_x(q) < center[0]


def test_a_wall_holds_at_every_sub_step_state():
    """A unicycle starting westward at speed 1 swings out to x = −1.0 on its free path; with
    the wall x ≥ −0.4 its RK4 sub-step states (the test's own integration of the returned
    controls from each node) keep x ≥ −0.4, the wall binds, and the cost rises."""
    wall = HalfSpace((1.0, 0.0), -0.4)
    shape = MsEndpointShape(make(agents=2).shape.model, intervals=INTERVALS, duration=DURATION,
                            steps=STEPS, free_end=(2,), obstacles=(wall,))
    params = np.array([0.5, -5.0, np.pi, 1.0, 0.3, 3.0, 0.0, 0.0])
    free = transcription(dataclasses.replace(shape, obstacles=(), obstacle_positions=())
                         ).solve(params)
    assert free.success and np.min(free.q[:, 0]) < -0.5
    walled = transcription(shape).solve(params)
    assert walled.success and walled.cost > free.cost
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    step = ca.Function("step", [x, u], [_rk4(x, u, DURATION / INTERVALS / STEPS)[0]])
    states = []
    for k in range(INTERVALS):
        state = walled.q[k]
        for _ in range(STEPS):
            state = np.asarray(step(state, walled.u[k])).ravel()
            states.append(state)
    lowest = min(float(s[0]) for s in states)
    assert -0.4 - 1e-9 <= lowest <= -0.4 + 1e-6


def test_the_free_paths_cross_the_disc(free_and_kept_out):
    free, result = free_and_kept_out[:2]
    assert result.status == "converged"
    gaps = segment_clearance(free.positions(result.trajectories), (Sphere(CENTER, RADIUS),))
    assert np.min(gaps) < -0.1


def test_unicycles_past_a_disc_equal_the_monolithic_nlp(free_and_kept_out):
    free_result, problem, result = free_and_kept_out[1:]
    assert result.status == "converged" and result.verification.passed, result.message
    assert result.total_cost > free_result.total_cost
    # clear on the dense re-integration (the verification's) and on an independent one
    assert result.obstacle_clearance.distance >= -1e-9
    dense = checked_positions(problem, result.trajectories, result.controls)
    assert dense.shape == (AGENTS, INTERVALS * STEPS * 8 + 1, 2)
    assert closest_obstacle(dense, problem.obstacles, DURATION).distance >= -1e-9
    assert np.min(_finely_integrated_clearance(problem, result)) >= -1e-9
    # the disc binds: some sub-step state lies on it
    assert result.obstacle_clearance.distance <= 1e-3
    value = monolithic(problem, result)
    assert abs(result.total_cost - value) <= 1e-8 * abs(value)
    # --mode monolithic: the package's one NLP of the agents' own transcriptions, the disc's
    # rows included, from each agent's inner optimum at the initial angles
    mono = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert mono.status == "converged" and mono.verification.passed, mono.message
    assert abs(mono.total_cost - value) <= 1e-8 * abs(value)
    assert mono.obstacle_clearance.distance >= -1e-9


def _finely_integrated_clearance(problem, result) -> np.ndarray:
    """Each agent's distance from the disc (length unit) at 64 points per interval, its
    controls integrated from its start node by 64 RK4 steps per interval (the test's RK4),
    all agents at once: (n, N 64)."""
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    states, state = [], x
    for _ in range(64):
        state = _rk4(state, u, DURATION / INTERVALS / 64)[0]
        states.append(state)
    interval = ca.Function("interval", [x, u], [ca.horzcat(*states)]).map(AGENTS)
    state, gaps = result.trajectories[:, 0].T, []
    for k in range(INTERVALS):
        points = np.asarray(interval(state, result.controls[:, k].T)).reshape(4, 64, AGENTS,
                                                                             order="F")
        gaps.append(np.linalg.norm(points[:2] - np.reshape(CENTER, (2, 1, 1)), axis=0)
                    - RADIUS)
        state = points[:, -1]
    return np.concatenate(gaps).T


def test_an_infeasible_start_goes_through_phase_one_and_equals_the_monolithic_nlp():
    """|a| ≤ 0.8 (the free optimum's peak is 1.2) with the formation turned by π at the start:
    some agent cannot reach its target there (the test's own NLP of it is infeasible), phase
    1 (the agents' elastic problems) finds a feasible rotation, phase 2 the optimum."""
    problem = make(agents=AGENTS, duration=DURATION, intervals=INTERVALS,
                   acceleration_limit=0.8)
    start = problem.initial_phi() + np.pi
    reachable = []
    for i in range(AGENTS):
        agent = _agent(problem, i, ca.DM(problem.curve.radius * np.array(
            [np.cos(start[i]), np.sin(start[i])])))
        guess = np.zeros(6 * INTERVALS)
        reachable.append(_ipopt(*agent, guess)[0])
    assert not all(reachable)
    result = solve_formation(problem, options=FormationOptions(initial_rotation=np.pi))
    assert result.status == "converged" and result.verification.passed, result.message
    assert "phase 1" in result.message
    value = monolithic(problem, result)
    assert abs(result.total_cost - value) <= 1e-8 * abs(value)
    assert np.max(np.abs(result.controls[..., 0])) <= 0.8 * (1 + 1e-9)


#: A disc on agent 0's path of the free per-agent T without obstacles (its midpoint, 0.1 on).
TIMED_DISC = ((-1.78, -2.33), 0.4)


def test_free_time_per_agent_past_a_disc_is_each_agents_nlp_with_t_a_variable():
    """Each agent its own T_i past a disc that binds: every T_i and J_i + w T_i equal to the
    agent's NLP written here with T a variable (the clearance rows on its RK4 sub-step
    polyline) at its returned end; the returned paths checked at their own T_i."""
    problem = dataclasses.replace(obstacle_problem(), obstacles=(Sphere(*TIMED_DISC),))
    weight, low, high = 1.0, 1.0, 50.0
    result = solve_formation(problem, options=FormationOptions(
        final_time="free_per_agent", time_bounds=(low, high), time_weight=weight))
    assert result.status == "converged" and result.verification.passed, result.message
    assert 0 <= result.obstacle_clearance.distance <= 1e-3   # the disc binds
    assert np.ptp(result.durations) > 0.5
    ends = problem.final_positions(result.phi)
    for i in range(AGENTS):
        t = ca.SX.sym("T")
        v, lo, hi, cost, equations, clear = _agent(problem, i, ca.DM(ends[i]), t, TIMED_DISC)
        guess = np.r_[result.trajectories[i, 1:].ravel(), result.controls[i].ravel(),
                      result.durations[i]]
        ok, value, x = _ipopt([*v, t], np.r_[lo, low], np.r_[hi, high], cost + weight * t,
                              equations, clear, guess)
        assert ok
        assert value == pytest.approx(result.agent_costs[i], rel=1e-8)
        assert x[-1] == pytest.approx(result.durations[i], rel=1e-6)


def test_a_chord_of_length_zero_has_finite_keep_out_derivatives():
    """A node that repeats (an ODE guess at rest: its sub-step states coincide): the keep-out
    row is the point's, and its gradient and Hessian are finite (they were NaN: IPOPT
    stopped at Invalid_Number_Detected, phase 1's elastic solves all failed)."""
    a, b = ca.SX.sym("a", 2), ca.SX.sym("b", 2)
    (row,) = segment_rows((Sphere(CENTER, RADIUS),), [a, b])
    at = [np.array([0.5, 0.2]), np.array([0.5, 0.2])]
    x = ca.vertcat(a, b)
    value, gradient, hessian = (np.asarray(ca.Function("f", [a, b], [e])(*at))
                                for e in (row, ca.gradient(row, x), ca.hessian(row, x)[0]))
    expected = np.sum((at[0] - CENTER) ** 2) / RADIUS**2 - 1
    assert value.item() == pytest.approx(expected, rel=1e-15)
    assert np.all(np.isfinite(gradient)) and np.all(np.isfinite(hessian))


def test_the_elastic_problem_s_gradient_is_the_finite_difference():
    """ds*/dx̄_N of an ODE agent's elastic problem (−λ_p) against central differences, where
    the end is out of reach under |a| ≤ 0.3 (s > 0)."""
    shape = make(agents=2, acceleration_limit=0.3).shape
    elastic = transcription(dataclasses.replace(shape, elastic=True, solver="ipopt"))
    params = np.array([0.0, -5.0, np.pi / 2, 0.0, 0.5, -2.0, 0.0, 0.0])
    solved = elastic.solve(params)
    assert solved.success and solved.cost > 1e-3
    assert not transcription(shape).solve(params).success
    for entry in (4, 5):
        step = np.zeros(8)
        step[entry] = 1e-5
        slope = (elastic.solve(params + step).cost - elastic.solve(params - step).cost) / 2e-5
        assert abs(solved.cost_gradient[entry] - slope) <= 1e-5 * (1 + abs(slope))


def test_obstacle_fields_are_checked_in_one_line():
    for kwargs, match in (({"obstacle_positions": (0, 1)}, "obstacle_positions needs"),
                          ({"obstacles": (Sphere((0, 0, 0), 1.0),)}, r"obstacles\[0\]"),
                          ({"obstacles": (Sphere((0, 0), 1.0),), "obstacle_positions": (0, 0)},
                           "obstacle_positions: must be distinct")):
        with pytest.raises(ValueError, match=match):
            MsEndpointShape(make(agents=2).shape.model, **kwargs)
    shape = MsEndpointShape(make(agents=2).shape.model,
                            obstacles=(HalfSpace((0.0, 1.0), -10.0),))
    assert shape.obstacle_positions == (0, 1) and shape.chosen_solver == "sqpmethod"


FACTORY = f"""\
import dataclasses
import itertools
from ocpar.examples.formation_unicycles import make as unicycles
from ocpar.formation.keep_out.obstacles import Sphere


def make():
    problem = unicycles(agents={AGENTS}, duration={DURATION}, intervals={INTERVALS})
    return dataclasses.replace(
        problem, shape=dataclasses.replace(problem.shape, steps={STEPS}),
        obstacles=(Sphere({CENTER}, {RADIUS}),))
"""


def test_mpirun_gives_the_serial_result_bitwise(tmp_path, free_and_kept_out):
    (tmp_path / "disc_unicycles.py").write_text(FACTORY)
    (tmp_path / "run.toml").write_text('scheme = "formation"\nproblem = '
                                       '"disc_unicycles:make"\nquiet = true\n')
    runs = {}
    for name, ranks in (("serial", None), ("mpi", 2)):
        proc = run_ocpar(tmp_path, tmp_path, "run", "run.toml", "--output",
                         str(tmp_path / name), mpi_ranks=ranks)
        assert proc.returncode == 0, proc.stderr
        runs[name] = read_result(tmp_path / name)
    assert runs["serial"]["status"] == "converged" and runs["mpi"]["workers"] == 2
    assert computed(runs["mpi"]) == computed(runs["serial"])
    assert runs["serial"]["total_cost"] == free_and_kept_out[3].total_cost
