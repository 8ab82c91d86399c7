"""Obstacles in the inner problems (``ocpar.ocp.obstacles``): every agent's DMOC NLP keeps
its continuous path out of each ball by one separating plane per interval, so that the outer
solver turns the formation for the obstacle. The asymmetric case is
``ocpar.examples.formation_obstacle``: six point masses onto a circle past a disc placed off
the problem's line of symmetry.
"""

from __future__ import annotations

import dataclasses
import json

import casadi as ca
import numpy as np
import pytest
from conftest import run_cli

import ocpar
from ocpar.bsp import open_backend
from ocpar.bsp.columns import LISTED, SHARED, STACKED
from ocpar.bsp.serial import SerialBackend
from ocpar.examples import formation_mixed_fleet
from ocpar.examples.formation_obstacle import make
from ocpar.formation import FormationOptions, Sphere, solve_formation
from ocpar.formation.hierarchical import OuterObjective
from ocpar.formation.solve import obstacle_check
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, OcpTask, dmoc_problem, solve_tasks
from ocpar.ocp.endpoint_agents import _from_previous, agent_tasks
from ocpar.ocp.obstacles import HalfSpace, plane_multipliers, segment_rows

CENTRE_2D, RADIUS = np.array([1.0, 3.0]), 0.8


@pytest.fixture(scope="module")
def free():
    return solve_formation(make(obstacle=None))


@pytest.fixture(scope="module")
def hierarchical():
    return solve_formation(make())


