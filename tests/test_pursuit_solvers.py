"""The pursuit subproblems' local solvers: Newton on the KKT system and sqpmethod re-solve a
neighbouring problem to IPOPT's optimum; Newton's failures fall back to IPOPT."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ocpar.models import OrbitTransfer
from ocpar.ocp import MsShape, ms_problem
from ocpar.ocp.multiple_shooting import LOCAL_SOLVERS, NEWTON_STEPS

MODEL = OrbitTransfer()
X0 = np.array([9.6, 0.0, MODEL.circular_rate(9.6), 0.525])
TARGET = np.array([9.65, 0.0, MODEL.circular_rate(9.65)])
COLD = MsShape(MODEL, 20, 1.0, (0, 1, 2))


@pytest.fixture(scope="module")
def neighbour():
    """IPOPT's solution for a target 1 km higher, and IPOPT's re-solve (no local solver) of
    the original target from it: the reference every local solver must reach."""
    ipopt = ms_problem(COLD)
    moved = ipopt.solve(np.concatenate([X0, TARGET + np.array([1e-3, 0, 0])]))
    assert moved.success, moved.status
    params = np.concatenate([X0, TARGET])
    reference = ipopt.solve(params, moved.w, moved.lam_g)
    assert reference.success, reference.status
    return params, moved, reference


@pytest.mark.parametrize("local_solver", LOCAL_SOLVERS)
def test_local_solvers_reach_ipopts_optimum(neighbour, local_solver):
    params, moved, reference = neighbour
    shape = dataclasses.replace(COLD, warm_start=True, local_solver=local_solver)
    sol = ms_problem(shape).solve(params, moved.w, moved.lam_g)
    assert sol.success and sol.status == "Solve_Succeeded"
    assert sol.iterations <= 3  # a local step from a neighbour, not IPOPT's barrier iterations
    assert sol.cost == pytest.approx(reference.cost, rel=1e-9)
    np.testing.assert_allclose(sol.w, reference.w, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sol.lam_g, reference.lam_g, rtol=1e-6, atol=1e-8)
    # dJ*/dp: Newton's ∇_p L against IPOPT's −lam_p (itself checked against finite differences)
    np.testing.assert_allclose(sol.cost_gradient, reference.cost_gradient, rtol=1e-6)
    assert sol.constraint_violation <= 1e-10


def test_newton_from_far_away_does_not_converge_and_ipopt_takes_over(neighbour):
    params, _, reference = neighbour
    nlp = ms_problem(dataclasses.replace(COLD, warm_start=True))
    guess = nlp.default_guess(params)  # x_0 held, no thrust: far from the transfer
    *_, dual, _ = nlp.newton(guess, np.zeros(nlp.ng), params)
    assert not dual[0] <= COLD.tol  # NEWTON_STEPS full steps are not enough from here
    sol = nlp.solve(params, guess)
    assert sol.success and sol.iterations > NEWTON_STEPS  # IPOPT's iterations
    assert sol.cost == pytest.approx(reference.cost, rel=1e-8)


def test_unknown_local_solver_is_refused():
    with pytest.raises(ValueError, match="local solver 'qp'"):
        MsShape(MODEL, 10, 1.0, (0,), local_solver="qp")


def test_a_batch_gives_each_row_the_one_by_one_solution_bitwise(neighbour):
    params, moved, _ = neighbour
    nlp = ms_problem(dataclasses.replace(COLD, warm_start=True))
    rows = np.array([params + dr * np.eye(7)[4] for dr in (0.0, 2e-4, -3e-4)])
    guesses = np.array([moved.w, moved.w, nlp.default_guess(params)])  # the last: far away
    lams = np.array([moved.lam_g, moved.lam_g, np.zeros(nlp.ng)])
    batch = nlp.solve_batch(rows, guesses, lams).items()
    pair = nlp.solve_batch(rows[1::-1], guesses[1::-1], lams[1::-1]).items()  # other order
    for i, sol in enumerate(batch):
        alone = nlp.solve(rows[i], guesses[i], lams[i])
        assert sol.success and sol.status == alone.status
        np.testing.assert_array_equal(sol.w, alone.w)
        np.testing.assert_array_equal(sol.lam_g, alone.lam_g)
        assert sol.cost == alone.cost and sol.iterations == alone.iterations
    np.testing.assert_array_equal(pair[0].w, batch[1].w)
    assert batch[0].iterations == NEWTON_STEPS and batch[2].iterations > NEWTON_STEPS
    with pytest.raises(ValueError, match="guesses"):
        nlp.solve_batch(rows, guesses[:2])
