"""The inner-problem contract on every transcription (DMOC, multiple shooting, DFET): one suite
run on each, as rockit's tests/test_methods.py runs every method on every problem.

The problem is the double integrator's minimum energy, q̈ = u, min ∫ u² dt over a fixed
horizon T between boundary data (q_0, v_0) and (q_T, v_T); its optimum is, per axis,
12 a²/T³ − 12 a b/T² + 4 b²/T with a = q_T − q_0 − v_0 T and b = v_T − v_0 (12 d²/T³ from
rest to rest). With a free final time and the cost w T + ∫ u² dt, the optimum is that
closed form plus w T minimised over T (a scalar minimisation).
"""

from __future__ import annotations

import dataclasses
import math
import pickle
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from ocpar.bsp.columns import SHARED, STACKED, to_columns
from ocpar.models import PointMass
from ocpar.ocp import (
    INVALID_GUESS,
    INVALID_PARAMS,
    DfetOcpShape,
    DmocShape,
    MsShape,
    OcpTask,
    Transcription,
    solve_task,
    transcription,
)
from ocpar.ocp.constraints import NormSquared, PathConstraint

DURATION = 2.0


@dataclass(frozen=True)
class DoubleIntegrator:
    """ẋ = (v, u) on the line, running cost u²."""

    nx = 2
    nu = 1

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.vertcat(x[1], u[0])

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return u[0] ** 2

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(2, -np.inf), np.full(2, np.inf)


def minimum_energy(q0, v0, qn, vn, duration: float) -> float:
    a, b = np.asarray(qn) - q0 - np.asarray(v0) * duration, np.asarray(vn) - v0
    t = duration
    return float(np.sum(12 * a**2 / t**3 - 12 * a * b / t**2 + 4 * b**2 / t))


@dataclass(frozen=True)
class Case:
    """A transcription of the problem: ``shape(n, **options)`` on n intervals/elements,
    parameters p, the exact optimum, and the order of the cost error it must show."""

    name: str
    shape: Callable[..., object]
    params: np.ndarray
    exact: float
    order: float
    grids: tuple[int, int]


# the planar point mass of DMOC: p = (q_0, v_0, q_N, v_N), 2-D each
DMOC_P = np.array([0.0, 0.0, 1.0, 0.5, 3.0, 1.0, 0.0, -1.0])
# the line: p = (q_0, v_0, q_T, v_T)
LINE_P = np.array([0.0, 0.5, 1.0, -1.0])
LINE_EXACT = minimum_energy(0.0, 0.5, 1.0, -1.0, DURATION)
#: The line's problem with a free final time in FREE_TIME and the cost T + ∫ u² dt.
FREE_TIME = (0.5, 10.0)
FREE_EXACT = float(minimize_scalar(lambda t: t + minimum_energy(0.0, 0.5, 1.0, -1.0, t),
                                   bounds=FREE_TIME, method="bounded",
                                   options={"xatol": 1e-12}).fun)

CASES = [
    # midpoint discrete Lagrangian: O(h²)
    Case("dmoc", lambda n, **o: DmocShape(PointMass(), n, DURATION, **o), DMOC_P,
         minimum_energy(*DMOC_P.reshape(4, 2), DURATION), 2.0, (10, 40)),
    # explicit Euler steps: O(h)
    Case("ms-euler", lambda n, **o: MsShape(DoubleIntegrator(), n, DURATION / n, (0, 1), **o),
         LINE_P, LINE_EXACT, 1.0, (20, 80)),
    # RK4 steps, controls held on each interval: O(h²) from the controls
    Case("ms-rk4", lambda n, **o: MsShape(DoubleIntegrator(), n, DURATION / n, (0, 1), "rk4",
                                          **o), LINE_P, LINE_EXACT, 2.0, (10, 40)),
    # the same with a free final time (T the NLP's last variable): O(h²)
    Case("ms-rk4-free-time", lambda n, **o: MsShape(
        DoubleIntegrator(), n, DURATION / n, (0, 1), "rk4", final_time=FREE_TIME,
        time_weight=1.0, **o), LINE_P, FREE_EXACT, 2.0, (10, 40)),
    # quadratic states, constant controls per element: O(h²) from the controls
    Case("dfet", lambda n, **o: DfetOcpShape(DoubleIntegrator(), n, 2, 0, ((-50.0, 50.0),),
                                             (DURATION, DURATION), (0, 1), **o),
         LINE_P, LINE_EXACT, 2.0, (8, 32)),
]


