"""Reference Pareto fronts of the MACS test problems (§V) and the front quality metrics.

The packaged fronts are checked against independent computations: a Radau collocation NLP
(IPOPT, exact derivatives) written here for both problems, pymoo's GD/IGD and a 2-D
rectangle sum for the hypervolume.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np
import pytest
from pymoo.indicators.gd import GD
from pymoo.indicators.igd import IGD
from scipy.integrate import solve_ivp

from ocpar.macs.metrics import (
    generational_distance,
    hypervolume,
    inverted_generational_distance,
    normalise,
)
from ocpar.macs.reference import (
    GODDARD_A,
    GODDARD_G,
    GODDARD_H,
    ORBIT_A,
    ORBIT_X0,
    goddard_max_vx,
    goddard_min_time,
    orbit_raising_max_energy,
    reference_front,
)


def radau_optimum(rhs: Callable, x0: np.ndarray, tf: float | None, n: int,
                  objective: Callable, terminal: Callable, u_bounds: tuple[float, float],
                  guess: Callable, degree: int = 4) -> float:
    """Optimal objective of an OCP by Radau collocation (n intervals, ``degree`` points each,
    one control per point), in normalised time; ``tf=None`` makes t_f a variable in [100, 250].
    ``guess(τ)`` gives (states (nx, len τ), controls (len τ,))."""
    tau = np.append(0.0, ca.collocation_points(degree, "radau"))
    deriv = np.zeros((degree + 1, degree + 1))  # deriv[j, r] = l_j'(τ_r)
    for j in range(degree + 1):
        basis = np.poly1d([1.0])
        for r in range(degree + 1):
            if r != j:
                basis *= np.poly1d([1.0, -tau[r]]) / (tau[j] - tau[r])
        deriv[j] = np.polyder(basis)(tau)
    nx, d = len(x0), degree
    xs, xc = ca.SX.sym("xs", nx), ca.SX.sym("xc", nx, d)
    uc, span = ca.SX.sym("uc", 1, d), ca.SX.sym("T")
    pts = ca.horzcat(xs, xc)
    res = [pts @ deriv[:, j] - span / n * rhs(xc[:, j - 1], uc[j - 1]) for j in range(1, d + 1)]
    defect = ca.Function("defect", [xs, xc, uc, span], [ca.horzcat(*res)]).map(n)
    w_mat = ca.SX.sym("w", nx * d + d, n)
    ends = w_mat[nx * (d - 1):nx * d, :]
    final_time = ca.SX.sym("tf") if tf is None else tf
    g = defect(ca.horzcat(ca.DM(x0), ends[:, :-1]), ca.reshape(w_mat[:nx * d, :], nx, d * n),
               ca.reshape(w_mat[nx * d:, :], 1, d * n), final_time)
    xf = ends[:, -1]
    w = ca.vec(w_mat)
    if tf is None:
        w = ca.vertcat(w, final_time)
    solver = ca.nlpsol("radau", "ipopt",
                       {"x": w, "f": objective(xf, final_time),
                        "g": ca.vertcat(ca.vec(g), *terminal(xf))},
                       {"print_time": False,
                        "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-12, "max_iter": 3000}})
    times = ((np.arange(n)[:, None] + tau[1:][None, :]) / n).ravel()
    xg, ug = guess(times)
    w0 = np.vstack([xg.reshape(nx, n, d).transpose(2, 0, 1).reshape(d * nx, n),
                    ug.reshape(n, d).T])
    lb, ub = np.full(w0.shape, -np.inf), np.full(w0.shape, np.inf)
    lb[nx * d:], ub[nx * d:] = u_bounds
    w0, lb, ub = (a.ravel(order="F") for a in (w0, lb, ub))
    if tf is None:
        w0, lb, ub = np.append(w0, 150.0), np.append(lb, 100.0), np.append(ub, 250.0)
    sol = solver(x0=w0, lbx=lb, ubx=ub, lbg=0, ubg=0)
    assert solver.stats()["success"], solver.stats()["return_status"]
    return float(sol["f"])


def goddard_rhs(x, u):
    return ca.vertcat(x[1], GODDARD_A * ca.cos(u), x[3], -GODDARD_G + GODDARD_A * ca.sin(u))


def goddard_guess(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.vstack([0 * t, 0.5 * t, GODDARD_H * t, 0 * t]), 0.5 - t


def goddard_terminal(xf) -> list:
    return [xf[2] - GODDARD_H, xf[3]]


def orbit_rhs(x, u):
    r, vr, vt = x[0], x[1], x[3]
    return ca.vertcat(vr, vt**2 / r - 1 / r**2 + ORBIT_A * ca.cos(u), vt / r,
                      -vt * vr / r + ORBIT_A * ca.sin(u))


@pytest.fixture(scope="module")
def goddard() -> np.ndarray:
    return reference_front("goddard")


@pytest.fixture(scope="module")
def orbit() -> np.ndarray:
    return reference_front("orbit-raising")


def row_near(front: np.ndarray, tf: float) -> np.ndarray:
    return front[np.argmin(np.abs(front[:, 0] - tf))]


# --- Goddard ---------------------------------------------------------------------------------

def test_goddard_front_spans_min_time_to_250(goddard):
    assert goddard.shape == (400, 2)
    assert goddard[0, 0] == goddard_min_time() == pytest.approx(109.10894511799619, rel=1e-14)
    assert goddard[0, 1] == 0.0 and goddard[-1, 0] == 250.0
    assert np.all(np.diff(goddard[:, 0]) > 0) and np.all(np.diff(goddard[:, 1]) < 0)


def test_goddard_smallest_tf_is_the_minimum_time():
    """Minimum time with v_x(t_f) free, by direct collocation with t_f free."""
    t_min = radau_optimum(goddard_rhs, np.zeros(4), None, 50, lambda xf, tf: tf / 100,
                          goddard_terminal, (-np.pi / 2, np.pi / 2), goddard_guess) * 100
    assert t_min == pytest.approx(goddard_min_time(), rel=1e-9)


@pytest.mark.parametrize("tf", [120.0, 180.0, 250.0])
def test_goddard_front_matches_direct_optimum(goddard, tf):
    t, j2 = row_near(goddard, tf)
    direct = radau_optimum(goddard_rhs, np.zeros(4), t, 60, lambda xf, _: -xf[1],
                           goddard_terminal, (-np.pi / 2, np.pi / 2), goddard_guess)
    assert j2 == pytest.approx(direct, rel=1e-8)


def test_goddard_csv_is_what_the_shooting_gives(goddard):
    t, j2 = goddard[200]
    vx, (u0, uf) = goddard_max_vx(t)
    assert -vx == pytest.approx(j2, rel=1e-11)
    assert -np.pi / 2 < uf < 0 < u0 < np.pi / 2  # linear tangent law: u decreasing


# --- orbit raising ---------------------------------------------------------------------------

def test_orbit_front_is_monotone(orbit):
    assert orbit.shape == (200, 2)
    np.testing.assert_allclose(orbit[:, 0], np.linspace(20.0, 80.0, 200), rtol=1e-15)
    assert np.all(np.diff(orbit[:, 1]) < 0)  # more time, more energy


@pytest.mark.parametrize("tf", [35.0, 65.0])
def test_orbit_front_matches_an_independent_solve(orbit, tf):
    t, j2 = row_near(orbit, tf)

    def aligned(_, s):  # thrust along the velocity: the guess
        r, vr, _, vt = s
        v = np.hypot(vr, vt)
        return [vr, vt**2 / r - 1 / r**2 + ORBIT_A * vr / v, vt / r,
                -vt * vr / r + ORBIT_A * vt / v]

    sim = solve_ivp(aligned, (0.0, t), ORBIT_X0, dense_output=True, rtol=1e-10, atol=1e-12)

    def guess(tau):
        x = sim.sol(tau * t)
        return x, np.arctan2(x[3], x[1])

    direct = radau_optimum(orbit_rhs, ORBIT_X0, t, 200,
                           lambda xf, _: -((xf[1] ** 2 + xf[3] ** 2) / 2 - 1 / xf[0]),
                           lambda xf: [], (-np.pi, np.pi), guess)
    assert j2 == pytest.approx(direct, abs=1e-9)  # |J2| ≥ 0.02 here: ≤ 5e-8 relative


def test_orbit_csv_is_what_the_transcription_gives(orbit):
    """A cold solve (thrust-along-velocity guess) at K = 1600 reproduces a warm-started row."""
    t, j2 = orbit[100]
    energy, samples = orbit_raising_max_energy(t, 1600)
    assert -energy == pytest.approx(j2, abs=1e-9)
    assert samples.shape == (3201, 5) and np.all(np.abs(samples[:, 4]) < np.pi)


# --- metrics ---------------------------------------------------------------------------------

@pytest.fixture(scope="module", params=["goddard", "orbit-raising"])
def fronts(request) -> tuple[np.ndarray, np.ndarray]:
    """(reference, an approximation: 60 reference points perturbed by ~1 % of the range)."""
    reference = reference_front(request.param)
    rng = np.random.default_rng(7)
    rows = reference[rng.choice(len(reference), 60, replace=False)]
    span = reference.max(axis=0) - reference.min(axis=0)
    return reference, rows + 0.01 * span * rng.standard_normal(rows.shape)


def test_normalise_maps_the_reference_onto_the_unit_square(fronts):
    reference, _ = fronts
    scaled = normalise(reference, reference)
    np.testing.assert_array_equal(scaled.min(axis=0), [0.0, 0.0])
    np.testing.assert_array_equal(scaled.max(axis=0), [1.0, 1.0])


def test_gd_and_igd_agree_with_pymoo(fronts):
    reference, front = fronts
    ref_n, front_n = normalise(reference, reference), normalise(front, reference)
    assert generational_distance(front, reference, interpolate=False) == pytest.approx(
        GD(ref_n)(front_n), rel=1e-12)
    assert inverted_generational_distance(front, reference) == pytest.approx(
        IGD(ref_n)(front_n), rel=1e-12)


def test_interpolated_gd_is_the_distance_to_the_polyline(fronts):
    """Against pymoo's GD on the reference polyline resampled 200 times more densely."""
    reference, front = fronts
    ref_n = normalise(reference, reference)
    s = np.linspace(0.0, len(ref_n) - 1, 200 * (len(ref_n) - 1) + 1)
    dense = np.column_stack([np.interp(s, np.arange(len(ref_n)), ref_n[:, i]) for i in (0, 1)])
    gd = generational_distance(front, reference)
    assert gd == pytest.approx(GD(dense)(normalise(front, reference)), abs=1e-6)
    assert gd <= generational_distance(front, reference, interpolate=False)


