"""Feasibility for every problem class (issue 42, item 3): the elastic (phase-1) inner
problem, and infeasible starts on a surface, on slots and on an isolated coupling, each under
a thrust limit, ending converged and equal to references computed here (the DMOC equations of
a point mass written by hand, solved by IPOPT; brute force over assignments)."""

from __future__ import annotations

import itertools
import json
import re

import casadi as ca
import numpy as np
import pytest
from phase_one_problems import DURATION, INTERVALS, MASSES, STARTS, U, reassignable
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation
from test_feasibility import lp_reach, run_config

from ocpar.formation import (
    DmocShape,
    Ellipse,
    FormationProblem,
    PotentialCoupling,
    SphereSurface,
    solve_formation,
)
from ocpar.models import PointMass
from ocpar.ocp import dmoc_problem
from ocpar.ocp.constraints import PathConstraint


def hand_dmoc(mass: float, start, end, intervals: int, duration: float, limit: str,
              u_max: float) -> float | None:
    """min h Σ|u_k|² of a point mass from rest at ``start`` to rest at ``end`` (any dimension)
    under |u_k|² ≤ U² (``norm``) or |u_k[j]| ≤ U (``box``): the DMOC equations by hand
    (midpoint L_d, forces (h/2) u_k each side), IPOPT; None where it finds no feasible point."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    d, n, h = len(start), intervals, duration / intervals
    inner = [ca.SX.sym(f"q{k}", d) for k in range(1, n)]
    u = [ca.SX.sym(f"u{k}", d) for k in range(n)]
    q = [ca.DM(start), *inner, ca.DM(end)]
    rows = [-mass * (q[1] - q[0]) / h + h / 2 * u[0]]
    rows += [mass * (2 * q[k] - q[k - 1] - q[k + 1]) / h + h / 2 * (u[k - 1] + u[k])
             for k in range(1, n)]
    rows.append(mass * (q[n] - q[n - 1]) / h + h / 2 * u[n - 1])
    ineq = [ca.sumsqr(uk) for uk in u] if limit == "norm" else []
    bound = u_max if limit == "box" else np.inf
    x = ca.vertcat(*inner, *u)
    n_eq = ca.vertcat(*rows).numel()
    solver = ca.nlpsol("hand", "ipopt", {"x": x, "f": h * ca.sumsqr(ca.vertcat(*u)),
                                         "g": ca.vertcat(*rows, *ineq)},
                       {"print_time": False, "ipopt": {"print_level": 0, "tol": 1e-12,
                                                       "bound_relax_factor": 0.0}})
    guess = np.concatenate([start + (end - start) * k / n for k in range(1, n)]
                           + [np.zeros(d * n)])
    out = solver(x0=guess, lbx=np.r_[np.full(d * (n - 1), -np.inf), np.full(d * n, -bound)],
                 ubx=np.r_[np.full(d * (n - 1), np.inf), np.full(d * n, bound)],
                 lbg=np.zeros(n_eq + len(ineq)),
                 ubg=np.r_[np.zeros(n_eq), np.full(len(ineq), u_max**2)])
    return float(out["f"]) if solver.stats()["success"] else None


# --- the elastic inner problem ---------------------------------------------------------------

@pytest.mark.parametrize("limit", ["box", "norm"])
def test_the_elastic_slack_is_the_excess_over_the_lp_reach_and_its_gradient_the_multipliers(
        limit):
    """A unit point mass at rest, T = 1, N = 10, |u| ≤ 1 moved d along x: s = max(0, d − r)
    with r the reach of the LP written in test_feasibility (ending beyond it costs one per
    unit of distance; relaxing the end velocity b gains r′(0) = T/2 < 1 per unit), and
    ds/dq_N from the multipliers equal to a central difference."""
    thrust = {"box": {"control_bounds": ((-1.0, 1.0), (-1.0, 1.0))},
              "norm": {"path_constraints": (PathConstraint(lambda u: ca.sumsqr(u), upper=1.0,
                                                           name="thrust"),)}}[limit]
    shape = DmocShape(PointMass(dim=2), 10, 1.0, elastic=True, **thrust)
    nlp = dmoc_problem(shape)
    reach = lp_reach(1.0, 10, 1.0, -1.0, 1.0)[1]
    for d in (0.1, reach - 0.01, reach + 0.05, 0.6):
        params = np.array([0, 0, 0, 0, d, 0, 0, 0.0])
        sol = nlp.solve(params)
        assert sol.success
        assert sol.cost == pytest.approx(max(0.0, d - reach), abs=1e-8)
        step = 1e-6
        up, down = (nlp.solve(params + np.eye(8)[4] * sign * step).cost for sign in (1, -1))
        assert sol.cost_gradient[4] == pytest.approx((up - down) / (2 * step), abs=1e-6)


def elastic_lp(d: float, u_max: float, intervals: int = 10, duration: float = 2.0) -> float:
    """The elastic problem of a unit mass at rest moved d under |u_k| ≤ U, written here as an
    LP (the DMOC equations by hand, in one dimension): min a⁺ + a⁻ + T (b⁺ + b⁻) + Σ σ_k / U
    with the end at d + a⁺ − a⁻, its velocity b⁺ − b⁻, −U − σ_k ≤ u_k ≤ U + σ_k (the slacks'
    characteristic sizes as docs/schemes/formation.md states them)."""
    from scipy.optimize import linprog
    n, h = intervals, duration / intervals
    # columns: q_1..q_{n−1}, u_0..u_{n−1}, σ_0..σ_{n−1}, a⁺, a⁻, b⁺, b⁻
    ui, si, ends = n - 1, 2 * n - 1, 3 * n - 1
    size = 3 * n + 3
    rows, rhs = [], []
    for k in range(n + 1):   # node k: m (q_k − q_{k−1})/h − m (q_{k+1} − q_k)/h + forces
        row, known = np.zeros(size), 0.0
        terms = ([(k, 1 / h), (k - 1, -1 / h)] if k > 0 else []) + \
            ([(k + 1, -1 / h), (k, 1 / h)] if k < n else [])
        for node, coef in terms:
            if node == n:   # the slackened end d + a⁺ − a⁻
                known += coef * d
                row[ends:ends + 2] += [coef, -coef]
            elif node > 0:   # q_0 = 0
                row[node - 1] += coef
        if k > 0:
            row[ui + k - 1] += h / 2
        if k < n:
            row[ui + k] += h / 2
        if k == n:   # − m ṽ_N, ṽ_N = b⁺ − b⁻
            row[ends + 2:ends + 4] += [-1.0, 1.0]
        rows.append(row)
        rhs.append(-known)
    ineq = []
    for k in range(n):
        for sign in (1.0, -1.0):
            row = np.zeros(size)
            row[ui + k], row[si + k] = sign, -1.0
            ineq.append(row)
    cost = np.zeros(size)
    cost[si:si + n] = 1 / u_max
    cost[ends:ends + 4] = [1.0, 1.0, duration, duration]
    bounds = [(None, None)] * (2 * n - 1) + [(0, None)] * (n + 4)
    out = linprog(cost, A_ub=np.array(ineq), b_ub=np.full(2 * n, u_max), A_eq=np.array(rows),
                  b_eq=np.array(rhs), bounds=bounds, method="highs")
    assert out.status == 0
    return float(out.fun)


@pytest.mark.parametrize("u_max", [1.0, 40.0])
def test_the_elastic_slacks_are_measured_against_their_characteristic_sizes(u_max):
    """A unit mass at rest moved 0.3 beyond its reach under a box limit U (T = 2, N = 10):
    the elastic cost equals the LP written here with the documented weights (1 per length
    of the end, T per velocity unit, 1/U per unit of a bound's slack). At U = 1 moving the
    end is cheapest (s = 0.3); at U = 40 relaxing the bound is (s < 0.3): the weights, not
    the units, decide, and the LP tells which."""
    shape = DmocShape(PointMass(dim=2), 10, 2.0, control_bounds=((-u_max, u_max),) * 2,
                      elastic=True)
    reach = lp_reach(1.0, 10, 2.0, -u_max, u_max)[1]
    d = reach + 0.3
    sol = dmoc_problem(shape).solve(np.array([0, 0, 0, 0, d, 0, 0, 0.0]))
    assert sol.success
    expected = elastic_lp(d, u_max)
    assert sol.cost == pytest.approx(expected, rel=1e-7, abs=1e-10)
    assert (expected == pytest.approx(0.3, rel=1e-9)) == (u_max == 1.0)


# --- a surface -------------------------------------------------------------------------------

TETRAHEDRON = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(3)


def test_an_infeasible_start_on_a_sphere_ends_at_the_optimum_under_a_norm_limit():
    """Four unit masses at rest on a regular tetrahedron of radius 1.5 onto the unit sphere
    (the potential: a regular tetrahedron, free up to rotations), |u| ≤ 0.6, T = 2: from that
    tetrahedron turned 2 rad about z (agent 0 then ~1.1 from its target, beyond its reach)
    phase 1 turns it feasible; the optimum is every agent 0.5 straight in (no point of the
    sphere is nearer), its cost 4 × the hand-written NLP's for that move."""
    u_max = 0.6
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
    surface = SphereSurface(radius=1.0)
    problem = FormationProblem(name="tetrahedron", curve=surface, starts=1.5 * TETRAHEDRON,
                               shape=DmocShape(PointMass(dim=3), INTERVALS, DURATION,
                                               path_constraints=(thrust,)))
    phi0 = surface.locate(Rotation.from_rotvec([0, 0, 2.0]).apply(TETRAHEDRON))
    far = np.linalg.norm(surface.points(phi0) - problem.starts, axis=1)
    assert hand_dmoc(1.0, [0, 0, 0], [far.max(), 0, 0], INTERVALS, DURATION, "norm",
                     u_max) is None   # the start is infeasible
    result = solve_formation(problem, phi0=phi0)
    assert result.status == "converged", result.message
    np.testing.assert_allclose(problem.final_positions(result.phi), TETRAHEDRON, atol=1e-6)
    one = hand_dmoc(1.0, [0, 0, 0], [0.5, 0, 0], INTERVALS, DURATION, "norm", u_max)
    assert result.total_cost == pytest.approx(4 * one, rel=1e-6)
    assert np.max(np.linalg.norm(result.controls, axis=2)) <= u_max * (1 + 1e-9)


# --- an isolated coupling --------------------------------------------------------------------

ELLIPSE = (3.0, 1.5)
ANGLES = np.array([0.3, 1.8, 3.5, 5.0])
ELLIPSE_STARTS = np.column_stack([3.6 * np.cos(ANGLES), 2.0 * np.sin(ANGLES)])


def ellipse_problem(u_max: float) -> FormationProblem:
    """Four unit masses from rest outside the ellipse ``ELLIPSE`` onto it (the potential's
    isolated critical points), |u| ≤ ``u_max``, T = 2, N = 10."""
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
    return FormationProblem(name="iso", curve=Ellipse(semi_axes=ELLIPSE, center=np.zeros(2)),
                            starts=ELLIPSE_STARTS, coupling=PotentialCoupling(),
                            shape=DmocShape(PointMass(dim=2), INTERVALS, DURATION,
                                            path_constraints=(thrust,)))


def critical_points() -> tuple[np.ndarray, np.ndarray]:
    """The critical set of the potential Σ 1/|z_i − z_j|² on the ellipse the starts' angles
    lead to (SciPy's BFGS, here): its angles (4,) and points (4, 2)."""
    a, b = ELLIPSE

    def potential(phi):
        z = np.column_stack([a * np.cos(phi), b * np.sin(phi)])
        i, j = np.triu_indices(len(phi), 1)
        return np.sum(1 / np.sum((z[i] - z[j]) ** 2, axis=1))

    critical = minimize(potential, ANGLES, method="BFGS", options={"gtol": 1e-12}).x
    return critical, np.column_stack([a * np.cos(critical), b * np.sin(critical)])


def pair_table(points: np.ndarray, u_max: float) -> dict:
    """The hand-written NLP's cost of each (agent, point) move, None where infeasible."""
    return {(i, j): hand_dmoc(1.0, ELLIPSE_STARTS[i], points[j], INTERVALS, DURATION, "norm",
                              u_max) for i in range(4) for j in range(4)}


def test_an_infeasible_start_on_an_isolated_coupling_ends_at_the_cheapest_feasible_assignment():
    """|u| ≤ 1.3: from the critical set with every agent sent one place on (infeasible),
    the result is the cheapest of the 4! assignments of the set's points whose every move
    the hand-written NLP solves."""
    u_max = 1.3
    problem = ellipse_problem(u_max)
    critical, points = critical_points()
    phi0 = np.roll(critical, 1)
    pair = pair_table(points, u_max)
    assert any(pair[i, (i + 3) % 4] is None for i in range(4))   # the start is infeasible
    best = min(sum(pair[i, j] for i, j in enumerate(p))
               for p in itertools.permutations(range(4))
               if all(pair[i, j] is not None for i, j in enumerate(p)))
    result = solve_formation(problem, phi0=phi0)
    assert result.status == "converged" and result.feasible_set == "discrete", result.message
    assert result.total_cost == pytest.approx(best, rel=1e-6)
    ends = problem.final_positions(result.phi)
    assert max(np.min(np.linalg.norm(points - end, axis=1)) for end in ends) <= 1e-6


def test_an_isolated_coupling_no_assignment_serves_is_refused_in_one_line_with_the_slack():
    """|u| ≤ 0.8: each agent reaches the ellipse (the problem is accepted), two of the 16
    (agent, point) moves onto the critical set are feasible, no assignment has all four (the
    hand-written NLP); the run is refused: ``failed``, one line naming the least total slack
    found (> 0) and the farthest agent, no verification words about paths that are no
    answer."""
    u_max = 0.8
    critical, points = critical_points()
    pair = pair_table(points, u_max)
    assert not any(all(pair[i, j] is not None for i, j in enumerate(p))
                   for p in itertools.permutations(range(4)))
    result = solve_formation(ellipse_problem(u_max), phi0=critical)
    assert result.status == "failed" and "\n" not in result.message
    assert result.message.startswith("no feasible formation: phase 1")
    assert "verification" not in result.message
    slack = float(result.message.split("smallest total slack of ")[1].split(" ")[0])
    assert slack > 0.1


def test_an_infeasible_start_on_a_users_coupling_with_free_directions_is_made_feasible():
    """The user's coupling of tests/test_couplings.py (two free directions: the tangent
    Newton search), |u| ≤ 8 (below the free optimum's peak 11.95): from the free optimum's
    angles with pairs (0, 1) and (2, 3) sent half a turn on (still c = 0, infeasible),
    phase 1 descends along c = 0 to a feasible formation and the run converges, equal to
    the monolithic mode started from the free optimum's angles (1e-9)."""
    from test_couplings import A, B, paired

    from ocpar.formation import FormationOptions, UserCoupling
    n, u_max = 6, 8.0
    starts = np.column_stack([np.linspace(-6.0, 6.0, n), np.full(n, -5.0)])

    def make(**limit) -> FormationProblem:
        return FormationProblem(name="coupled", starts=starts,
                                shape=DmocShape(PointMass(dim=2), 10, 2.0, **limit),
                                curve=Ellipse(semi_axes=(A, B), center=np.array([1.0, 2.0])),
                                coupling=UserCoupling(paired(n)))

    free = solve_formation(make())
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
    problem = make(path_constraints=(thrust,))
    phi0 = free.phi + np.array([np.pi, np.pi, np.pi, np.pi, 0.0, 0.0])
    moves = np.linalg.norm(problem.final_positions(phi0) - starts, axis=1)
    assert any(hand_dmoc(1.0, [0, 0], [d, 0], 10, 2.0, "norm", u_max) is None
               for d in moves)   # the start is infeasible
    result = solve_formation(problem, phi0=phi0)
    assert result.status == "converged" and "phase 1" in result.message, result.message
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"),
                                 phi0=free.phi)
    assert monolithic.status == "converged"
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-9)