@pytest.fixture(params=CASES, ids=lambda c: c.name)
def case(request) -> Case:
    return request.param


def test_transcriptions_implement_the_contract(case):
    shape = case.shape(case.grids[0])
    nlp = transcription(shape)
    assert isinstance(nlp, Transcription)
    assert transcription(pickle.loads(pickle.dumps(shape))) is nlp  # built once per shape
    assert nlp.n_params == case.params.size


def test_cost_converges_to_the_analytic_optimum_at_the_expected_order(case):
    coarse, fine = case.grids
    errors = {}
    for n in case.grids:
        sol = solve_task(OcpTask(case.shape(n), case.params))
        assert sol.success and sol.attempts == 1, sol.status
        errors[n] = abs(sol.cost - case.exact)
    assert errors[coarse] / case.exact < 0.1
    observed = math.log(errors[coarse] / errors[fine]) / math.log(fine / coarse)
    assert observed == pytest.approx(case.order, abs=0.1)


def test_warm_start_gives_the_same_optimum_in_no_more_iterations(case):
    nlp = transcription(case.shape(case.grids[0]))
    cold = nlp.solve(case.params)
    warm = nlp.solve(case.params, nlp.warm_start(cold), getattr(cold, "lam_g", None))
    assert cold.success and warm.success
    assert warm.cost == pytest.approx(cold.cost, rel=1e-9)
    assert warm.iterations <= cold.iterations
    # the same through the kernel, the warm start carried by the task as data
    task = OcpTask(case.shape(case.grids[0]), case.params, nlp.warm_start(cold))
    assert solve_task(task).cost == pytest.approx(cold.cost, rel=1e-9)


def test_failures_are_data(case):
    nlp = transcription(case.shape(case.grids[0]))
    nan_params = np.full(case.params.size, np.nan)
    direct = nlp.solve(nan_params)  # the solver meets NaN: a status, no exception
    assert not direct.success and direct.status
    kernel = solve_task(OcpTask(case.shape(case.grids[0]), nan_params))
    assert (kernel.success, kernel.status, kernel.attempts) == (False, INVALID_PARAMS, 1)

    # a solver that cannot finish: every guess is tried (the task's, then the fallbacks)
    stuck = case.shape(case.grids[0], max_iter=0)
    sol = solve_task(OcpTask(stuck, case.params))
    fallbacks = len(list(transcription(stuck).fallback_guesses(case.params)))
    assert not sol.success and sol.status and sol.attempts == 1 + fallbacks

    # a first guess that is not finite fails without a solve; the task's fallback succeeds
    guess = nlp.default_guess(case.params)
    retried = solve_task(OcpTask(case.shape(case.grids[0]), case.params,
                                 warm_start=np.full_like(guess, np.nan), fallback=guess))
    assert retried.success and retried.attempts == 2
    assert retried.cost == pytest.approx(nlp.solve(case.params).cost, rel=1e-9)
    failed = nlp.failure(case.params, INVALID_GUESS, 0.0)
    assert not failed.success and math.isnan(failed.cost)


def test_cost_gradient_from_multipliers_matches_finite_differences(case):
    """dJ*/dp from CasADi's lam_p (lam_p = −dJ*/dp) against central differences."""
    nlp = transcription(case.shape(case.grids[0]))
    gradient = nlp.solve(case.params).cost_gradient
    step = 1e-5
    fd = np.array([(nlp.solve(case.params + step * e).cost
                    - nlp.solve(case.params - step * e).cost) / (2 * step)
                   for e in np.eye(case.params.size)])
    assert np.linalg.norm(gradient) > 1.0
    np.testing.assert_allclose(gradient, fd, rtol=1e-6, atol=1e-6)


def test_tasks_pack_into_one_array_per_field(case):
    shape, rng = case.shape(case.grids[0]), np.random.default_rng(0)
    guess = transcription(shape).default_guess(case.params)
    tasks = [OcpTask(shape, case.params + rng.standard_normal(case.params.size),
                     fallback=guess + k) for k in range(5)]
    packed = to_columns(tasks)
    kinds = {name: kind for name, (kind, _) in packed.fields.items()}
    assert kinds == {"shape": SHARED, "params": STACKED, "warm_start": SHARED,
                     "multipliers": SHARED, "fallback": STACKED}


