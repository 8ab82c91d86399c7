"""A feasible formation whenever one exists (issue 34, item 1): thrust-limited fleets whose
default start lies outside the window of rotations where every agent can reach its target.

References are computed here, outside ocpar's code path: the DMOC equations of a point mass
written out by hand (an LP with scipy, an NLP with CasADi/IPOPT)."""

from __future__ import annotations

import json
import re

import casadi as ca
import numpy as np
import pytest
from conftest import assert_no_sentinel
from feasibility_problems import DURATION, INTERVALS, build, fleet, free_peak, masses
from scipy.optimize import linprog

from ocpar.__main__ import main as ocpar_main
from ocpar.bsp.serial import SerialBackend
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.ordering import cost_table, pair_costs, slot_base
from ocpar.models import PointMass
from ocpar.ocp import DmocShape
from ocpar.ocp.constraints import PathConstraint
from ocpar.ocp.reach import rest_to_rest_reach
from ocpar.result_files import write_result

H = DURATION / INTERVALS
CENTRE, RADIUS = np.array([0.0, 6.0]), 4.0


def dmoc_rows(mass: float, q: list, u: list, h: float) -> list:
    """The DMOC equations of a point mass at rest at both ends, by hand: midpoint
    L_d(a, b) = m (b − a)² / (2h), forces (h/2) u_k on both sides of interval k:
    −m(q_1 − q_0)/h + (h/2)u_0 = 0; m(q_k − q_{k−1})/h − m(q_{k+1} − q_k)/h
    + (h/2)(u_{k−1} + u_k) = 0; m(q_N − q_{N−1})/h + (h/2)u_{N−1} = 0."""
    n = len(u)
    rows = [-mass * (q[1] - q[0]) / h + h / 2 * u[0]]
    rows += [mass * (q[k] - q[k - 1]) / h - mass * (q[k + 1] - q[k]) / h
             + h / 2 * (u[k - 1] + u[k]) for k in range(1, n)]
    rows.append(mass * (q[n] - q[n - 1]) / h + h / 2 * u[n - 1])
    return rows


def lp_reach(mass: float, intervals: int, duration: float, lo: float, hi: float
             ) -> tuple[float, float]:
    """(min, max) of q_N − q_0 under lo ≤ u_k ≤ hi: the LP of :func:`dmoc_rows`, variables
    q_1..q_N, u_0..u_{N−1} (q_0 = 0)."""
    n, h = intervals, duration / intervals
    size = 2 * n
    a_eq = np.zeros((n + 1, size))
    # column j < n: q_{j+1}; column n + k: u_k
    def put(row, node, value):
        if node > 0:
            a_eq[row, node - 1] += value
    for k in range(n + 1):
        if k == 0:
            put(0, 1, -mass / h)
            a_eq[0, n] += h / 2
        elif k < n:
            put(k, k, 2 * mass / h)
            put(k, k - 1, -mass / h)
            put(k, k + 1, -mass / h)
            a_eq[k, n + k - 1] += h / 2
            a_eq[k, n + k] += h / 2
        else:
            put(n, n, mass / h)
            put(n, n - 1, -mass / h)
            a_eq[n, 2 * n - 1] += h / 2
    bounds = [(None, None)] * n + [(lo, hi)] * n
    ends = []
    for sign in (1.0, -1.0):
        cost = np.zeros(size)
        cost[n - 1] = sign
        ends.append(linprog(cost, A_eq=a_eq, b_eq=np.zeros(n + 1), bounds=bounds).x[n - 1])
    return ends[0], ends[1]


@pytest.mark.parametrize(("mass", "intervals", "duration", "lo", "hi"),
                         [(1.3, 5, 2.0, -1.0, 2.5), (2.1, 20, 5.0, -0.7, 0.7),
                          (0.8, 7, 1.5, -3.0, 0.4)])
def test_box_reach_equals_an_lp_on_the_dmoc_equations_written_here(mass, intervals, duration,
                                                                   lo, hi):
    """Asymmetric bounds, odd N: ocpar's reach (an LP on its transcription) equals the LP on
    the equations by hand, per axis, to 1e-9."""
    shape = DmocShape(PointMass(dim=2, mass=mass), intervals, duration, solver="sqpmethod",
                      control_bounds=((lo, hi), (-hi, -lo)))
    reach = rest_to_rest_reach(shape)
    low, high = lp_reach(mass, intervals, duration, lo, hi)
    assert reach.radius is None
    np.testing.assert_allclose([reach.lower[0], reach.upper[0]], [low, high], rtol=1e-9)
    np.testing.assert_allclose([reach.lower[1], reach.upper[1]], [-high, -low], rtol=1e-9)


