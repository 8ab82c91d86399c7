"""Formation agents of any dynamics: unicycles (an ODE model, multiple shooting,
:class:`~ocpar.ocp.MsEndpointShape`) from a line onto a circle and onto slots, against NLPs of
the same transcription written here (RK4 per interval, independent of the package's code);
the inner problem's dJ*/dp and end Hessian against finite differences; serial, mpirun -n 2
and two Dask workers bit-identical."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools

import casadi as ca
import numpy as np
import pytest
from conftest import computed, local_cluster, read_result, run_ocpar
from scipy.optimize import linear_sum_assignment

from ocpar.examples.formation_unicycles import make
from ocpar.formation import (
    Circle,
    Ellipse,
    EqualArcLength,
    FormationOptions,
    FormationProblem,
    SphereSurface,
    solve_formation,
    verify_formation,
)
from ocpar.models import Unicycle
from ocpar.ocp import MsEndpointShape, transcription
from ocpar.ocp.constraints import PathConstraint
from ocpar.ocp.reach import end_cost_convexity

AGENTS, RADIUS, DURATION, INTERVALS = 8, 3.0, 6.0, 20
#: |a| ≤ this binds on the slots (the unbounded optimum's peak is 1.28).
ACCELERATION_LIMIT = 1.0


# ------------------------------------------------------------------------------------------
# the reference NLPs, written here: RK4 multiple shooting of the unicycle
# ------------------------------------------------------------------------------------------

def _rk4(x: ca.MX, u: ca.MX, h: float) -> tuple[ca.MX, ca.MX]:
    """One classical RK4 step of ẋ = (v cos ψ, v sin ψ, ω, a) and of the cost a² + ω²."""
    def f(s: ca.MX) -> ca.MX:
        return ca.vertcat(s[3] * ca.cos(s[2]), s[3] * ca.sin(s[2]), u[1], u[0])
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), h * ca.sumsqr(u)


#: An agent's part of an NLP: variables, their lower and upper bounds, cost, rows (= 0).
Nlp = tuple[list[ca.MX], list[np.ndarray], list[np.ndarray], ca.MX, list[ca.MX]]


def _agent_nlp(start: np.ndarray | ca.MX, end: ca.MX, limit: float | None) -> Nlp:
    """One unicycle's variables (x_1..x_N, u), their bounds, its cost and its rows (the
    continuity rows, then x_N's position = ``end`` and speed 0; heading free)."""
    h = DURATION / INTERVALS
    xs = [ca.MX.sym(f"x{k}", 4) for k in range(INTERVALS)]
    us = [ca.MX.sym(f"u{k}", 2) for k in range(INTERVALS)]
    cost, rows, x = 0, [], start
    for k in range(INTERVALS):
        nxt, c = _rk4(x, us[k], h)
        cost += c
        rows.append(xs[k] - nxt)
        x = xs[k]
    rows += [x[:2] - end, x[3]]
    a = np.inf if limit is None else limit
    lower = [np.full(4, -np.inf)] * INTERVALS + [np.array([-a, -np.inf])] * INTERVALS
    upper = [np.full(4, np.inf)] * INTERVALS + [np.array([a, np.inf])] * INTERVALS
    return xs + us, lower, upper, cost, rows


IPOPT = {"print_time": False, "ipopt.print_level": 0, "ipopt.tol": 1e-12,
         "ipopt.bound_relax_factor": 0.0, "ipopt.max_iter": 3000}


def _dmoc_point_mass(start: np.ndarray, end: ca.MX, mass: float) -> Nlp:
    """A planar point mass's DMOC NLP (midpoint rule, L = ½ m |q̇|², F = u), at rest at both
    ends: variables (q_1..q_{N−1}, u), the discrete Euler–Lagrange equations with the
    boundary momenta, cost h Σ |u_k|²."""
    h = DURATION / INTERVALS
    inner = [ca.MX.sym(f"q{k}", 2) for k in range(1, INTERVALS)]
    us = [ca.MX.sym(f"u{k}", 2) for k in range(INTERVALS)]
    q = [ca.DM(start), *inner, end]
    rows = [-mass * (q[1] - q[0]) / h + h / 2 * us[0]]
    rows += [mass * (q[k] - q[k - 1]) / h - mass * (q[k + 1] - q[k]) / h
             + h / 2 * (us[k - 1] + us[k]) for k in range(1, INTERVALS)]
    rows.append(mass * (q[-1] - q[-2]) / h + h / 2 * us[-1])
    free = [np.full(2, np.inf)] * (2 * INTERVALS - 1)
    return inner + us, [-b for b in free], free, h * ca.sumsqr(ca.vertcat(*us)), rows