# -- constrained cases: one path constraint vocabulary on every transcription ------------------

U_MAX, V_MAX = 1.2, 0.6
#: Rest to rest over d = 1 in T = 2 with |u| ≤ 1.2 (the free peak 6d/T² = 1.5): u = ±1.2 near
#: both ends, linear in between (closed form, as in tests/test_dmoc.py).
THRUST_EXACT = 1.5223549801
#: The same with |v| ≤ 0.6 (the free peak 1.5 d/T = 0.75): v rises as a parabola to 0.6 at
#: t₁ = 3(T − d/v_max)/2 = 0.5 with u = 0 there, coasts, and falls back; J = 8 v_max²/(3 t₁).
SPEED_EXACT = 8 * V_MAX**2 / (3 * 0.5)
DIAGONAL = np.sqrt(0.5)
# the planar point mass from rest at the origin to rest at distance 1 along the diagonal
DMOC_REST = np.array([0.0, 0.0, 0.0, 0.0, DIAGONAL, DIAGONAL, 0.0, 0.0])
LINE_REST = np.array([0.0, 0.0, 1.0, 0.0])


def constrained_shape(name: str, limit: str, n: int):
    """Shape and parameters of transcription ``name`` on n intervals with a thrust limit
    (DMOC: the norm |u| ≤ 1.2 in the plane; else the box on the line) or a speed limit."""
    if name == "dmoc":
        constraint = (PathConstraint(lambda u: ca.sumsqr(u), upper=U_MAX**2, name="thrust")
                      if limit == "thrust" else
                      PathConstraint(lambda v: ca.sumsqr(v), upper=V_MAX**2, name="speed"))
        return DmocShape(PointMass(dim=2), n, DURATION, solver="sqpmethod",
                         path_constraints=(constraint,)), DMOC_REST
    constraint = (PathConstraint(lambda u: u, lower=-U_MAX, upper=U_MAX, name="thrust")
                  if limit == "thrust" else PathConstraint(lambda x: x[1], upper=V_MAX))
    shapes = {
        "ms-euler": lambda: MsShape(DoubleIntegrator(), n, DURATION / n, (0, 1),
                                    path_constraints=(constraint,)),
        "ms-rk4": lambda: MsShape(DoubleIntegrator(), n, DURATION / n, (0, 1), "rk4",
                                  path_constraints=(constraint,)),
        # T an NLP variable pinned by equal bounds: the free-time NLP on the closed forms
        "ms-rk4-free-time": lambda: MsShape(
            DoubleIntegrator(), n, DURATION / n, (0, 1), "rk4",
            path_constraints=(constraint,), final_time=(DURATION, DURATION)),
        "dfet": lambda: DfetOcpShape(DoubleIntegrator(), n, 2, 0, ((-50.0, 50.0),),
                                     (DURATION, DURATION), (0, 1),
                                     path_constraints=(constraint,)),
    }
    return shapes[name](), LINE_REST


@pytest.mark.parametrize("limit", ["thrust", "speed"])
def test_an_active_path_constraint_reaches_the_closed_form_at_second_order(case, limit):
    """Thrust limit (control) and speed limit (state) on every transcription: the cost
    converges to the closed-form constrained optimum at O(h²) (measured: 3.38e-3, 8.42e-4,
    2.11e-4 at N = 20, 40, 80 for the thrust limit, 2.00e-2, 4.85e-3, 1.20e-3 for the speed
    limit, on all four), well above the free optimum 1.5."""
    exact = THRUST_EXACT if limit == "thrust" else SPEED_EXACT
    errors = {}
    for n in (20, 80):
        shape, params = constrained_shape(case.name, limit, n)
        sol = solve_task(OcpTask(shape, params))
        assert sol.success, sol.status
        errors[n] = sol.cost - exact
    assert errors[20] > 0 and errors[80] > 0
    assert math.log(errors[20] / errors[80]) / math.log(4) == pytest.approx(2.0, abs=0.1)


def test_path_constraints_keep_shapes_hashable_and_picklable(case):
    """A lambda compiles to text: the shape pickles (to MPI ranks, Dask workers) and equal
    shapes share one transcription."""
    shape, _ = constrained_shape(case.name, "thrust", 10)
    again, _ = constrained_shape(case.name, "thrust", 10)
    assert again == shape and transcription(pickle.loads(pickle.dumps(shape))) is \
        transcription(shape)