def test_norm_reach_is_the_disc_of_the_one_axis_reach_checked_by_ipopt():
    """|u_k| ≤ a: the farthest move along a diagonal, by IPOPT on the hand-written equations
    with the norm limit, is the disc's radius (the one-axis LP's reach), to 1e-7."""
    mass, n, duration, a = 1.4, 9, 3.0, 0.9
    limit = PathConstraint(lambda u: 2 * ca.sumsqr(u), upper=2 * a**2, name="thrust")
    shape = DmocShape(PointMass(dim=2, mass=mass), n, duration, solver="sqpmethod",
                      path_constraints=(limit,))
    reach = rest_to_rest_reach(shape)
    assert reach.radius == pytest.approx(lp_reach(mass, n, duration, -a, a)[1], rel=1e-12)
    h = duration / n
    q = [ca.DM.zeros(2)] + [ca.SX.sym(f"q{k}", 2) for k in range(1, n + 1)]
    u = [ca.SX.sym(f"u{k}", 2) for k in range(n)]
    direction = np.array([0.6, 0.8])
    rows = ca.vertcat(*dmoc_rows(mass, q, u, h), *[ca.sumsqr(uk) for uk in u])
    x = ca.vertcat(*q[1:], *u)
    solver = ca.nlpsol("reach", "ipopt", {"x": x, "f": -ca.dot(direction, q[n]), "g": rows},
                       {"print_time": False, "ipopt": {"print_level": 0, "tol": 1e-12}})
    n_eq = 2 * (n + 1)
    out = solver(x0=np.zeros(x.numel()), lbg=np.r_[np.zeros(n_eq), np.zeros(n)],
                 ubg=np.r_[np.zeros(n_eq), np.full(n, a**2)])
    assert solver.stats()["success"]
    assert -float(out["f"]) == pytest.approx(reach.radius, rel=1e-7)


def reference_formation(problem, order: np.ndarray, theta0: float, limit: str, u_max: float
                        ) -> tuple[float, float]:
    """The monolithic problem written here: every agent's DMOC variables (hand-written
    equations) and the common rotation θ of equidistant angles 2π rank_i / n + θ in the
    cyclic ``order`` (ranks), the thrust limit as bounds or |u_k|² ≤ U², min h Σ|u|², by
    IPOPT from straight-line paths at ``theta0``. Returns (total cost, θ)."""
    n = problem.agents
    theta = ca.SX.sym("theta")
    xs, rows, lbx, ubx, guess, cost, ineq = [], [], [], [], [], 0, []
    for i, m in enumerate(masses(n)):
        start = problem.starts[i]
        angle = 2 * np.pi * order[i] / n + theta
        end = ca.vertcat(CENTRE[0] + RADIUS * ca.cos(angle), CENTRE[1] + RADIUS * ca.sin(angle))
        inner = [ca.SX.sym(f"q{i}_{k}", 2) for k in range(1, INTERVALS)]
        u = [ca.SX.sym(f"u{i}_{k}", 2) for k in range(INTERVALS)]
        q = [ca.DM(start), *inner, end]
        rows += dmoc_rows(float(m), q, u, H)
        ineq += [ca.sumsqr(uk) for uk in u] if limit == "norm" else []
        xs += inner + u
        end0 = CENTRE + RADIUS * np.array([np.cos(2 * np.pi * order[i] / n + theta0),
                                           np.sin(2 * np.pi * order[i] / n + theta0)])
        guess += [start + (end0 - start) * k / INTERVALS for k in range(1, INTERVALS)]
        guess += [np.zeros(2)] * INTERVALS
        bound = u_max if limit == "box" else np.inf
        lbx += [-np.inf] * 2 * (INTERVALS - 1) + [-bound] * 2 * INTERVALS
        ubx += [np.inf] * 2 * (INTERVALS - 1) + [bound] * 2 * INTERVALS
        cost += H * ca.sumsqr(ca.vertcat(*u))
    x = ca.vertcat(*xs, theta)
    g = ca.vertcat(*rows, *ineq)
    n_eq = ca.vertcat(*rows).numel()
    solver = ca.nlpsol("reference", "ipopt", {"x": x, "f": cost, "g": g},
                       {"print_time": False, "ipopt": {"print_level": 0, "tol": 1e-12,
                                                       "bound_relax_factor": 0.0}})
    out = solver(x0=np.r_[np.concatenate(guess), theta0], lbx=np.r_[lbx, -np.inf],
                 ubx=np.r_[ubx, np.inf], lbg=np.r_[np.zeros(n_eq), np.zeros(len(ineq))],
                 ubg=np.r_[np.zeros(n_eq), np.full(len(ineq), u_max**2)])
    assert solver.stats()["success"], solver.stats()["return_status"]
    return float(out["f"]), float(out["x"][-1])