def _solve(variables: list[ca.MX], lower: list, upper: list, cost: ca.MX, rows: list,
           guess: np.ndarray) -> tuple[float, np.ndarray]:
    x = ca.vertcat(*variables)
    g = ca.vertcat(*rows)
    solver = ca.nlpsol("reference", "ipopt", {"x": x, "f": cost, "g": g}, IPOPT)
    out = solver(x0=guess, lbx=np.concatenate(lower), ubx=np.concatenate(upper), lbg=0, ubg=0)
    assert solver.stats()["success"], solver.stats()["return_status"]
    return float(out["f"]), np.asarray(out["x"]).ravel()


def _guess(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """A variable vector (x_1..x_N, u) from a path (N+1, 4) and controls (N, 2)."""
    return np.concatenate([x[1:].ravel(), u.ravel()])


def monolithic_circle(problem: FormationProblem, result) -> tuple[float, np.ndarray]:
    """All agents and the coupling in one IPOPT NLP: the potential's solutions on a circle
    are equidistant angles in the agents' order (counter-clockwise by start x, as the
    documented start), φ_i = θ + 2π rank_i / n, θ free. Returns (J*, φ)."""
    n = problem.agents
    rank = np.argsort(np.argsort(problem.starts[:, 0], kind="stable"))
    theta = ca.MX.sym("theta")
    variables, lower, upper, cost, rows, guess = [theta], [[-np.inf]], [[np.inf]], 0, [], []
    phi = theta + 2 * np.pi * rank / n
    first = float(np.asarray(result.phi)[np.argmin(rank)])
    guess.append([first])   # started at the answer's rotation, every path from its own
    for i, shape in enumerate(problem.shapes):
        end = RADIUS * ca.vertcat(ca.cos(phi[i]), ca.sin(phi[i]))
        if isinstance(shape, MsEndpointShape):
            limit = None if shape.control_bounds is None else shape.control_bounds[0][1]
            v, lo, hi, c, r = _agent_nlp(problem.starts[i], end, limit)
            guess.append(_guess(result.trajectories[i], result.controls[i]))
        else:   # a point mass (a mixed fleet): its path is the first two entries
            v, lo, hi, c, r = _dmoc_point_mass(problem.starts[i, :2], end, shape.model.mass)
            guess.append(np.concatenate([result.trajectories[i, 1:-1, :2].ravel(),
                                         result.controls[i].ravel()]))
        variables += v
        lower += lo
        upper += hi
        cost += c
        rows += r
    value, x = _solve(variables, lower, upper, cost, rows, np.concatenate(guess))
    return value, x[0] + 2 * np.pi * rank / n


# ------------------------------------------------------------------------------------------
# fixtures: each run once
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def circle():
    problem = make(agents=AGENTS, radius=RADIUS, duration=DURATION, intervals=INTERVALS)
    return problem, solve_formation(problem)


@pytest.fixture(scope="module")
def mixed():
    problem = make(agents=AGENTS, radius=RADIUS, duration=DURATION, intervals=INTERVALS,
                   mixed=True)
    return problem, solve_formation(problem)


@pytest.fixture(scope="module")
def slots():
    problem = make(agents=AGENTS, radius=RADIUS, duration=DURATION, intervals=INTERVALS,
                   slots=AGENTS, acceleration_limit=ACCELERATION_LIMIT)
    return problem, solve_formation(problem)


# ------------------------------------------------------------------------------------------
# the inner problem
# ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("limit", [None, 0.9])
def test_inner_derivatives_are_the_finite_differences(limit):
    """dJ*/dp (all 2 nx entries) and d²J*/dx̄_N² (the fixed end entries) against central
    differences of re-solves; with a bound on a that is active, from the active set."""
    bounds = None if limit is None else ((-limit, limit), (-np.inf, np.inf))
    shape = MsEndpointShape(Unicycle(), intervals=INTERVALS, duration=DURATION, free_end=(2,),
                            control_bounds=bounds)
    nlp = transcription(shape)
    p = np.array([-1.0, -5.0, np.pi / 2, 0.0, 2.0, 1.0, 0.0, 0.0])
    sol = nlp.solve(p)
    assert sol.success
    if limit is not None:
        assert np.isclose(np.max(np.abs(sol.u[:, 0])), limit, rtol=0, atol=1e-9)
    guess = nlp.warm_start(sol)
    step = 1e-5
    for i in range(len(p)):
        if i == 6:   # the free heading: p does not enter
            assert sol.cost_gradient[i] == 0 and not np.any(sol.end_hessian[2])
            continue
        up, down = p.copy(), p.copy()
        up[i] += step
        down[i] -= step
        plus, minus = nlp.solve(up, guess), nlp.solve(down, guess)
        assert plus.success and minus.success
        slope = (plus.cost - minus.cost) / (2 * step)
        assert abs(slope - sol.cost_gradient[i]) <= 1e-6 * (1 + abs(slope))
        if i >= 4:
            fixed = [0, 1, 3]
            curvature = (plus.cost_gradient - minus.cost_gradient)[4:][fixed] / (2 * step)
            assert np.allclose(curvature, sol.end_hessian[i - 4][fixed], rtol=1e-5,
                               atol=1e-6)


def test_batched_solves_are_the_one_by_one_solves_bitwise():
    """From a previous solution (a formation's later supersteps) the batched Newton solves
    k tasks in one call, each as alone."""
    shape = MsEndpointShape(Unicycle(), intervals=INTERVALS, duration=DURATION, free_end=(2,))
    nlp = transcription(shape)
    p = np.array([-1.0, -5.0, np.pi / 2, 0.0, 2.0, 1.0, 0.0, 0.0])
    base = nlp.solve(p)
    params = np.tile(p, (5, 1))
    params[:, 4] += np.linspace(0.0, 0.2, 5)
    guesses = np.tile(nlp.warm_start(base), (5, 1))
    batch = nlp.solve_batch(params, guesses, [None] * 5)
    assert batch is not None and all(batch.column("success"))
    for k in range(5):
        alone = nlp.solve_batch(params[k:k + 1], guesses[k:k + 1], [None])
        for name in ("cost", "cost_gradient", "end_hessian", "q", "u"):
            assert np.array_equal(np.asarray(batch.column(name))[k],
                                  np.asarray(alone.column(name))[0])
        reference = nlp.solve(params[k], guesses[k])   # IPOPT, one task
        assert abs(reference.cost - batch.column("cost")[k]) <= 1e-10 * reference.cost


# ------------------------------------------------------------------------------------------
# the formations
# ------------------------------------------------------------------------------------------

def test_unicycles_onto_a_circle_equal_the_monolithic_nlp(circle):
    problem, result = circle
    assert result.status == "converged", result.message
    assert result.failed_solves == 0 and result.verification.passed
    value, phi = monolithic_circle(problem, result)
    assert abs(result.total_cost - value) <= 1e-8 * value
    gap = np.angle(np.exp(1j * (np.asarray(result.phi) - phi)))
    assert np.max(np.abs(gap)) <= 1e-8
    # the paths end at rest on the circle, heading free
    ends = result.trajectories[:, -1]
    assert np.allclose(np.hypot(ends[:, 0], ends[:, 1]), RADIUS, rtol=0, atol=1e-12)
    assert np.max(np.abs(ends[:, 3])) <= 1e-12


def test_a_fleet_of_point_masses_and_unicycles_equals_the_monolithic_nlp(mixed):
    """Every second agent a DMOC point mass: each kind solved by its own transcription,
    batched kind by kind; the formation equals one NLP of both (written here)."""
    problem, result = mixed
    assert problem.mixed_kinds and result.status == "converged", result.message
    assert result.verification.passed and result.failed_solves == 0
    checks = result.verification.checks
    assert checks["momentum"].value <= 1e-12 and checks["dynamics"].value <= 1e-12
    # the point masses' paths are padded: two entries, then NaN
    assert result.trajectories.shape == (AGENTS, INTERVALS + 1, 4)
    assert np.all(np.isnan(result.trajectories[::2, :, 2:]))
    assert np.all(np.isfinite(result.trajectories[1::2]))
    value, phi = monolithic_circle(problem, result)
    assert abs(result.total_cost - value) <= 1e-8 * value
    assert np.max(np.abs(np.angle(np.exp(1j * (np.asarray(result.phi) - phi))))) <= 1e-8


@pytest.fixture(scope="module")
def bounded():
    """Four unicycles onto the circle under |a| ≤ 0.8 (active: the free peak is higher)."""
    problem = make(agents=4, radius=RADIUS, duration=DURATION, intervals=INTERVALS,
                   acceleration_limit=0.8)
    return problem, solve_formation(problem)


@pytest.mark.parametrize("case", ["circle", "mixed", "bounded"])
def test_the_monolithic_mode_takes_ode_agents(case, circle, mixed, bounded):
    """``--mode monolithic``: one IPOPT NLP of every agent's own transcription (unicycles,
    point masses and unicycles, an active bound) and the coupling, equal to the hierarchical
    answer and to the NLP written here."""
    problem, result = {"circle": circle, "mixed": mixed, "bounded": bounded}[case]
    assert result.status == "converged", result.message
    mono = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert mono.status == "converged" and mono.verification.passed, mono.message
    assert mono.verification.checks["dynamics"].value <= 1e-12
    assert abs(mono.total_cost - result.total_cost) <= 1e-8 * result.total_cost
    assert np.max(np.abs(np.angle(np.exp(1j * (np.asarray(mono.phi) - result.phi))))) <= 1e-8
    value, _ = monolithic_circle(problem, result)
    assert abs(mono.total_cost - value) <= 1e-8 * value
    if case == "bounded":
        assert np.max(np.abs(mono.controls[..., 0])) >= 0.8 - 1e-9


@pytest.mark.slow
def test_phase_one_refuses_an_unreachable_bound_in_few_supersteps():
    """|a| ≤ 0.6 for four unicycles: no rotation lets every robot reach its place, and the
    NLP written here says so at every rotation of a grid (some agent's is infeasible);
    phase 1 ends ``failed`` with its smallest total slack, its descents started from the
    scan's local minima only (75 supersteps; 1101 before, smallest slack 1.072 against 1.057)."""
    problem = make(agents=4, radius=RADIUS, duration=DURATION, intervals=INTERVALS,
                   acceleration_limit=0.6)
    result = solve_formation(problem)
    assert result.status == "failed", result.message
    assert result.message.startswith("no feasible formation: phase 1")
    assert len(result.trace) <= 100
    rank = np.argsort(np.argsort(problem.starts[:, 0], kind="stable"))
    for theta in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        phi = theta + 2 * np.pi * rank / 4
        reachable = []
        for i in range(4):
            end = ca.DM(RADIUS * np.array([np.cos(phi[i]), np.sin(phi[i])]))
            v, lo, hi, c, r = _agent_nlp(problem.starts[i], end, 0.6)
            x = ca.vertcat(*v)
            solver = ca.nlpsol("reach", "ipopt", {"x": x, "f": c, "g": ca.vertcat(*r)}, IPOPT)
            solver(x0=np.zeros(x.numel()), lbx=np.concatenate(lo), ubx=np.concatenate(hi),
                   lbg=0, ubg=0)
            reachable.append(solver.stats()["success"])
        assert not all(reachable), theta


def test_the_verification_re_integrates_the_returned_controls(circle):
    problem, result = circle
    checks = result.verification.to_dict()["checks"]
    assert checks["dynamics"]["worst"] <= 1e-12 and checks["attitude"]["worst"] <= 1e-12
    # a path off by 1e-4 at one node breaks its shooting residual there
    q = result.trajectories.copy()
    q[3, 7, 2] += 1e-4
    broken = verify_formation(problem, q, result.controls, result.phi)
    assert [name for name, check in broken.checks.items() if not check.passed] == ["dynamics"]
    assert "shooting residual" in broken.failures[0]
    assert broken.checks["dynamics"].agent == 3
    assert 1e-5 < broken.checks["dynamics"].value < 1e-4


def test_euler_and_several_steps_per_interval_are_options(circle):
    """Three Euler steps per interval: its own formation, verified by re-integrating with
    three Euler steps; the RK4 answer checked as if Euler fails the shooting check."""
    problem, rk4 = circle
    euler = problem.with_shapes(lambda s: dataclasses.replace(s, integrator="euler", steps=3))
    result = solve_formation(euler)
    assert result.status == "converged" and result.verification.passed
    assert 1e-6 < abs(result.total_cost - rk4.total_cost) / rk4.total_cost < 1e-2
    mismatch = verify_formation(euler, rk4.trajectories, rk4.controls, rk4.phi)
    assert not mismatch.checks["dynamics"].passed


def test_unicycles_onto_slots_with_an_active_bound_are_the_optimal_assignment(slots):
    """Onto slots only the assignment is free: the package's total equals the optimal
    assignment over the cost table of the NLP written here (each agent to each slot)."""
    problem, result = slots
    assert result.status == "converged", result.message
    assert result.verification.passed and "control_bounds" in result.verification.checks
    assert np.isclose(np.max(np.abs(result.controls[..., 0])), ACCELERATION_LIMIT, rtol=0,
                      atol=1e-9)
    points = problem.curve.points
    start, end = ca.MX.sym("start", 4), ca.MX.sym("end", 2)
    v, lo, hi, c, r = _agent_nlp(start, end, ACCELERATION_LIMIT)
    solver = ca.nlpsol("pair", "ipopt", {"x": ca.vertcat(*v), "p": ca.vertcat(start, end),
                                         "f": c, "g": ca.vertcat(*r)}, IPOPT)
    table = np.empty((AGENTS, len(points)))
    s = np.linspace(0, 1, INTERVALS + 1)[1:, None]
    for i, j in itertools.product(range(AGENTS), range(len(points))):
        x0 = problem.starts[i]
        line = x0 + s * (np.r_[points[j], x0[2], 0.1] - x0)
        out = solver(x0=np.concatenate([line.ravel(), np.full(2 * INTERVALS, 0.01)]),
                     p=np.r_[x0, points[j]], lbx=np.concatenate(lo), ubx=np.concatenate(hi),
                     lbg=0, ubg=0)
        status = solver.stats()["return_status"]
        assert solver.stats()["success"] or status == "Infeasible_Problem_Detected", status
        table[i, j] = float(out["f"]) if solver.stats()["success"] else 1e9  # out of reach
    rows, cols = linear_sum_assignment(table)
    best = table[rows, cols].sum()
    assert abs(result.total_cost - best) <= 1e-8 * best
    assert np.array_equal(np.asarray(result.phi, int), cols)
    assert np.allclose(result.agent_costs, table[rows, cols], rtol=1e-8, atol=0)


def test_every_outer_solver_and_active_path_constraints(circle):
    """The three outer solvers reach the same formation; a speed limit (a row of x) and a
    turn-rate limit (a row of u), both active, solved by the batched sqpmethod equal IPOPT's
    solves, and the returned paths meet them (the verification's own evaluation)."""
    problem, newton = circle
    for outer in ("sqp", "offset"):
        other = solve_formation(problem, options=FormationOptions(outer=outer))
        assert other.status == "converged", other.message
        assert abs(other.total_cost - newton.total_cost) <= 1e-11 * newton.total_cost
    speed = PathConstraint(lambda x: x[3], upper=1.8, name="speed")
    turn = PathConstraint(lambda u: u[1], lower=-0.2, upper=0.2, name="turn")
    limited = problem.with_shapes(lambda s: dataclasses.replace(
        s, path_constraints=(speed, turn)))
    batched = solve_formation(limited)
    alone = solve_formation(limited, options=FormationOptions(inner_solver="ipopt"))
    for result in (batched, alone):
        assert result.status == "converged" and result.verification.passed
        assert "path_constraints" in result.verification.checks
    assert np.isclose(np.max(batched.trajectories[..., 3]), 1.8, rtol=0, atol=1e-9)
    assert np.isclose(np.max(np.abs(batched.controls[..., 1])), 0.2, rtol=0, atol=1e-9)
    assert batched.total_cost > newton.total_cost * (1 + 1e-3)
    assert abs(batched.total_cost - alone.total_cost) <= 1e-10 * alone.total_cost


@dataclasses.dataclass(frozen=True)
class DoubleIntegrator:
    """A user's ODE agent: x = (position, velocity) in ``dim`` dimensions, u the
    acceleration, cost |u|²."""

    dim: int = 3

    @property
    def nx(self) -> int:
        return 2 * self.dim

    @property
    def nu(self) -> int:
        return self.dim

    @property
    def position_indices(self) -> tuple[int, ...]:
        return tuple(range(self.dim))

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.vertcat(x[self.dim:], u)

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.sumsqr(u)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self.nx, -np.inf), np.full(self.nx, np.inf)