# --- slots -----------------------------------------------------------------------------------

def test_an_infeasible_nearest_assignment_onto_slots_ends_at_the_cheapest_feasible_one():
    """The nearest assignment sends the heavy agent (reach 1/6) 0.2 up, infeasible; the
    result is the cheapest of the 6 assignments whose every move the hand-written NLP
    solves under the box limit."""
    problem = reassignable()
    points = problem.curve.points
    nearest = problem.initial_phi().astype(int)
    cost = {(i, j): hand_dmoc(MASSES[i], STARTS[i], points[j], INTERVALS, DURATION, "box", U)
            for i in range(2) for j in range(3)}
    assert any(cost[i, j] is None for i, j in enumerate(nearest))
    best = min(cost[0, a] + cost[1, b] for a, b in itertools.permutations(range(3), 2)
               if cost[0, a] is not None and cost[1, b] is not None)
    result = solve_formation(problem)
    assert result.status == "converged", result.message
    assert result.total_cost == pytest.approx(best, rel=1e-6)


def test_slots_with_no_feasible_assignment_are_refused_in_one_line_with_the_slack(
        tmp_path, capsys):
    """Each agent reaches slot 0 alone (the light one misses slots 1 and 2 by 0.1 along x,
    its LP reach 0.5; the heavy one misses slot 1 by 0.3 − 1/6 and 0.2 − 1/6): the least
    total slack is 0.1. The run writes result.json and its picture, exits 3 (failed)."""
    reach = lp_reach(MASSES[0], INTERVALS, DURATION, -U, U)[1]
    code, text = run_config(tmp_path, "", capsys, problem="phase_one_problems:unassignable")
    assert code == 3 and "Traceback" not in text, text
    summary = json.loads((tmp_path / "out" / "result.json").read_text())
    assert summary["status"] == "failed" and "\n" not in summary["message"]
    assert "no feasible formation" in summary["message"]
    slack = float(summary["message"].split("smallest total slack of ")[1].split(" ")[0])
    assert slack == pytest.approx(0.6 - reach, rel=1e-3)
    assert any(p.suffix == ".png" for p in (tmp_path / "out").iterdir())