def test_metrics_of_the_reference_itself_and_of_a_shifted_copy(fronts):
    reference, _ = fronts
    assert generational_distance(reference, reference) == pytest.approx(0.0, abs=1e-15)
    assert generational_distance(reference, reference, interpolate=False) == 0.0
    assert inverted_generational_distance(reference, reference) == 0.0
    shift = 0.05 * (reference[:, 1].max() - reference[:, 1].min())
    worse = reference + np.array([0.0, shift])  # 0.05 in normalised J2, everywhere
    assert 0 < generational_distance(worse, reference) <= 0.05 + 1e-12
    assert generational_distance(worse, reference, interpolate=False) > 0
    assert inverted_generational_distance(worse, reference) > 0
    assert hypervolume(worse, reference) < hypervolume(reference, reference)


def test_hypervolume_of_the_reference_is_a_sum_of_rectangles(fronts):
    reference, _ = fronts
    points = normalise(reference, reference)
    points = points[np.argsort(points[:, 0])]  # non-dominated: J2 decreasing
    right = np.append(points[1:, 0], 1.1)
    expected = float(np.sum((right - points[:, 0]) * (1.1 - points[:, 1])))
    assert hypervolume(reference, reference) == pytest.approx(expected, rel=1e-12)
    assert hypervolume(reference, reference, ref_point=(2.0, 2.0)) > expected


def test_hypervolume_ignores_dominated_and_outside_points(fronts):
    reference, _ = fronts
    ideal, nadir = reference.min(axis=0), reference.max(axis=0)
    extra = ideal + np.array([[1.2, -0.5], [0.5, 1.2], [1.05, 1.05]]) * (nadir - ideal)
    assert hypervolume(np.vstack([reference, extra]), reference) == pytest.approx(
        hypervolume(reference, reference), rel=1e-14)
    assert hypervolume(extra[:2], reference) == 0.0
    assert hypervolume(reference[:0], reference) == 0.0