def test_other_targets_and_couplings():
    """An ellipse under equal arc length (unicycles) and a sphere (a user's ODE model in
    space, two parameters per agent): converged and verified (target, coupling, shooting)."""
    problem = make(agents=6)
    ellipse = dataclasses.replace(problem, curve=Ellipse(semi_axes=(3.0, 2.0)),
                                  coupling=EqualArcLength())
    n = 6
    starts = np.column_stack([np.linspace(-3, 3, n), np.full(n, -5.0), np.zeros((n, 4))])
    sphere = FormationProblem("space", MsEndpointShape(DoubleIntegrator(), duration=2.0),
                              SphereSurface(radius=2.0), starts, final_state=np.zeros(3))
    for case in (ellipse, sphere):
        result = solve_formation(case)
        assert result.status == "converged", result.message
        assert result.verification.passed and result.outer_iterations >= 1
        assert result.verification.checks["dynamics"].value <= 1e-12


def test_the_optimal_ordering_of_unicycles_claims_no_bound():
    """On a circle the search over assignments and rotation runs on ODE agents too; their
    inner problems are not known to be convex in the end position: no bound is claimed."""
    problem = make(agents=6)
    kept = solve_formation(problem)
    best = solve_formation(problem, options=FormationOptions(ordering="optimal"))
    assert best.status == "converged" and best.verification.passed
    assert "no bound claimed" in best.message and best.ordering["bound"] is None
    assert best.total_cost < kept.total_cost * (1 - 1e-3)