# --- every outer solver ----------------------------------------------------------------------

@pytest.mark.parametrize("outer", ["sqp", "offset"])
def test_sqp_and_offset_start_from_phase_one_and_stay_feasible(outer):
    """The 6-mass fleet of test_feasibility onto its circle, box limit at 0.8 × the free
    peak plus an inactive speed limit (so no exact reach set: the start is found by phase 1
    alone): its default start is infeasible by the LP reach written there; ``sqp`` and
    ``offset`` end converged, equal to the monolithic NLP written there (1e-8)."""
    from feasibility_problems import build, free_peak, masses
    from test_feasibility import reference_formation

    from ocpar.formation import FormationOptions
    agents = 6
    u_max = 0.8 * free_peak(agents)
    speed = PathConstraint(lambda v: ca.sumsqr(v), upper=1e4, name="speed")
    problem = build(agents, "box", u_max, (speed,))
    assert problem.reach_sets() == []
    moves = problem.curve.points(problem.initial_phi()) - problem.starts
    reach = np.array([lp_reach(float(m), 20, 5.0, -u_max, u_max)[1] for m in masses(agents)])
    assert np.any(np.max(np.abs(moves), axis=1) > reach)
    result = solve_formation(problem, options=FormationOptions(
        outer=outer, outer_tol=1e-14 if outer == "sqp" else 1e-12))
    assert result.status == "converged", result.message
    order = np.argsort(np.argsort(np.mod(result.phi - result.phi[0], 2 * np.pi)))
    theta = float(result.phi[0] - 2 * np.pi * order[0] / agents)
    reference, _ = reference_formation(problem, order, theta + 0.05, "box", u_max)
    assert result.total_cost == pytest.approx(reference, rel=1e-8)
    assert np.abs(result.controls).max() <= u_max * (1 + 1e-9)


