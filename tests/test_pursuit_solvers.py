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
    moved = ipopt.solve(np.concatenate([X0, TARGET + [1e-3, 0, 0]]))
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
