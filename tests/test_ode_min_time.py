"""The minimum final time of a fleet of ODE agents (:class:`~ocpar.ocp.MsEndpointShape`):
four double integrators (ẋ = v, v̇ = u, |u_j| ≤ U) from rest onto a circle at rest, the
bracket by phase-1 bisection against the same discretisation's minimum time computed here
independently: piecewise-constant u on N intervals under RK4 is exact for this linear
system, so the end state is linear in u and "displacement d reachable in T" is an LP per
axis (scipy's linprog), bisected in T for the rotation and assignment the run returns."""

from __future__ import annotations

import itertools

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import linprog

from ocpar.formation import Circle, FormationOptions, FormationProblem, solve_formation
from ocpar.models.expressions import ode_model
from ocpar.ocp import MsEndpointShape
from ocpar.ocp.obstacles import Sphere

LIMIT = 1.0
INTERVALS = 8
RADIUS = 2.0
TOL = 1e-2
STARTS = np.array([[-1.5, -4.0, 0, 0], [-0.5, -4.2, 0, 0], [0.6, -3.9, 0, 0],
                   [1.4, -4.1, 0, 0]])


def _double_integrator():
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 2)
    return ode_model(x, u, [x[2], x[3], u[0], u[1]], ca.sumsqr(u), position_indices=[0, 1])


def _reachable(d: float, duration: float) -> bool:
    """An axis moved by ``d`` from rest to rest in ``duration`` under |u| ≤ LIMIT: the exact
    discrete end state v_N = h Σ u_k = 0, p_N = h² Σ (N − k − ½) u_k = d, as an LP."""
    h = duration / INTERVALS
    k = np.arange(INTERVALS)
    a_eq = np.vstack([np.full(INTERVALS, h), h**2 * (INTERVALS - k - 0.5)])
    lp = linprog(np.zeros(INTERVALS), A_eq=a_eq, b_eq=[0.0, d],
                 bounds=[(-LIMIT, LIMIT)] * INTERVALS, method="highs")
    return lp.status == 0


def _least_time(d: float) -> float:
    """The least T at which ``d`` is reachable on one axis (bisection to 1e-9 relative)."""
    low, high = 1e-3, 100.0
    assert _reachable(d, high)
    while high - low > 1e-9 * high:
        middle = 0.5 * (low + high)
        low, high = (low, middle) if _reachable(d, middle) else (middle, high)
    return high


@pytest.fixture(scope="module")
def result():
    shape = MsEndpointShape(_double_integrator(), intervals=INTERVALS, duration=4.0,
                            control_bounds=((-LIMIT, LIMIT),) * 2)
    problem = FormationProblem(name="double integrators", shape=shape,
                               curve=Circle(radius=RADIUS), starts=STARTS,
                               final_state=np.zeros(2))
    options = FormationOptions(final_time="minimum", time_bounds=(2.0, 8.0), time_tol=TOL)
    return solve_formation(problem, options=options)


def test_bracket_holds_the_discrete_minimum_time(result):
    """T_lo ≤ T*(returned formation) ≤ T_hi, T* the LP bisection's bottleneck over agents
    and axes; the bracket as narrow as asked; solved and verified at T_hi."""
    assert result.status == "converged", result.message
    low, high = result.final_time["bracket"]
    assert high * (1 - TOL) <= low <= high
    assert result.final_time["method"] == "phase 1" and not result.final_time["proven"]
    phi = np.asarray(result.phi, float)
    ends = RADIUS * np.column_stack([np.cos(phi), np.sin(phi)])
    needed = max(_least_time(abs(d)) for d in (ends - STARTS[:, :2]).ravel())
    assert low * (1 - 1e-6) <= needed <= high * (1 + 1e-6)
    assert result.final_time["T"] == high
    assert result.fleet.duration == high
    assert result.verification is not None and result.verification.passed
    assert np.allclose(result.trajectories[:, -1, :2], ends, atol=1e-6)
    assert np.max(np.abs(result.controls)) <= LIMIT * (1 + 1e-6)