@pytest.fixture(scope="module")
def solved() -> dict:
    """Each limit's hierarchical and monolithic runs from the default start."""
    runs = {}
    for limit in ("box", "norm"):
        problem = fleet(limit)
        runs[limit] = (problem, solve_formation(problem),
                       solve_formation(problem, options=FormationOptions(mode="monolithic")))
    return runs


@pytest.mark.parametrize("limit", ["box", "norm"])
def test_the_limited_fleet_converges_from_the_default_start_to_the_reference(limit, solved):
    """12 masses 1 + 0.1 i, U = 0.8 × the free optimum's peak |u|: the default start is
    infeasible (an agent cannot reach its target there, by the hand-written LP), yet the
    hierarchical run converges, equal to ocpar's monolithic run and to the NLP written here
    to 1e-8 (relative), with every control within the limit."""
    problem, hierarchical, monolithic = solved[limit]
    u_max = 0.8 * free_peak()
    # the default start is outside the window: some agent's move exceeds its reach
    phi = problem.initial_phi()
    moves = problem.curve.points(phi) - problem.starts
    reach = np.array([lp_reach(float(m), INTERVALS, DURATION, -u_max, u_max)[1]
                      for m in masses(problem.agents)])
    outside = (np.linalg.norm(moves, axis=1) if limit == "norm"
               else np.max(np.abs(moves), axis=1)) > reach
    assert outside.any()
    assert hierarchical.status == "converged", hierarchical.message
    assert monolithic.status == "converged", monolithic.message
    order = np.argsort(np.argsort(np.mod(hierarchical.phi - hierarchical.phi[0], 2 * np.pi)))
    theta = float(hierarchical.phi[0] - 2 * np.pi * order[0] / problem.agents)
    reference, _ = reference_formation(problem, order, theta + 0.05, limit, u_max)
    assert hierarchical.total_cost == pytest.approx(reference, rel=1e-8)
    assert monolithic.total_cost == pytest.approx(reference, rel=1e-8)
    peak = (np.linalg.norm(hierarchical.controls, axis=2) if limit == "norm"
            else np.abs(hierarchical.controls))
    assert peak.max() <= u_max * (1 + 1e-9)
    print(f"{limit}: cost {hierarchical.total_cost:.12f} reference {reference:.12f} outer "
          f"iterations {hierarchical.outer_iterations} supersteps {hierarchical.supersteps} "
          f"monolithic {monolithic.total_cost:.12f} ({monolithic.outer_iterations} IPOPT "
          "iterations)")


def test_infeasible_pairs_of_the_cost_table_are_infinite_and_not_solved():
    """Box fleet: a table entry is +∞ exactly where the hand-written LP's reach excludes the
    target, and the superstep solved only the others."""
    problem = fleet("box")
    u_max = 0.8 * free_peak()
    backend = SerialBackend()
    slots = slot_base(problem)
    table = cost_table(problem, backend, slots)
    reach = np.array([lp_reach(float(m), INTERVALS, DURATION, -u_max, u_max)[1]
                      for m in masses(problem.agents)])
    moves = problem.curve.points(slots)[None] - problem.starts[:, None]
    out = np.max(np.abs(moves), axis=2) > reach[:, None]
    assert out.any() and not out.all()
    np.testing.assert_array_equal(~np.isfinite(table), out)
    assert backend.traces[-1].tasks == int(np.sum(~out))


def test_optimal_ordering_completes_on_the_box_fleet(solved):
    """``ordering="optimal"`` on the box fleet: no traceback, converged, no dearer than keep,
    within the limit."""
    problem, keep, _ = solved["box"]
    result = solve_formation(problem, options=FormationOptions(ordering="optimal"))
    assert result.status == "converged", result.message
    assert result.total_cost <= keep.total_cost * (1 + 1e-9)
    assert np.abs(result.controls).max() <= 0.8 * free_peak() * (1 + 1e-9)
    print(f"optimal ordering {result.total_cost:.12f} (keep {keep.total_cost:.12f}), "
          f"{result.supersteps} supersteps, {result.inner_solves} inner solves")