@pytest.mark.parametrize(("constraint", "message"), [
    (PathConstraint(lambda y: y), "function takes 'y'; it may take"),
    (PathConstraint(lambda u: u.nope), "does not evaluate on CasADi symbols"),
    (PathConstraint(lambda u: ca.SX.sym("z")), "depends on symbols other than its arguments"),
    (PathConstraint(lambda u: ca.vertcat(u, u), lower=(1.0, 2.0, 3.0)), "lower: must be"),
    (PathConstraint(lambda u: u, lower=1.0, upper=0.0), "needs lower <= upper"),
    (PathConstraint(lambda u: u, upper=float("nan")), "upper: NaN"),
    (PathConstraint(lambda u: ca.SX(2, 2)), "must return a number or a column"),
    (PathConstraint(lambda u: ca.horzcat(u[0], u[0])), "got a row of shape (1, 2)"),
    (PathConstraint(lambda u: 0 * u[0] + 1.0), "depends on none of its arguments"),
    (PathConstraint(lambda u: ca.vertcat(u[0], 2.0)), "row 1 depends on none"),
    (PathConstraint(lambda u: u, name=""), "name must be a non-empty string"),
    (PathConstraint("u <= 1"), "function must be callable"),
    (lambda u: u, "must be a PathConstraint"),
])
def test_a_malformed_path_constraint_is_one_error_naming_the_field(case, constraint, message):
    shape = case.shape(4)
    with pytest.raises(ValueError, match="path_constraints\\[0\\]") as error:
        dataclasses.replace(shape, path_constraints=(constraint,))
    assert message in str(error.value) and "\n" not in str(error.value)


def norm_shapes(name: str, n: int):
    """The thrust limit |u| ≤ U_MAX written with ``ca.norm_2`` and as its square, on
    transcription ``name`` (DMOC: in the plane along the diagonal; else on the line)."""
    norm = PathConstraint(lambda u: ca.norm_2(u), upper=U_MAX, name="thrust")
    square = PathConstraint(lambda u: ca.sumsqr(u), upper=U_MAX**2, name="thrust")
    shape, params = constrained_shape(name, "thrust", n)
    with pytest.warns(NormSquared, match="thrust"):
        with_norm = dataclasses.replace(shape, path_constraints=(norm,))
    return with_norm, dataclasses.replace(shape, path_constraints=(square,)), params


def test_a_norm_thrust_limit_is_solved_exactly_as_its_square(case):
    """|u|₂ ≤ U written with norm_2 (no derivative at u = 0, where every solve starts) is
    compiled as |u|² ≤ U², with a NormSquared warning: the same optimum as the squared form
    to 1e-8 on every transcription (formation: DMOC; pursuit: multiple shooting; MACS: DFET),
    with the limit active (the cost within 1e-2 of the closed form 1.5224, above the free
    1.5)."""
    with_norm, square, params = norm_shapes(case.name, 20)
    a, b = solve_task(OcpTask(with_norm, params)), solve_task(OcpTask(square, params))
    assert a.success and b.success, (a.status, b.status)
    assert a.cost == pytest.approx(b.cost, abs=1e-8)
    assert a.cost == pytest.approx(THRUST_EXACT, abs=1e-2) and a.cost > 1.5 + 1e-3


def test_a_norm_that_is_not_a_bound_is_refused_where_the_solves_start():
    """|u| + u_0 ≤ 1 is no norm bound (not squared): it has no derivative at u = 0, where the
    formation's inner solves start, and the problem is refused with one line naming it."""
    from ocpar.formation import Circle, FormationProblem

    shape = DmocShape(PointMass(dim=2), 10, 1.0, solver="sqpmethod", path_constraints=(
        PathConstraint(lambda u: ca.norm_2(u) + u[0], upper=1.0, name="thrust"),))
    with pytest.raises(ValueError, match=r"shape.path_constraints\[0\] \(thrust\): not "
                       r"differentiable at u = \[0.0, 0.0\] \(agent 0's start\)") as error:
        FormationProblem(name="t", starts=np.array([[0.0, -3.0], [1.0, -3.0]]), shape=shape,
                         curve=Circle(radius=2.0, center=np.zeros(2)))
    assert "sumsqr" in str(error.value) and "\n" not in str(error.value)