def test_linear_quadratic_ode_agents_get_a_proven_optimal_ordering():
    """Linear dynamics, a quadratic cost, no inequalities: J* is a convex quadratic of the
    end point (end_cost_convexity), so the ordering's search proves its global optimum."""
    assert end_cost_convexity(MsEndpointShape(DoubleIntegrator(2))) == "quadratic"
    assert end_cost_convexity(MsEndpointShape(Unicycle())) is None
    n = 8
    starts = np.random.default_rng(3).uniform(-4, 4, (n, 2)) + np.array([0.0, -6.0])
    problem = FormationProblem("di", MsEndpointShape(DoubleIntegrator(2), duration=2.0),
                               Circle(radius=3.0), np.hstack([starts, np.zeros((n, 2))]),
                               final_state=np.zeros(2))
    best = solve_formation(problem, options=FormationOptions(ordering="optimal"))
    assert best.status == "converged" and best.verification.passed
    assert best.ordering["proven"] and best.ordering["gap"] <= 1e-8
    assert best.total_cost < solve_formation(problem).total_cost


def test_configuration_is_described_by_the_agents_kind(circle, mixed):
    """result.nc's ``configuration``: an ODE fleet's node states, a mixed fleet's in neutral
    words, a DMOC fleet's configurations."""
    from ocpar.examples import formation_point_masses
    from ocpar.formation.result import NODE_PATHS, Units

    def described(result) -> str:
        return result.arrays()["configuration"][2]["long_name"]

    assert described(circle[1]) == NODE_PATHS["ms"] and "state x_k" in NODE_PATHS["ms"]
    assert described(mixed[1]) == NODE_PATHS["mixed"] and "DMOC" in NODE_PATHS["mixed"]
    point_masses = formation_point_masses.make(agents=3)
    assert Units.of_fleet(point_masses).node_path == NODE_PATHS["dmoc"]
    assert "DMOC node path" in NODE_PATHS["dmoc"]


