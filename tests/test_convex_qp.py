"""The batched convex QP (ocpar.ocp.convex_qp) against IPOPT on DMOC keep-out columns."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_keep_out import keep_out_params, point_mass_shape

from ocpar.models import PointMass
from ocpar.ocp import DmocShape, transcription
from ocpar.ocp.convex_qp import ConvexQp
from ocpar.ocp.dmoc import UNUSED_OFFSET

SLOTS = 3


@pytest.fixture(scope="module")
def ipopt_nlp():
    """The point mass's keep-out NLP (10 intervals, 3 slots), solved by IPOPT."""
    return transcription(point_mass_shape(SLOTS))


@pytest.fixture(scope="module")
def auto_nlp():
    """The same shape under the ``auto`` solver: batched by the convex QP."""
    return transcription(DmocShape(PointMass(dim=2, mass=1.0), intervals=10, duration=1.0,
                                   keep_out_slots=SLOTS, keep_out_positions=(0, 1)))


def random_columns(count: int, seed: int = 5) -> np.ndarray:
    """Random boundary data and half-spaces (random normals and offsets on intervals 2..7,
    slots 0 and 1) with penalties 1 or 1e3: asymmetric, several rows active."""
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(count):
        data = np.zeros((10, SLOTS, 4))
        data[..., 2:] = UNUSED_OFFSET
        for k in range(2, 8):
            for slot in range(2):
                angle = rng.uniform(0.0, 2 * np.pi)
                data[k, slot] = [np.cos(angle), np.sin(angle), *rng.uniform(-0.4, 0.4, 2)]
        boundary = np.concatenate([rng.normal(0, 0.3, 2), rng.normal(0, 1, 2),
                                   np.array([1.0, 0.0]) + rng.normal(0, 0.3, 2),
                                   rng.normal(0, 1, 2)])
        rows.append(np.concatenate([boundary, data.ravel(), [rng.choice([1.0, 1e3])]]))
    return np.array(rows)


def ipopt_solve(nlp, params: np.ndarray) -> dict:
    out = nlp.solver(x0=nlp.default_guess(params), p=params, lbg=nlp.lbg, ubg=nlp.ubg,
                     lbx=nlp.lbx, ubx=nlp.ubx)
    assert nlp.solver.stats()["success"]
    return {key: np.asarray(value).ravel() for key, value in out.items()}


def test_batched_qp_is_ipopts_answer_on_random_keep_out_columns(ipopt_nlp):
    nlp = ipopt_nlp
    w, p = nlp._w, nlp._p
    qp = ConvexQp.of("test", w, p, nlp.cost(w, p), nlp.constraints(w, p),
                     (nlp.lbg, nlp.ubg, nlp.lbx, nlp.ubx), 1e-12, 1e-10)
    assert qp is not None
    params = random_columns(12)
    batch = qp.solve(params)
    assert batch.success.all()
    n_eq, active = nlp.nq * (nlp.n + 1), 0
    for i, column in enumerate(params):
        reference = ipopt_solve(nlp, column)
        assert batch.f[i] == pytest.approx(reference["f"][0], rel=1e-8)
        scale = 1 + np.max(np.abs(reference["lam_p"]))
        np.testing.assert_allclose(batch.lam_p[i], reference["lam_p"], atol=1e-7 * scale)
        g = np.asarray(nlp.constraints(reference["x"], column)).ravel()
        active += int(np.sum(np.abs(g[n_eq:]) < 1e-8))
    assert active >= len(params)     # the half-spaces bind: not an unconstrained test


def test_a_column_infeasible_without_slacks(ipopt_nlp, auto_nlp):
    """y ≥ 0.3 and −y ≥ 0.3 at the same nodes (interval 4): no path meets both, the
    slacks carry the difference at the penalty's price; the QP's answer is IPOPT's."""
    params = keep_out_params(SLOTS, {4: ([0.0, 1.0], 0.3, 0.3)}, penalty=50.0)
    data = params[8:-1].reshape(10, SLOTS, 4)
    data[4, 1] = [0.0, -1.0, 0.3, 0.3]
    params[8:-1] = data.ravel()
    reference = ipopt_solve(ipopt_nlp, params)
    slacks = reference["x"][ipopt_nlp.nw - 10 * SLOTS:]
    assert slacks.max() > 0.1
    solved = auto_nlp.solve_batch(params[None], [None], [None])
    alone = ipopt_nlp.solve(params)
    assert solved.column("success")[0] and alone.success
    assert solved.column("cost")[0] == pytest.approx(alone.cost, rel=1e-8)
    np.testing.assert_allclose(solved.column("q")[0], alone.q, atol=1e-7)
    np.testing.assert_allclose(solved.column("cost_gradient")[0], alone.cost_gradient,
                               atol=1e-6 * (1 + np.max(np.abs(alone.cost_gradient))))


def test_dispatch_gives_ipopts_solutions(ipopt_nlp, auto_nlp):
    params = random_columns(6, seed=11)
    batch = auto_nlp.solve_batch(params, [None] * 6, [None] * 6)
    assert np.all(batch.column("success"))
    for i, column in enumerate(params):
        alone = ipopt_nlp.solve(column)
        assert batch.column("cost")[i] == pytest.approx(alone.cost, rel=1e-8)
        np.testing.assert_allclose(batch.column("q")[i], alone.q, atol=1e-6)


def test_not_a_convex_qp_is_refused():
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p", 1)
    bounds = (np.zeros(1), np.full(1, np.inf), np.full(2, -np.inf), np.full(2, np.inf))
    assert ConvexQp.of("q", x, p, ca.sumsqr(x), x[0] * x[1] - p, bounds, 1e-12, 1e-10) is None
    assert ConvexQp.of("q", x, p, -ca.sumsqr(x), x[0] - p, bounds, 1e-12, 1e-10) is None
    assert ConvexQp.of("q", x, p, ca.sumsqr(x), x[0] - p, bounds, 1e-12, 1e-10) is not None


def test_a_column_does_not_depend_on_its_batch(auto_nlp):
    """Bitwise: a task's result is the same whichever tasks share its batch (determinism
    across worker counts)."""
    params = random_columns(5, seed=3)
    together = auto_nlp.keep_out_qp.solve(params)
    for i in range(len(params)):
        alone = auto_nlp.keep_out_qp.solve(params[i:i + 1])
        assert np.array_equal(alone.x[0], together.x[i])
        assert np.array_equal(alone.lam_p[0], together.lam_p[i])
