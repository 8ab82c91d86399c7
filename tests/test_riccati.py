"""The Riccati Newton solver of ODE agents between two states (:mod:`ocpar.ocp.riccati`, the
``newton`` batches of :class:`~ocpar.ocp.MsEndpointShape`) against the same NLP solved by
sparse QR on its whole KKT matrix (``newton.kkt_solver = qr``) and by IPOPT, whose end
Hessian comes from the KKT system (:mod:`ocpar.ocp.sensitivity`): random unicycle and
Clohessy–Wiltshire tasks; each task's result bitwise independent of the other tasks in its
batch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ocpar.bsp.columns import SHARED, Columns
from ocpar.models import ClohessyWiltshire, Unicycle
from ocpar.ocp import MsEndpointShape, transcription
from ocpar.ocp.columns_eval import evaluate_columns
from ocpar.ocp.compiled import BLOCK, CompiledPoints
from ocpar.ocp.endpoint_agents import agent_tasks, solve_agents
from ocpar.ocp.multiple_shooting import step_function
from ocpar.ocp.riccati import RiccatiNewton, stage_function

TASKS = 6
FIELDS = ("cost", "cost_gradient", "end_hessian", "q", "u")


def _unicycle_tasks(rng: np.random.Generator) -> np.ndarray:
    """(TASKS, 8): starts near (−1, −5) facing +y at rest, ends near (2, 1) at rest."""
    p = np.tile([-1.0, -5.0, np.pi / 2, 0.0, 2.0, 1.0, 0.0, 0.0], (TASKS, 1))
    p[:, :3] += rng.uniform(-1.0, 1.0, (TASKS, 3))
    p[:, 3] = rng.uniform(0.0, 0.5, TASKS)
    p[:, 4:6] += rng.uniform(-2.0, 2.0, (TASKS, 2))
    return p


def _cw_tasks(rng: np.random.Generator) -> np.ndarray:
    """(TASKS, 12): starts scattered about the V-bar, moving; ends on a 100 m ring."""
    starts = np.column_stack([rng.uniform(-60, 60, TASKS), rng.uniform(-500, -250, TASKS),
                              rng.uniform(-40, 40, TASKS), rng.uniform(-2, 2, (TASKS, 3))])
    angle = rng.uniform(0, 2 * np.pi, TASKS)
    ends = np.column_stack([100 * np.cos(angle), 100 * np.sin(angle), np.zeros((TASKS, 4))])
    return np.hstack([starts, ends])


CASES = {
    "unicycle": (MsEndpointShape(Unicycle(), intervals=12, duration=6.0, free_end=(2,)),
                 _unicycle_tasks),
    "unicycle-euler-2-steps": (MsEndpointShape(Unicycle(), intervals=8, duration=6.0,
                                               steps=2, integrator="euler", free_end=(2,)),
                               _unicycle_tasks),
    "cw": (MsEndpointShape(ClohessyWiltshire(0.0011, time_unit="min"), intervals=10,
                           duration=1500.0), _cw_tasks),
    "cw-free-velocity": (MsEndpointShape(ClohessyWiltshire(0.0011, time_unit="min"),
                                         intervals=10, duration=1500.0, free_end=(3, 4, 5)),
                         _cw_tasks),
}


def _close(a: np.ndarray, b: np.ndarray, tol: float = 1e-10) -> bool:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return bool(np.all(np.abs(a - b) <= tol * (1.0 + np.max(np.abs(b)))))


def _cw_end_hessian(shape: MsEndpointShape) -> np.ndarray:
    """d²J*/dx̄_N² of a Clohessy–Wiltshire agent in closed form (numpy, not the package's
    NLP): x_N = Φᴺ x_0 + G U with RK4's Φ = Σ_{k≤4} (hA)ᵏ/k!, Γ = h Σ_{k≤3} (hA)ᵏ/(k+1)! B,
    G = [Φᴺ⁻¹Γ … Γ], J = h |U|² at the least-norm U: J* = h rᵀ (E G Gᵀ Eᵀ)⁻¹ r on the fixed
    rows E, so d²J*/dx̄² = 2h (E G Gᵀ Eᵀ)⁻¹ there, 0 on the free ones."""
    n, steps = shape.model.mean_motion, shape.intervals
    h = shape.duration / steps
    a = np.zeros((6, 6))
    a[:3, 3:] = np.eye(3)
    a[3, 0], a[3, 4], a[4, 3], a[5, 2] = 3 * n**2, 2 * n, -2 * n, -n**2
    b = np.vstack([np.zeros((3, 3)), np.eye(3)])
    powers = [np.linalg.matrix_power(h * a, k) for k in range(5)]
    phi = sum(p / math.factorial(k) for k, p in enumerate(powers))
    gamma = h * sum(p / math.factorial(k + 1) for k, p in enumerate(powers[:4])) @ b
    g = np.hstack([np.linalg.matrix_power(phi, steps - 1 - j) @ gamma for j in range(steps)])
    fixed = [i for i in range(6) if i not in shape.free_end]
    hessian = np.zeros((6, 6))
    hessian[np.ix_(fixed, fixed)] = 2 * h * np.linalg.inv(g[fixed] @ g[fixed].T)
    return hessian


@pytest.mark.parametrize("case", CASES)
def test_riccati_equals_sparse_qr_and_ipopt(case):
    """J*, dJ*/dp, the end Hessian, path and controls of each task equal IPOPT's (its end
    Hessian from the KKT system) and the sparse-QR Newton's to 1e-10 (relative to the largest
    entry), from the default guess. On the Clohessy–Wiltshire tasks (ill-conditioned: metres
    against controls of 1e-3 m/min², 1500 min) the Riccati end Hessian equals the closed
    form to 1e-12 where the KKT system's is 3e-9..4e-8 off, and the QR Newton's path 3e-9
    off IPOPT's where the Riccati path is within 5e-15: those fields against the closed
    form, and the QR path to 1e-7."""
    shape, tasks = CASES[case]
    params = tasks(np.random.default_rng(46))
    riccati = transcription(shape)
    qr = transcription(MsEndpointShape(**{**shape.__dict__,
                                          "solver_options": {"newton.kkt_solver": "qr"}}))
    assert isinstance(riccati.batch_solver, RiccatiNewton)
    assert not isinstance(qr.batch_solver, RiccatiNewton)
    new = riccati.solve_batch(params, [None] * TASKS, [None] * TASKS)
    old = qr.solve_batch(params, [None] * TASKS, [None] * TASKS)
    assert all(new.column("success")) and all(old.column("success"))
    linear = case.startswith("cw")
    for name in FIELDS:
        assert _close(new.column(name), old.column(name), 1e-7 if linear else 1e-10), name
    for k in range(TASKS):
        reference = riccati.solve(params[k])     # IPOPT, its end Hessian from the KKT system
        assert reference.success
        for name in FIELDS:
            tol = 1e-7 if linear and name == "end_hessian" else 1e-10
            assert _close(np.asarray(new.column(name))[k], getattr(reference, name), tol), name
    hessian = np.asarray(new.column("end_hessian"))
    if linear:
        assert _close(hessian, np.broadcast_to(_cw_end_hessian(shape), hessian.shape), 1e-12)
    free = list(shape.free_end)
    assert np.all(hessian[:, free] == 0.0) and np.all(hessian[:, :, free] == 0.0)


@pytest.mark.parametrize("case", ["unicycle", "cw"])
def test_a_task_does_not_depend_on_its_batch_bitwise(case):
    """Each task's solution, solved with the others, in reverse order, alone and beside
    tasks that fail (a NaN start), has the same bits."""
    shape, tasks = CASES[case]
    params = tasks(np.random.default_rng(7))
    nlp = transcription(shape)
    together = nlp.solve_batch(params, [None] * TASKS, [None] * TASKS)
    reverse = nlp.solve_batch(params[::-1], [None] * TASKS, [None] * TASKS)
    broken = params[:2].copy()
    broken[:, 0] = np.nan
    mixed = nlp.solve_batch(np.vstack([broken, params[:3]]), [None] * 5, [None] * 5)
    assert all(together.column("success"))
    assert not any(mixed.column("success")[:2])
    for k in range(TASKS):
        alone = nlp.solve_batch(params[k:k + 1], [None], [None])
        others = [(alone, 0), (reverse, TASKS - 1 - k)] + ([(mixed, 2 + k)] if k < 3 else [])
        for name in (*FIELDS, "iterations"):
            mine = np.asarray(together.column(name))[k]
            for batch, row in others:
                assert np.array_equal(mine, np.asarray(batch.column(name))[row]), name


def test_a_warm_start_takes_fewer_steps_and_lands_on_the_same_point():
    """From a solution of nearby ends and its multipliers (a formation's later supersteps)
    the batch takes 1–3 steps, fewer than from the default guess, and meets the KKT check;
    the same point as from the default guess to 1e-10."""
    shape, tasks = CASES["unicycle"]
    params = tasks(np.random.default_rng(3))
    nlp = transcription(shape)
    first = nlp.solve_batch(params, [None] * TASKS, [None] * TASKS)
    moved = params.copy()
    moved[:, 4:6] += 0.05
    cold = nlp.solve_batch(moved, [None] * TASKS, [None] * TASKS)
    q, u = np.asarray(first.column("q")), np.asarray(first.column("u"))
    warm = nlp.solve_batch(moved, nlp.shape.previous_guesses(q, u),
                           np.asarray(first.column("multipliers")))
    assert all(warm.column("success")) and all(cold.column("success"))
    steps = np.asarray(warm.column("iterations"))
    assert np.all(steps <= 3) and np.all(steps < np.asarray(cold.column("iterations")))
    for name in FIELDS:
        assert _close(warm.column(name), cold.column(name)), name


def test_agents_re_solve_from_their_previous_multipliers():
    """An ODE agent's state keeps its solution's multipliers and its next solve starts from
    them (:func:`~ocpar.ocp.endpoint_agents.solve_agents`): fewer Newton steps than from the
    same path with λ = 0, the same solution to 1e-10."""
    shape, tasks = CASES["unicycle"]
    params = tasks(np.random.default_rng(5))
    _, states = solve_agents(agent_tasks(shape, 2, params=params), None)
    multipliers = np.asarray(states.column("multipliers"))
    assert multipliers.shape == (TASKS, transcription(shape).ng)
    assert np.all(np.isfinite(multipliers)) and np.any(multipliers != 0.0)
    moved = agent_tasks(shape, 2, end=params[:, 4:6] + 0.2)
    without = Columns(cls=states.cls, length=TASKS,
                      fields=states.fields | {"multipliers": (SHARED, None)})
    warm, warm_states = solve_agents(moved, states)
    cold, cold_states = solve_agents(moved, without)
    assert all(warm.column("success")) and all(cold.column("success"))
    steps, cold_steps = (np.asarray(s.column("iterations")) for s in (warm_states, cold_states))
    assert np.all(steps <= cold_steps) and np.sum(steps) < np.sum(cold_steps)
    for name in ("cost", "end_gradient", "end_hessian"):
        assert _close(warm.column(name), cold.column(name)), name


def test_the_kkt_solver_option_is_checked():
    with pytest.raises(ValueError, match=r"newton\.kkt_solver: 'lu' is not a valid value"):
        MsEndpointShape(Unicycle(), free_end=(2,), solver_options={"newton.kkt_solver": "lu"})


def test_compiled_stage_data_equal_casadi_and_numpy(tmp_path, monkeypatch):
    """The compiled stage derivatives (built into an empty cache, then loaded from it) equal
    CasADi's own evaluation and the numpy walk at points of a partial last block; where the
    host has no C compiler the solver evaluates them by numpy, with the same solutions to
    1e-12."""
    monkeypatch.setenv("OCPAR_CACHE", str(tmp_path))
    monkeypatch.delenv("OCPAR_COMPILE", raising=False)   # the suite turns it off
    shape, tasks = CASES["unicycle"]
    step = shape.duration / shape.intervals

    def stage():
        return stage_function(step_function(shape.model, step, "rk4"), 1, step)

    points = np.random.default_rng(5).normal(size=(BLOCK + 7, 10))
    rows = [points[:, :4].T.copy(), points[:, 4:6].T.copy(), points[:, 6:].T.copy()]
    first = CompiledPoints.of(stage())
    assert first is not None and len(list((tmp_path / "compiled").glob("*.so"))) == 1
    again = CompiledPoints.of(stage())
    assert again is not None and len(list((tmp_path / "compiled").glob("*.so"))) == 1
    function = stage()
    casadi = function.map(len(points))(*rows)
    walked = evaluate_columns(function, *(row.T for row in rows))
    for i, (out, also, ref, by_numpy) in enumerate(zip(first(*rows), again(*rows), casadi,
                                                       walked, strict=True)):
        size1, size2 = function.size_out(i)
        ref = np.asarray(ref).reshape(size1, len(points), size2).transpose(2, 0, 1)
        assert np.array_equal(out, also)
        assert np.allclose(out, ref.reshape(size1 * size2, -1), rtol=1e-14, atol=1e-14)
        assert np.allclose(out, by_numpy.T, rtol=1e-14, atol=1e-14)
    params = tasks(np.random.default_rng(11))
    nlp = transcription(shape)
    guesses = nlp.default_guesses(params)
    compiled_solve = RiccatiNewton(stage(), shape.intervals, (0, 1, 3), 1e-12).solve(
        guesses, params, np.zeros((TASKS, nlp.ng)), nlp.lbx, nlp.ubx)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    assert CompiledPoints.of(stage()) is None
    numpy_solve = RiccatiNewton(stage(), shape.intervals, (0, 1, 3), 1e-12).solve(
        guesses, params, np.zeros((TASKS, nlp.ng)), nlp.lbx, nlp.ubx)
    assert all(compiled_solve.success) and all(numpy_solve.success)
    for name in ("x", "f", "lam_g", "lam_p", "extra"):
        assert _close(getattr(compiled_solve, name), getattr(numpy_solve, name), 1e-12), name