def test_a_feasible_window_narrower_than_the_old_scan_spacing_is_found():
    """The 12-mass fleet at 0.615 × the free peak (box) plus an inactive speed limit (no
    exact reach set): the feasible rotations form one window 0.058 rad wide (the exact reach
    sets' window of the same fleet without the speed limit, checked here), narrower than
    the 2π/32 spacing of the old 32-shift scan, which missed it; phase 1 finds it, and the
    run equals the monolithic NLP written in test_feasibility (1e-8)."""
    from feasibility_problems import build, fleet, free_peak
    from test_feasibility import reference_formation

    from ocpar.formation.feasibility import feasible_window
    exact = fleet("box", 0.615, 12)
    family = exact.coupling.family(exact.initial_phi(), exact.curve)
    window = feasible_window(exact, family)
    assert 0 < window.high - window.low < 2 * np.pi / 32
    u_max = 0.615 * free_peak(12)
    speed = PathConstraint(lambda v: ca.sumsqr(v), upper=1e4, name="speed")
    result = solve_formation(build(12, "box", u_max, (speed,)))
    assert result.status == "converged", result.message
    order = np.argsort(np.argsort(np.mod(result.phi - result.phi[0], 2 * np.pi)))
    theta = float(result.phi[0] - 2 * np.pi * order[0] / 12)
    shift = np.angle(np.exp(1j * (result.phi - family.base)))   # the family's θ, each agent
    assert np.ptp(shift) < 1e-9 and window.low <= shift[0] <= window.high
    reference, _ = reference_formation(exact, order, theta, "box", u_max)
    assert result.total_cost == pytest.approx(reference, rel=1e-8)