def test_what_ode_agents_do_not_offer_yet_is_refused_in_one_line():
    problem = make(agents=3)
    with pytest.raises(ValueError, match=r"^separation 'exact': not yet for ODE agents"):
        solve_formation(problem, options=FormationOptions(min_separation=0.1))
    with pytest.raises(ValueError, match=r"^min_separation: not yet for a fleet of agents"):
        solve_formation(make(agents=4, mixed=True), options=FormationOptions(
            min_separation=0.1, separation="rounds"))
    with pytest.raises(ValueError, match=r"^final_velocity: DMOC agents' field"):
        FormationProblem("x", problem.shape, problem.curve, problem.starts,
                         final_velocity=np.zeros(4))
    with pytest.raises(ValueError, match=r"^final_state: must be finite"):
        FormationProblem("x", problem.shape, problem.curve, problem.starts,
                         final_state=[0.0, np.nan])
    with pytest.raises(ValueError, match=r"^free_end: "):
        MsEndpointShape(Unicycle(), free_end=(0,))


# ------------------------------------------------------------------------------------------
# backends: serial, mpirun -n 2, two Dask workers
# ------------------------------------------------------------------------------------------

CONFIG = """\
scheme = "formation"
problem = "ocpar.examples.formation_unicycles:make"
quiet = true

[problem_args]
agents = 8
"""