def test_without_an_exact_reach_set_failed_solves_are_rejected_steps():
    """Box limit plus an inactive speed limit (no exact reach set known to ocpar): the start
    fails, phase 1 (the elastic inner problems) finds a feasible one, and the run converges
    to the exact-reach run's cost
    (1e-9); the failures are counted, not raised."""
    u_max = 0.8 * free_peak()
    speed = PathConstraint(lambda v: ca.sumsqr(v), upper=1e4, name="speed")
    problem = build(12, "box", u_max, (speed,))
    assert problem.reach_sets() == []
    result = solve_formation(problem)
    assert result.status == "converged", result.message
    assert result.failed_solves > 0
    assert result.total_cost == pytest.approx(solve_formation(fleet("box")).total_cost,
                                              rel=1e-9)


def test_monolithic_never_calls_an_infeasible_iterate_converged(solved, tmp_path):
    """Monolithic mode stopped after 3 IPOPT iterations: its point breaks the constraints;
    the status is failed and the message says by how much. Its cost, far below the optimum
    (an infeasible point is cheaper), is no headline anywhere: NaN in Python, null in
    result.json, "not reached" in the summary; kept apart as the last iterate's only."""
    problem, optimum, _ = solved["norm"]
    result = solve_formation(problem, options=FormationOptions(
        mode="monolithic", max_outer_iterations=3))
    assert result.status == "failed"
    assert re.search(r"breaks the constraints by [0-9.e+-]+: an infeasible iterate",
                     result.message), result.message
    assert np.isnan(result.total_cost) and optimum.converged
    unreached = result.last_iterate["total_cost"]
    assert unreached == pytest.approx(float(np.sum(result.agent_costs)), rel=1e-12)
    assert unreached < 0.5 * optimum.total_cost   # what the headline would have misstated
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["total_cost"] is None and data["outer_iterations"] == 3
    summary = result.summary()
    assert "total cost — not reached (failed: Maximum_Iterations_Exceeded)" in summary
    assert_no_sentinel(summary)


# --- the command line and TOML ---------------------------------------------------------------

def run_config(tmp_path, body: str, capsys, problem: str = "feasibility_problems:fleet"
               ) -> tuple[int, str]:
    """``ocpar run`` of a formation TOML file (``problem``, output ``tmp_path``/out, then
    ``body``): its exit status and output."""
    path = tmp_path / "fleet.toml"
    path.write_text(f'scheme = "formation"\nproblem = "{problem}"\n'
                    f'output = "{tmp_path / "out"}"\n{body}')
    capsys.readouterr()
    try:
        code = ocpar_main(["run", str(path)])
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out + err


def test_a_limit_below_any_feasible_formation_is_one_line_exit_2_before_any_solve(
        tmp_path, capsys, monkeypatch):
    """U at 0.55 × the free peak: every agent alone reaches some point of the circle (the
    problem is built), but no rotation serves all: exit 2, one line naming the agent and its
    limit, and no solve."""
    u_max = 0.55 * free_peak()
    build(12, "box", u_max)   # each agent can reach the curve: the problem itself is valid

    def no_solve(*args, **kwargs):
        raise AssertionError("a solve ran")

    monkeypatch.setattr("ocpar.formation.run.solve_formation", no_solve)
    for limit, label in (("box", r"shape\[\d+\]\.control_bounds"),
                         ("norm", r"shape\[\d+\]\.path_constraints\[0\] \(thrust\)")):
        code, text = run_config(tmp_path, f'\n[problem_args]\nlimit = "{limit}"\n'
                                f"u_max = {u_max!r}\n", capsys)
        lines = text.strip().splitlines()
        assert code == 2 and len(lines) == 1, text
        assert re.match(rf"ocpar.formation: error: {label}: no formation lets every agent "
                        r"reach its target .* agent \d+ \(mass [0-9.]+\)", lines[0]), lines[0]