def test_an_sqp_step_out_of_the_feasible_window_is_backtracked():
    """The 12-mass box fleet at 0.615 × the free peak (exact reach sets: the start is inside
    its 0.058 rad window): an SLSQP iterate leaves the window (its inner solve fails, counted),
    which used to end the run ``failed``; J = +∞ there makes SLSQP backtrack, and the run
    equals the monolithic NLP written in test_feasibility (1e-8)."""
    from feasibility_problems import fleet, free_peak
    from test_feasibility import reference_formation

    from ocpar.formation import FormationOptions
    problem = fleet("box", 0.615, 12)
    result = solve_formation(problem, options=FormationOptions(outer="sqp", outer_tol=1e-14))
    assert result.status == "converged", result.message
    assert result.failed_solves >= 1
    order = np.argsort(np.argsort(np.mod(result.phi - result.phi[0], 2 * np.pi)))
    theta = float(result.phi[0] - 2 * np.pi * order[0] / 12)
    reference, _ = reference_formation(problem, order, theta, "box", 0.615 * free_peak(12))
    assert result.total_cost == pytest.approx(reference, rel=1e-8)


# --- obstacles and holonomic models (phase 1 robust) -----------------------------------------

def _limited(problem: FormationProblem, rows: tuple) -> FormationProblem:
    """``problem`` with every agent's shape carrying the path constraints ``rows``."""
    import dataclasses
    return problem.with_shapes(lambda s: dataclasses.replace(s, path_constraints=rows))