#: A disc between the starts and the circle (centre, radius), kept out on the polyline
#: through each interval's two RK4 sub-step states.
DISC = ((0.0, -3.0), 0.5)


def _clear_at(duration: float, start: np.ndarray, end: np.ndarray, guess: np.ndarray
              ) -> bool:
    """Whether a double integrator reaches ``end`` at rest from ``start`` at rest in
    ``duration`` under |u_j| ≤ LIMIT with its polyline clear of the disc: an NLP written
    here (RK4 is exact on it: p + h v + h²/2 u, v + h u per sub-step), IPOPT from the
    controls ``guess`` (N, 2)."""
    h = duration / INTERVALS / 2
    center, radius = ca.DM(DISC[0]), DISC[1]
    us = [ca.SX.sym(f"u{k}", 2) for k in range(INTERVALS)]
    p, v, points = ca.DM(start[:2]), ca.DM(start[2:]), [ca.DM(start[:2])]
    for u in us:
        for _ in range(2):
            p, v = p + h * v + h**2 / 2 * u, v + h * u
            points.append(p)
    rows = []
    for a, b in itertools.pairwise(points):
        ya, yb = (a - center) / radius, (b - center) / radius
        step = yb - ya
        s = ca.fmin(ca.fmax(-ca.dot(ya, step) / ca.fmax(ca.dot(step, step), 1e-12), 0), 1)
        rows.append(ca.sumsqr(ya + s * step) - 1)
    g = ca.vertcat(p - ca.DM(end), v, *rows)
    solver = ca.nlpsol("clear", "ipopt", {"x": ca.vertcat(*us), "f": ca.sumsqr(ca.vertcat(*us)),
                                          "g": g},
                       {"print_time": False, "ipopt.print_level": 0, "ipopt.tol": 1e-10})
    out = solver(x0=guess.ravel(), lbx=-LIMIT, ubx=LIMIT,
                 lbg=np.r_[np.zeros(4), np.zeros(len(rows))],
                 ubg=np.r_[np.zeros(4), np.full(len(rows), np.inf)])
    return bool(solver.stats()["success"]) and np.all(np.isfinite(np.asarray(out["x"])))


@pytest.mark.slow
def test_the_minimum_time_past_a_disc_is_bracketed():
    """ODE agents past a disc (it crashed phase 1: a zero-length chord of a guess at rest
    made the keep-out rows' Hessian NaN): the bracket as narrow as asked, each agent's
    target reachable at T_hi clear of the disc (the NLP written here), phase 1 above its
    tolerance at T_hi (1 − tol), and T_hi no earlier than the disc-free minimum of the same
    targets (the LP bisection)."""
    shape = MsEndpointShape(_double_integrator(), intervals=INTERVALS, duration=4.0, steps=2,
                            control_bounds=((-LIMIT, LIMIT),) * 2)
    problem = FormationProblem(name="past a disc", shape=shape, curve=Circle(radius=RADIUS),
                               starts=STARTS, final_state=np.zeros(2),
                               obstacles=(Sphere(*DISC),))
    result = solve_formation(problem, options=FormationOptions(
        final_time="minimum", time_bounds=(2.0, 8.0), time_tol=TOL))
    assert result.status == "converged" and result.verification.passed, result.message
    low, high = result.final_time["bracket"]
    assert high * (1 - TOL) <= low <= high
    assert result.final_time["phase_one_slack"] > 1e-8
    assert result.obstacle_clearance.distance >= -1e-9
    phi = np.asarray(result.phi, float)
    ends = RADIUS * np.column_stack([np.cos(phi), np.sin(phi)])
    assert all(_clear_at(high, STARTS[i], ends[i], result.controls[i])
               for i in range(len(STARTS)))
    free = max(_least_time(abs(d)) for d in (ends - STARTS[:, :2]).ravel())
    assert high >= free * (1 - 1e-6)