def test_the_start_given_in_toml_is_honoured(tmp_path, capsys):
    """``initial_rotation`` in TOML: the first superstep's cost is Σ Ĵ_i at the default angles
    plus that rotation (each solved here one by one), not at the default feasible start; the
    run converges to the same optimum. ``initial_angles`` of the wrong length: exit 2."""
    problem = fleet("box")
    rotation = -1.3
    expected = float(np.sum(pair_costs(problem, SerialBackend(), np.arange(problem.agents),
                                       problem.initial_phi() + rotation, "check")))
    code, text = run_config(tmp_path, f"initial_rotation = {rotation}\n"
                            '\n[problem_args]\nlimit = "box"\n', capsys)
    assert code == 0, text
    first = float(re.search(r"superstep +0 +cost (\S+)", text).group(1))
    assert first == pytest.approx(expected, rel=1e-11)
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    lines: list[str] = []
    default = solve_formation(problem, progress=lines.append)
    default_first = float(re.search(r"superstep +0 +cost (\S+)", lines[0]).group(1))
    assert abs(first - default_first) > 1e-3 * first   # not the default (feasible) start
    assert result["status"] == "converged"
    assert result["total_cost"] == pytest.approx(default.total_cost, rel=1e-9)
    angles = ", ".join(repr(float(a)) for a in problem.initial_phi()[:5])
    code, text = run_config(tmp_path, f"initial_angles = [{angles}]\n"
                            '\n[problem_args]\nlimit = "box"\n', capsys)
    assert code == 2 and text.strip() == ("ocpar.formation: error: initial_angles: needs 12 "
                                          "angles (12 agents), got 5"), text


def test_initial_angles_in_toml_become_the_start(tmp_path, capsys):
    """``initial_angles`` (a TOML array) inside the feasible window: the first superstep's
    cost is the sum of the agents' costs at those angles."""
    problem = fleet("norm")
    angles = problem.initial_phi() - 1.2
    expected = float(np.sum(pair_costs(problem, SerialBackend(), np.arange(problem.agents),
                                       angles, "check")))
    listed = ", ".join(repr(float(a)) for a in angles)
    code, text = run_config(tmp_path, f"initial_angles = [{listed}]\n"
                            '\n[problem_args]\nlimit = "norm"\n', capsys)
    assert code == 0, text
    first = float(re.search(r"superstep +0 +cost (\S+)", text).group(1))
    assert first == pytest.approx(expected, rel=1e-11)


@pytest.mark.parametrize("limit", ["box", "norm"])
def test_the_feasible_window_ends_where_an_agent_leaves_its_reach(limit):
    """The window of rotations (about the initial guess) ends where some agent's move leaves
    the reach of the hand-written LP: 1e-7 rad inside both ends every agent reaches its
    target, 1e-7 rad outside one does not; the start lies inside, the initial guess not."""
    from ocpar.formation.feasibility import feasible_window

    problem = fleet(limit)
    u_max = 0.8 * free_peak()
    reach = np.array([lp_reach(float(m), INTERVALS, DURATION, -u_max, u_max)[1]
                      for m in masses(problem.agents)])
    phi0 = problem.initial_phi()

    def reached(theta: float) -> bool:
        moves = CENTRE + RADIUS * np.column_stack([np.cos(phi0 + theta),
                                                   np.sin(phi0 + theta)]) - problem.starts
        size = (np.linalg.norm(moves, axis=1) if limit == "norm"
                else np.max(np.abs(moves), axis=1))
        return bool(np.all(size <= reach))

    window = feasible_window(problem, problem.coupling.family(phi0, problem.curve))
    assert not reached(0.0) and reached(window.start)
    assert window.low < window.start < window.high
    for end, inward in ((window.low, 1.0), (window.high, -1.0)):
        assert reached(end + inward * 1e-7) and not reached(end - inward * 1e-7)


@pytest.mark.parametrize(("argv", "needle"), [
    (["--initial-angles", "0.1,x"], "argument --initial-angles: expected numbers separated "
                                    "by commas, got '0.1,x'"),
    (["--initial-angles", "0.1,inf"], "argument --initial-angles: expected a non-empty list "
                                      "of finite numbers"),
    (["--initial-rotation", "nan"], "argument --initial-rotation: expected a finite number"),
    (["--initial-rotation=-1", "--ordering", "optimal"],
     "initial_angles/initial_rotation: ordering 'optimal' chooses its own start"),
    (["--initial-rotation=-1", "--initial-angles=1,2"],
     "initial_angles and initial_rotation: give one start, not both"),
])
def test_bad_starts_on_the_command_line_are_one_line_exit_2(argv, needle, capsys, monkeypatch):
    from ocpar import driver
    from ocpar.formation.run import FormationRun

    monkeypatch.setattr("ocpar.formation.run.solve_formation", None)   # never reached
    try:
        code = driver.main(FormationRun, ["--problem", "feasibility_problems:fleet", "--quiet",
                                          *argv])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and needle in err[0], err