def _infeasible(problem: FormationProblem, phi: np.ndarray) -> bool:
    """Whether some agent's hard inner problem at ``phi`` has no solution."""
    from ocpar.bsp.serial import SerialBackend
    from ocpar.formation.feasibility import inner_costs
    costs = inner_costs(problem, SerialBackend(), np.arange(problem.agents), phi).costs
    return not np.all(np.isfinite(costs))


@pytest.fixture(scope="module")
def limited_past_the_disc():
    """The obstacle example (4 masses past its disc) under |u| ≤ u_max = 0.8 × its free
    optimum's peak plus an inactive speed limit (no exact reach set): (problem, the free
    optimum, u_max)."""
    from ocpar.examples import formation_obstacle
    base = formation_obstacle.make(agents=4)
    free = solve_formation(base)
    u_max = 0.8 * float(np.linalg.norm(free.controls, axis=2).max())
    problem = _limited(base, (PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2,
                                             name="thrust"),
                              PathConstraint(lambda v: ca.sumsqr(v), upper=1e4, name="speed")))
    return problem, free, u_max


def test_an_infeasible_start_past_an_obstacle_ends_converged_equal_to_the_monolithic_nlp(
        limited_past_the_disc):
    """The obstacle example (4 masses, the disc of radius 0.8) under |u| ≤ 0.8 × the free
    optimum's peak plus an inactive speed limit (no exact reach set): the free optimum turned
    1.15 rad is infeasible; phase 1 (the elastic solves past the disc stop at local minima
    above 0 for agents the hard solve serves: the hard solve decides) finds a feasible turn,
    and the run ends converged, the disc cleared and the limit met, equal to the monolithic
    NLP (every agent's path, planes and the coupling in one IPOPT solve) started 0.02 rad
    from it (1e-6)."""
    from ocpar.formation import FormationOptions
    problem, free, u_max = limited_past_the_disc
    assert problem.reach_sets() == []
    phi0 = free.phi + 1.15
    assert _infeasible(problem, phi0)
    result = solve_formation(problem, phi0=phi0)
    assert result.status == "converged" and "phase 1" in result.message, result.message
    assert "obstacles cleared" in result.message
    assert np.linalg.norm(result.controls, axis=2).max() <= u_max * (1 + 1e-9)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"),
                                 phi0=result.phi + 0.02)
    assert monolithic.status == "converged", monolithic.message
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-6)