def segment_distances(nodes: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Distance (n, N) of each segment [q_k, q_{k+1}] of paths with nodes (n, N+1, d) from
    the point ``centre``, in closed form: the foot of the perpendicular clipped to the
    segment."""
    a, b = nodes[:, :-1], nodes[:, 1:]
    step = b - a
    s = np.clip(np.sum((centre - a) * step, axis=-1) / np.sum(step * step, axis=-1), 0, 1)
    return np.linalg.norm(a + s[..., None] * step - centre, axis=-1)


def offset(phi: np.ndarray) -> float:
    """The common offset of angles φ (n,) on the circle, mod 2π/n (rad)."""
    n = len(phi)
    return float(np.angle(np.mean(np.exp(1j * n * np.asarray(phi)))) / n)


def independent_cost(start: np.ndarray, end: np.ndarray, centre: np.ndarray, radius: float,
                     side: str, intervals: int = 10, duration: float = 1.0) -> float:
    """A unit point mass's DMOC optimum from ``start`` to ``end`` at rest, written here: the
    discrete Euler–Lagrange equations of L_d(a, b) = |b − a|²/(2h) with forces (h/2) u_k,
    cost h Σ|u_k|², and the segments kept out of the disc by a plane n_k per interval,
    |n_k|² ≤ 1, n_k·(q − c) ≥ r at both ends. Started on ``side`` (2-D: the centre on the
    agent's left or right): straight path pushed away from the centre, planes that way."""
    h, n = duration / intervals, intervals
    inner = ca.SX.sym("q", n - 1, 2)
    u = ca.SX.sym("u", n, 2)
    planes = ca.SX.sym("n", n, 2)
    nodes = [ca.DM(start).T] + [inner[k, :] for k in range(n - 1)] + [ca.DM(end).T]
    eqs = [-(nodes[1] - nodes[0]) / h + h / 2 * u[0, :]]
    eqs += [(nodes[k] - nodes[k - 1]) / h - (nodes[k + 1] - nodes[k]) / h
            + h / 2 * (u[k - 1, :] + u[k, :]) for k in range(1, n)]
    eqs.append((nodes[n] - nodes[n - 1]) / h + h / 2 * u[n - 1, :])
    keep = []
    for k in range(n):
        keep += [1 - ca.sumsqr(planes[k, :])] + [
            ca.dot(planes[k, :], nodes[j] - ca.DM(centre).T) - radius for j in (k, k + 1)]
    x = ca.vertcat(ca.vec(inner), ca.vec(u), ca.vec(planes))
    g = ca.vertcat(*[e.T for e in eqs], *keep)
    chord = end - start
    left = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
    away = -left if side == "left" else left   # centre on the left: the agent passes right
    s = np.arange(1, n)[:, None] / n
    path = start + s * chord + 1.5 * radius * np.sin(np.pi * s) * away
    x0 = np.concatenate([path.ravel(order="F"), np.zeros(2 * n),
                         np.tile(away, (n, 1)).ravel(order="F")])
    solver = ca.nlpsol("independent", "ipopt", {"x": x, "f": h * ca.sumsqr(u), "g": g},
                       {"ipopt.tol": 1e-12, "ipopt.print_level": 0, "print_time": False,
                        "ipopt.bound_relax_factor": 0.0})
    n_eq = 2 * (n + 1)
    out = solver(x0=x0, lbg=np.zeros(g.numel()),
                 ubg=np.concatenate([np.zeros(n_eq), np.full(3 * n, np.inf)]))
    assert solver.stats()["success"]
    return float(out["f"])


def test_the_disc_turns_the_formation_and_hierarchical_equals_monolithic(free, hierarchical):
    """The disc moves the best rotation by −0.383 rad (cost 2830.303 → 2859.206); the
    hierarchical scheme equals the monolithic NLP with the same planes to 1e-8 in cost and
    1e-6 in rotation; every returned segment keeps the disc's radius (closed-form distance
    here); agents 0–3 pass it with its centre on their right, 4 and 5 on their left."""
    result = hierarchical
    assert result.status == "converged", result.message
    assert offset(result.phi) - offset(free.phi) == pytest.approx(-0.38316, abs=1e-4)
    assert result.total_cost == pytest.approx(2859.2063, abs=1e-3)
    assert free.total_cost == pytest.approx(2830.3030, abs=1e-3)
    monolithic = solve_formation(make(), options=FormationOptions(mode="monolithic"))
    assert monolithic.status == "converged", monolithic.message
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert abs(offset(result.phi) - offset(monolithic.phi)) <= 1e-6
    assert result.obstacle_sides == [["right"]] * 4 + [["left"]] * 2
    assert monolithic.obstacle_sides == result.obstacle_sides
    for run in (result, monolithic):
        gaps = segment_distances(run.trajectories, CENTRE_2D)
        assert gaps.min() >= RADIUS - 1e-9
        assert run.obstacle_clearance.distance == pytest.approx(gaps.min() - RADIUS, abs=1e-12)
    # the disc binds: the free paths cross it, the returned ones touch it
    assert segment_distances(free.trajectories, CENTRE_2D).min() < RADIUS - 0.3
    assert segment_distances(result.trajectories, CENTRE_2D).min() <= RADIUS + 1e-9
    fields = result.scheme_fields()
    assert result.arrays()["obstacle_side"][1][:, 0].tolist() == [-1] * 4 + [1] * 2
    assert fields["min_obstacle_clearance"] == result.obstacle_clearance.distance


def test_each_agent_cost_is_an_independent_nlps_at_its_target(hierarchical):
    """Each agent's cost at the optimum equals that of a DMOC NLP with planes written in this
    test (IPOPT), from its start to its returned target, on its reported side, to 1e-9."""
    problem = make()
    targets = problem.final_positions(hierarchical.phi)
    for i, (start, end) in enumerate(zip(problem.starts, targets, strict=True)):
        cost = independent_cost(start, end, CENTRE_2D, RADIUS, hierarchical.obstacle_sides[i][0])
        assert hierarchical.agent_costs[i] == pytest.approx(cost, rel=1e-9, abs=0), i


def test_outer_gradient_and_hessian_with_an_active_obstacle_match_finite_differences(
        hierarchical):
    """dĴ_i/dφ_i and d²Ĵ_i/dφ_i² from the inner sensitivities (the planes' active set) at the
    optimum, where the disc binds agent 3's path, against central differences of the
    agents' own costs and gradients (Ĵ_i depends on φ_i alone)."""
    problem = make()
    phi = hierarchical.phi
    objective = OuterObjective(problem, SerialBackend())
    gradient, hessian = objective.gradient(phi), objective.hessian_diagonal(phi)
    gaps = segment_distances(hierarchical.trajectories, CENTRE_2D).min(axis=1) - RADIUS
    assert gaps[3] <= 1e-9 and gaps[0] > 0.1   # agent 3 touches the disc, agent 0 is clear
    eps = 1e-4
    costs, slopes = [], []
    for sign in (1, -1):
        costs.append(np.asarray(objective.outcomes(phi + sign * eps).column("cost")))
        slopes.append(objective.gradient(phi + sign * eps))
    np.testing.assert_allclose(gradient, (costs[0] - costs[1]) / (2 * eps), rtol=1e-6)
    np.testing.assert_allclose(hessian, (slopes[0] - slopes[1]) / (2 * eps), rtol=1e-5)
    objective.close()


def test_a_ball_in_3d_turns_the_tilted_formation():
    """Point masses in space onto a circle tilted by 0.3 rad, past a ball: hierarchical =
    monolithic (cost 1e-8, rotation 1e-6), every segment at least the radius from the centre
    (closed form), the rotation moved by −0.347 rad; each side a unit vector."""
    problem = make(dim=3)
    result = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    free = solve_formation(make(dim=3, obstacle=None))
    assert result.status == monolithic.status == "converged", result.message
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert abs(offset(result.phi) - offset(monolithic.phi)) <= 1e-6
    assert offset(result.phi) - offset(free.phi) == pytest.approx(-0.34695, abs=1e-4)
    gaps = segment_distances(result.trajectories, np.array([1.0, 3.0, 0.2]))
    assert RADIUS - 1e-9 <= gaps.min() <= RADIUS + 1e-9
    for (side,) in result.obstacle_sides:
        assert len(side) == 3 and np.linalg.norm(side) == pytest.approx(1.0, rel=1e-12)


def test_the_ordering_is_chosen_with_the_obstacle():
    """``--ordering optimal`` builds its cost tables with the disc: its formation is cheaper
    than the default order's and than the obstacle-free optimal order's, solved with the
    disc (measured 2786.447 against 2859.206 and 2791.586)."""
    problem = make()
    chosen = solve_formation(problem, options=FormationOptions(ordering="optimal"))
    free_order = solve_formation(make(obstacle=None), options=FormationOptions(ordering="optimal"))
    blind = solve_formation(problem, phi0=free_order.phi)
    keep = solve_formation(problem)
    assert chosen.status == blind.status == "converged", chosen.message
    assert chosen.total_cost < blind.total_cost - 5 and chosen.total_cost < keep.total_cost - 70
    assert segment_distances(chosen.trajectories, CENTRE_2D).min() >= RADIUS - 1e-9


def test_a_target_inside_an_obstacle_starts_the_formation_elsewhere(hierarchical):
    """A buoy (radius 0.3) over agent 2's target at the initial angles (its centre 0.05 rad
    on): the run starts from the nearest rotation whose targets clear it by 10 % of its
    radius (−0.1166 rad) and reaches the disc's optimum, which clears it; a ball over the
    whole circle (no rotation avoids it) is one line naming the obstacles."""
    problem = make()
    phi = problem.initial_phi()
    target = problem.final_positions(phi + 0.05)[2]
    with_buoy = dataclasses.replace(
        problem, obstacles=(*problem.obstacles, Sphere(tuple(target), 0.3, "buoy")))
    start = with_buoy.clear_start(phi)
    np.testing.assert_allclose(start - phi, -0.11658, atol=1e-5)
    assert np.linalg.norm(with_buoy.final_positions(start) - target, axis=1).min() >= 0.33
    result = solve_formation(with_buoy)
    assert result.status == "converged", result.message
    assert result.total_cost == pytest.approx(hierarchical.total_cost, rel=1e-12)
    assert segment_distances(result.trajectories, target).min() >= 0.3
    everywhere = dataclasses.replace(problem, obstacles=(Sphere((0.0, 6.0), 2.5, "cloud"),))
    with pytest.raises(ValueError, match=r"^final positions .*no shift of the formation avoids "
                                         r"the obstacles\): agent 0 lies inside obstacles\[0\]"):
        solve_formation(everywhere)


def test_a_returned_path_inside_an_obstacle_is_not_converged(free):
    """The verification reads the returned paths alone: the obstacle-free paths, checked
    against the disc, are ``obstacles_not_cleared`` with where and by how much."""
    problem = make()
    status, message, fields = obstacle_check(problem, free.trajectories, "converged", "ok")
    depth = RADIUS - segment_distances(free.trajectories, CENTRE_2D).min()
    c = fields["obstacle_clearance"]
    assert status == "obstacles_not_cleared" and c.distance == pytest.approx(-depth, abs=1e-12)
    assert message.startswith(f"obstacles not cleared: agent {c.agent} comes {depth:.3g} inside")


@pytest.mark.parametrize("solver", ["ipopt", "sqpmethod"])
def test_the_inner_solve_keeps_the_cheaper_side(solver):
    """A disc just above the straight path from (0, 0) to (1, 0): the solve from the default
    guess tries both sides and keeps the cheaper, below it, whose cost is the smaller of the
    independent NLP's from either side (to 1e-9). A warm start below it (the straight path's
    side) is solved from alone; one above it (the far side) with both sides too, so the
    cheaper side still wins. Both the one-task solver and the batch (``sqpmethod``'s mapped
    call)."""
    centre, radius = np.array([0.5, 0.1]), 0.3
    shape = DmocShape(PointMass(2), intervals=10, duration=1.0, solver=solver,
                      obstacles=(Sphere(tuple(centre), radius),))
    params = np.array([0.0, 0, 0, 0, 1, 0, 0, 0])
    sides = {side: independent_cost(np.zeros(2), np.array([1.0, 0.0]), centre, radius, side)
             for side in ("left", "right")}
    assert sides["left"] < sides["right"] - 1   # centre on the left: the agent passes below
    nlp = dmoc_problem(shape)
    one = nlp.solve(params)
    (batch,) = solve_tasks([OcpTask(shape, params)])
    for solution in (one, batch):
        assert solution.success and solution.cost == pytest.approx(sides["left"], rel=1e-9)
        assert solution.q[1:-1, 1].max() < 0
    arc = 0.5 * np.sin(np.linspace(0, np.pi, 11))
    for sign, count in ((-1, 1), (1, 3)):   # below: the guess alone; above: and both sides
        path = np.column_stack([np.linspace(0, 1, 11), sign * arc])
        warm = np.concatenate([path[1:-1].ravel(), np.zeros(20)])
        starts = nlp.start_guesses(warm, lambda: nlp.default_guess(params), params)
        assert len(starts) == count
        np.testing.assert_array_equal(starts[0, :38], warm)
        kept = nlp.solve(params, warm)
        (batch,) = solve_tasks([OcpTask(shape, params, warm_start=warm)])
        for solution in (kept, batch):
            assert solution.success and solution.cost == pytest.approx(sides["left"], rel=1e-9)
            assert solution.q[1:-1, 1].max() < 0
            assert segment_distances(solution.q[None], centre).min() >= radius - 1e-9


@pytest.mark.parametrize(("solver", "dim"), [("ipopt", 2), ("ipopt", 3), ("sqpmethod", 2),
                                             ("sqpmethod", 3)])
def test_end_gradient_and_hessian_with_a_binding_ball_match_finite_differences(solver, dim):
    """One point mass past a ball its straight path crosses: dJ*/dq_N (multipliers) and
    d²J*/dq_N² (the planes' active set) against central differences of J* and of dJ*/dq_N,
    by ``solve_tasks`` (``sqpmethod``: the mapped batch on the segment rows, lifted to the
    planes; no IPOPT: ``iterations`` −1, one attempt) and by one IPOPT solve."""
    centre = np.array([0.5, 0.1, 0.05][:dim])
    shape = DmocShape(PointMass(dim), intervals=10, duration=1.0, solver=solver,
                      obstacles=(Sphere(tuple(centre), 0.3),))
    end = np.array([1.0, 0.0, 0.1][:dim])

    def solve(q_end: np.ndarray):
        params = np.concatenate([np.zeros(2 * dim), q_end, np.zeros(dim)])
        (solution,) = solve_tasks([OcpTask(shape, params)])
        assert solution.success
        if solver == "sqpmethod":
            assert (solution.attempts, solution.iterations) == (1, -1)
        return solution

    base = solve(end)
    assert segment_distances(base.q[None], centre).min() == pytest.approx(0.3, abs=1e-9)
    gradient, hessian = base.cost_gradient[2 * dim:3 * dim], base.end_hessian
    alone = dmoc_problem(shape).solve(np.concatenate([np.zeros(2 * dim), end, np.zeros(dim)]))
    np.testing.assert_allclose(alone.end_hessian, hessian, rtol=1e-7, atol=1e-7)
    eps = 1e-5
    for j in range(dim):
        step = np.eye(dim)[j] * eps
        up, down = solve(end + step), solve(end - step)
        assert gradient[j] == pytest.approx((up.cost - down.cost) / (2 * eps), rel=1e-6)
        np.testing.assert_allclose(
            hessian[:, j], (up.cost_gradient - down.cost_gradient)[2 * dim:3 * dim] / (2 * eps),
            rtol=1e-5, atol=1e-5 * np.abs(hessian).max())


def test_segment_rows_are_the_squared_segment_distance_less_one():
    """The keep-out without planes (``segment_rows``, what the batches solve) on random
    segments about a ball of radius 0.8: |y*|² − 1 in the ball's scaled coordinates equals
    (distance / r)² − 1 from the closed-form segment distance, segments through the ball
    included (negative), and its plane multipliers λ (1, 2(1 − s), 2s) make the planes'
    ∂L/∂n vanish at the canonical plane n = y*/|y*| of a touching segment."""
    rng = np.random.default_rng(3)
    centre, radius = np.array([1.0, 3.0, 0.2]), 0.8
    ball = Sphere(tuple(centre), radius)
    a, b = ca.SX.sym("a", 3), ca.SX.sym("b", 3)
    (row,) = segment_rows((ball,), [a, b])
    f = ca.Function("row", [a, b], [row])
    starts, ends = centre + rng.normal(size=(40, 3)), centre + rng.normal(size=(40, 3))
    got = np.array([float(f(x, y)) for x, y in zip(starts, ends, strict=True)])
    want = (segment_distances(np.stack([starts, ends], axis=1), centre)[:, 0] / radius)**2 - 1
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert (want < 0).any() and (want > 0).any()
    # a segment touching the ball at its interior point s = 0.25
    normal, along = np.array([0.0, 0.6, 0.8]), np.array([1.0, 0.0, 0.0])
    ya, yb = normal - 0.25 * along, normal + 0.75 * along
    path = centre + radius * np.stack([ya, yb])[None]
    (lam_plane,) = plane_multipliers((ball,), path, np.array([[-2.0]]))
    assert lam_plane == pytest.approx([-2.0, -2 * 2 * 0.75, -2 * 2 * 0.25])
    grad_n = -2 * lam_plane[0] * normal + lam_plane[1] * ya + lam_plane[2] * yb
    np.testing.assert_allclose(grad_n, 0.0, atol=1e-12)


@pytest.fixture(scope="module")
def fleet_3d():
    """The mixed fleet in space past its ball (``formation_mixed_fleet.make(dim=3)``, no
    thrust limit), solved by each shape's own (batched) solver and by IPOPT."""
    problem = formation_mixed_fleet.make(limit=None, obstacle=2.5, dim=3)
    return problem, {solver: solve_formation(problem, options=FormationOptions(
        inner_solver=solver)) for solver in (None, "ipopt")}


def test_the_3d_fleet_past_its_ball_is_solved_in_batches_as_ipopt_solves_it(fleet_3d):
    """The 3-D fleet past its ball: the batched run (tasks whose unconstrained path clears
    the ball keep it; the others by the mapped sqpmethod on the segment rows) reaches IPOPT's
    formation (cost to 1e-9 relative, angles to 1e-7), every continuous path clears the ball
    (closed-form segment distances) and it binds; at the optimum every inner solution equals
    IPOPT's (cost, dJ*/dp, d²J*/dq_N²), none of them by IPOPT (one attempt, no IPOPT
    iterations: −1 from the mapped sqpmethod, 1 Newton step), and so are the run's own
    (warm-started) agents' costs."""
    problem, results = fleet_3d
    batched, ipopt = results[None], results["ipopt"]
    assert batched.status == ipopt.status == "converged", batched.message
    assert batched.total_cost == pytest.approx(ipopt.total_cost, rel=1e-9)
    np.testing.assert_allclose(batched.phi, ipopt.phi, atol=1e-7)
    (ball,) = problem.obstacles
    gaps = segment_distances(batched.trajectories, np.array(ball.center)) - ball.semi_axes[0]
    assert -1e-9 <= gaps.min() <= 1e-9
    binding = np.flatnonzero(gaps.min(axis=1) <= 1e-9)
    assert len(binding) >= 2
    tasks = problem.tasks(batched.phi).items()
    mine = solve_tasks(tasks)
    theirs = solve_tasks([dataclasses.replace(t, shape=dataclasses.replace(
        t.shape, solver="ipopt")) for t in tasks])
    for a, b in zip(mine, theirs, strict=True):
        assert a.success and a.attempts == 1 and a.iterations in (-1, 1)
        assert a.cost == pytest.approx(b.cost, rel=1e-9)
        np.testing.assert_allclose(a.cost_gradient, b.cost_gradient, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(a.end_hessian, b.end_hessian, rtol=1e-5, atol=1e-7)
    assert {mine[i].iterations for i in binding} == {-1}
    # the run's agents re-solved from their previous paths and sides (the far side tried in
    # their first solve only): their last costs are the cold solves' from both sides
    np.testing.assert_allclose(batched.agent_costs, [b.cost for b in theirs], rtol=1e-9)


def test_without_obstacles_the_nlp_is_the_one_of_old():
    """No planes, no rows: a point mass's NLP is the N−1 inner nodes, the N controls and the
    DMOC equations alone."""
    nlp = dmoc_problem(DmocShape(PointMass(2), intervals=10))
    assert (nlp.nw, nlp.ng, nlp.n_planes, nlp.n_rows) == (2 * 9 + 2 * 10, 2 * 11, 0, 0)
    with_disc = dmoc_problem(DmocShape(PointMass(2), intervals=10, solver="ipopt",
                                       obstacles=(Sphere((1.0, 3.0), 0.8),)))
    assert (with_disc.nw, with_disc.ng) == (nlp.nw + 2 * 10, nlp.ng + 3 * 10)
    with pytest.raises(ValueError, match=r"^solver: obstacles are inequalities"):
        DmocShape(PointMass(2), solver="newton", obstacles=(Sphere((1.0, 3.0), 0.8),))


def test_serial_mpi_and_dask_agree_bit_for_bit(tmp_path, hierarchical):
    """The asymmetric case on 2 Dask workers and on ``mpirun -n 2``: the serial result, bit
    for bit (sides included)."""
    with open_backend("dask", workers=2) as backend:
        dask = solve_formation(make(), backend)
    assert dask.total_cost == hierarchical.total_cost
    np.testing.assert_array_equal(dask.phi, hierarchical.phi)
    np.testing.assert_array_equal(dask.trajectories, hierarchical.trajectories)
    proc = run_cli("-m", "ocpar.formation", "--problem", "ocpar.examples.formation_obstacle:make",
                   "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    mpi = json.loads((tmp_path / "result.json").read_text())
    assert mpi["status"] == "converged"
    assert mpi["total_cost"] == hierarchical.total_cost
    assert mpi["phi"] == hierarchical.phi.tolist()
    arrays = ocpar.load(tmp_path).dataset
    assert arrays["configuration"].values.tolist() == hierarchical.trajectories.tolist()
    sides = {1: "left", -1: "right", 0: None}
    assert [[sides[int(s)] for s in row] for row in arrays["obstacle_side"].values] == \
        hierarchical.obstacle_sides


def test_only_agents_with_ellipsoids_re_solve_from_their_previous_solution():
    """An agent's inner task starts from its previous solution where its shape has an
    ellipsoid (and that solution is finite); elsewhere from the default guess with the
    previous solution as its fallback, as without obstacles of old."""
    plain = DmocShape(PointMass(2), intervals=10)
    ball = DmocShape(PointMass(2), intervals=10, obstacles=(Sphere((1.0, 3.0), 0.8),))
    wall = DmocShape(PointMass(2), intervals=10, obstacles=(HalfSpace((0.0, 1.0), -5.0),))
    assert (plain.resolves_from_previous, ball.resolves_from_previous,
            wall.resolves_from_previous) == (False, True, False)
    previous = np.arange(12.0).reshape(3, 4)
    previous[2, 1] = np.nan
    fallback = (STACKED, previous)

    def columns(*shapes):
        return agent_tasks(shapes[0] if len(shapes) == 1 else list(shapes), 2,
                           end=np.zeros((3, 2)))

    assert _from_previous(columns(plain), previous, fallback) == ((SHARED, None), fallback)
    warm, back = _from_previous(columns(ball, plain, ball), previous, fallback)
    assert warm[0] == back[0] == LISTED
    assert [None if w is None else w.tolist() for w in warm[1]] == [
        previous[0].tolist(), None, None]   # the third agent's previous solve failed
    assert [b is None for b in back[1]] == [True, False, False]


def test_the_far_side_bound_is_the_least_cost_of_reaching_the_far_half_plane():
    """The bound that skips the far side: for the disc just above the straight path from
    (0, 0) to (1, 0), every path with a node at y ≥ 0.4 (the far half-plane d·(q − c) ≤ −r,
    d = (0, −1)) costs at least the least over the inner nodes k of the unconstrained DMOC
    optimum with q_k,y ≥ 0.4, each written and solved here by IPOPT; the bound equals it
    (1e-8), lies below the far side's optimum and above the near side's, so the batch solves
    the near side alone and still returns the cheaper side."""
    centre, radius, n, h = np.array([0.5, 0.1]), 0.3, 10, 0.1
    shape = DmocShape(PointMass(2), intervals=n, duration=1.0, solver="sqpmethod",
                      obstacles=(Sphere(tuple(centre), radius),))
    params = np.array([0.0, 0, 0, 0, 1, 0, 0, 0])
    nlp = dmoc_problem(shape)
    (bound,) = nlp._far_bounds(params[None], [((0, np.array([0.0, -1.0])),)])
    inner, u = ca.SX.sym("q", n - 1, 2), ca.SX.sym("u", n, 2)
    nodes = [ca.DM([[0.0, 0.0]])] + [inner[k, :] for k in range(n - 1)] + [ca.DM([[1.0, 0.0]])]
    eqs = [-(nodes[1] - nodes[0]) / h + h / 2 * u[0, :]]
    eqs += [(nodes[k] - nodes[k - 1]) / h - (nodes[k + 1] - nodes[k]) / h
            + h / 2 * (u[k - 1, :] + u[k, :]) for k in range(1, n)]
    eqs.append((nodes[n] - nodes[n - 1]) / h + h / 2 * u[n - 1, :])
    x = ca.vertcat(ca.vec(inner), ca.vec(u))
    least = np.inf
    for k in range(n - 1):
        g = ca.vertcat(*[e.T for e in eqs], inner[k, 1])
        solver = ca.nlpsol("reach", "ipopt", {"x": x, "f": h * ca.sumsqr(u), "g": g},
                           {"ipopt.tol": 1e-12, "ipopt.print_level": 0, "print_time": False,
                            "ipopt.bound_relax_factor": 0.0})
        out = solver(x0=np.zeros(x.numel()), lbg=np.r_[np.zeros(2 * (n + 1)), 0.4],
                     ubg=np.r_[np.zeros(2 * (n + 1)), np.inf])
        least = min(least, float(out["f"]))
    assert bound == pytest.approx(least, rel=1e-8)
    sides = {side: independent_cost(np.zeros(2), np.array([1.0, 0.0]), centre, radius, side)
             for side in ("left", "right")}
    assert sides["left"] < bound <= sides["right"]
    (solution,) = solve_tasks([OcpTask(shape, params)])
    assert solution.success and solution.cost == pytest.approx(sides["left"], rel=1e-9)