@pytest.fixture(scope="module")
def backend_runs(tmp_path_factory):
    """The circle and the bounded slots by ``ocpar run``, each run once on first use:
    ``runs(case, backend)`` with backend serial, mpi (mpirun -n 2) or dask (a two-worker
    cluster, started once)."""
    work = tmp_path_factory.mktemp("unicycles")
    (work / "circle.toml").write_text(CONFIG)
    (work / "mixed.toml").write_text(CONFIG + "mixed = true\n")
    (work / "slots.toml").write_text(CONFIG + f"slots = 8\nacceleration_limit = "
                                     f"{ACCELERATION_LIMIT}\n")
    results: dict[tuple[str, str], dict] = {}

    def run(case: str, backend: str) -> dict:
        if (case, backend) not in results:
            out = work / f"{case}-{backend}"
            args, kwargs = [], {}
            if backend == "mpi":
                kwargs["mpi_ranks"] = 2
            if backend == "dask":
                if "cluster" not in results:
                    results["cluster"] = stack.enter_context(local_cluster())
                args = ["--scheduler", results["cluster"]]
            proc = run_ocpar(work, work, "run", f"{case}.toml", "--output", str(out), *args,
                             **kwargs)
            assert proc.returncode == 0, proc.stderr
            results[case, backend] = read_result(out)
        return results[case, backend]

    with contextlib.ExitStack() as stack:
        yield run


def _same_as_serial(runs, case: str, backend: str, reference) -> None:
    serial = runs(case, "serial")
    assert serial["status"] == "converged" and serial["verification"]["passed"]
    other = runs(case, backend)
    assert other["backend"] == backend and other["workers"] == 2
    assert computed(other) == computed(serial)
    # the run's files say what the Python API's result says
    assert serial["total_cost"] == reference.total_cost
    assert serial["verification"]["checks"]["dynamics"]["worst"] <= 1e-12


@pytest.mark.parametrize("case", ["circle", "slots",
                                  pytest.param("mixed", marks=pytest.mark.slow)])
def test_mpirun_gives_the_serial_result_bitwise(backend_runs, case, circle, slots, mixed):
    reference = {"circle": circle, "slots": slots, "mixed": mixed}[case][1]
    _same_as_serial(backend_runs, case, "mpi", reference)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["circle", "slots", "mixed"])
def test_dask_gives_the_serial_result_bitwise(backend_runs, case, circle, slots, mixed):
    reference = {"circle": circle, "slots": slots, "mixed": mixed}[case][1]
    _same_as_serial(backend_runs, case, "dask", reference)