def test_an_infeasible_start_of_rigid_spacecraft_ends_converged_equal_to_the_monolithic_nlp():
    """Three halo spacecraft (unit quaternions: a holonomic constraint at every node) under
    |F| ≤ 0.65 × the free optimum's peak force: the free optimum turned 2.6 rad is
    infeasible; phase 1's elastic solves keep the slackened end on |p| = 1, and the run ends
    converged with the limit met, equal to the monolithic NLP started 0.05 rad from it
    (1e-6)."""
    from ocpar.examples import formation_halo
    from ocpar.formation import FormationOptions
    base = formation_halo.make(agents=3)
    free = solve_formation(base)
    u_max = 0.65 * float(np.linalg.norm(free.controls[..., :3], axis=2).max())
    problem = _limited(base, (PathConstraint(lambda u: ca.sumsqr(u[:3]), upper=u_max**2,
                                             name="thrust"),))
    phi0 = free.phi + 2.6
    assert _infeasible(problem, phi0)
    result = solve_formation(problem, phi0=phi0)
    assert result.status == "converged" and "phase 1" in result.message, result.message
    assert np.linalg.norm(result.controls[..., :3], axis=2).max() <= u_max * (1 + 1e-9)
    np.testing.assert_allclose(np.linalg.norm(result.trajectories[..., 3:], axis=2), 1.0,
                               atol=1e-9)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"),
                                 phi0=result.phi + 0.05)
    assert monolithic.status == "converged", monolithic.message
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-6)


def test_the_elastic_end_of_a_quaternion_model_stays_on_its_constraint():
    """A halo spacecraft's elastic NLP sent beyond its force limit: the slackened end q_N +
    a⁺ − a⁻ read from the solution has a unit quaternion (the hard row c(q) = 0 there), and
    the slack is positive (one limit |u| ≤ 1 on force and torque together: the turn
    competes with the move; without that row IPOPT failed on this NLP, measured)."""
    from ocpar.examples import formation_halo
    from ocpar.formation.feasibility import elastic_shape
    base = formation_halo.make(agents=2)
    u_max = 1.0
    shape = elastic_shape(_limited(base, (PathConstraint(lambda u: ca.sumsqr(u),
                                                         upper=u_max**2, name="effort"),)
                                   ).common_shape)
    nlp = dmoc_problem(shape)
    params = base.boundary_params_rows(np.array([0]), np.array([0.3]))[0]
    out = nlp.solver(x0=nlp.default_guess(params), p=params, lbg=nlp.lbg, ubg=nlp.ubg,
                     lbx=nlp.lbx, ubx=nlp.ubx)
    assert nlp.solver.stats()["success"]
    w = np.asarray(out["x"]).ravel()
    nq, n = 7, shape.intervals
    start = nq * (n - 1) + 6 * n + (n + 1)   # after the inner nodes, controls and λ
    a_plus, a_minus = w[start:start + nq], w[start + nq:start + 2 * nq]
    end = params[2 * nq:3 * nq] + a_plus - a_minus
    assert np.linalg.norm(end[3:]) == pytest.approx(1.0, abs=1e-9)
    assert float(out["f"]) > 1e-3


def test_past_an_obstacle_the_hard_solve_decides_where_the_elastic_one_stops_above_zero():
    """The obstacle example (6 masses) under |u| ≤ 31.6 (0.7 × the free optimum's peak),
    the free optimum turned 0.5236 rad: agent 3's elastic NLP stops at a local minimum of
    total slack ~2.19 from every side of the disc, yet its hard inner problem is solved
    (and the elastic NLP from that solution gives ~0); the measure phase 1 uses is 0."""
    from ocpar.bsp.serial import SerialBackend
    from ocpar.examples import formation_obstacle
    from ocpar.formation.feasibility import elastic_problem, elastic_slacks
    base = formation_obstacle.make()
    free = solve_formation(base)
    u_max = 0.7 * float(np.linalg.norm(free.controls, axis=2).max())
    problem = _limited(base, (PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2,
                                             name="thrust"),
                              PathConstraint(lambda v: ca.sumsqr(v), upper=1e4, name="speed")))
    phi = free.phi + 0.5236
    params = problem.boundary_params_rows(np.array([3]), phi[3:4])[0]
    elastic = dmoc_problem(elastic_problem(problem).common_shape).solve(params)
    hard = dmoc_problem(problem.common_shape).solve(params)
    assert elastic.success and elastic.cost > 1.0
    assert hard.success
    found = elastic_slacks(problem, SerialBackend(), np.array([3]), phi[3:4])
    assert found.slack[0] == 0.0 and np.all(found.end_gradient == 0.0)


def test_a_shift_search_stopped_at_a_jump_of_j_says_it_is_no_stationary_point(
        limited_past_the_disc):
    """The obstacle example of the test above started 0.95 rad turned: the shift search ends
    where a step downhill raises J (an agent's optimum passes the disc on its other side
    beyond it), a local minimum with |dJ/dθ| far from 0; the message says so instead of
    claiming a stationary point."""
    problem, free, _ = limited_past_the_disc
    result = solve_formation(problem, phi0=free.phi + 0.95)
    assert result.status == "converged", result.message
    slope = float(re.search(r"dJ/dtheta = (\S+), not a stationary point", result.message)[1])
    assert abs(slope) > 1.0 and "a jump of J" in result.message
