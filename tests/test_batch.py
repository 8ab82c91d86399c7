"""Batched inner solves (:mod:`ocpar.ocp.batch`, :func:`ocpar.ocp.solve_tasks`): the same
solutions whatever the chunking, a per-task KKT check with the one-task fallback, and the
KKT-based second derivative d²J*/dq_N²."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

from ocpar.bsp.columns import to_columns
from ocpar.bsp.partition import contiguous_blocks
from ocpar.examples.formation_halo import make as halo_example
from ocpar.examples.formation_point_masses import make as point_masses
from ocpar.ocp import DmocShape, OcpTask, dmoc_problem, solve_task, solve_tasks
from ocpar.ocp.batch import KktNewton, KktSystem, MappedNlp, constant_outputs


def formation_tasks(problem, phi=None, solver: str | None = None) -> list[OcpTask]:
    """The inner tasks of ``problem`` at angles ``phi``, with the DMOC ``solver`` if given."""
    phi = problem.initial_phi() if phi is None else phi
    tasks = problem.tasks(phi).items()
    if solver is None:
        return tasks
    shape = dataclasses.replace(problem.shape, solver=solver)
    return [dataclasses.replace(t, shape=shape) for t in tasks]


BATCHED = pytest.mark.parametrize("solver", ["newton", "sqpmethod"])


def payload(solution) -> bytes:
    """Every array and number of a DMOC solution, as bytes (bitwise comparison)."""
    fields = dataclasses.asdict(solution)
    fields.pop("solve_time_s")
    return b"".join(np.asarray(v).tobytes() if not isinstance(v, str) else v.encode()
                    for v in fields.values())


@BATCHED
@pytest.mark.parametrize("workers", [1, 2, 3])
@pytest.mark.parametrize("example", ["halo", "point-masses"])
def test_results_do_not_depend_on_the_chunking(workers, solver, example):
    """A worker solves its chunk in one mapped call: every task's solution is bitwise the
    one it gets alone, for the chunks of 1, 2 and 3 workers, on rigid spacecraft (a
    nonlinear NLP) and on point masses (a QP: one factorisation per call)."""
    problem = (halo_example(agents=5, intervals=10) if example == "halo"
               else point_masses(7))
    tasks = formation_tasks(problem, solver=solver)
    alone = [payload(solve_tasks([task])[0]) for task in tasks]
    chunked = [payload(s) for block in contiguous_blocks(len(tasks), workers)
               for s in solve_tasks([tasks[i] for i in block])]
    assert chunked == alone


@BATCHED
def test_batched_solves_agree_with_ipopt(solver):
    """Point masses (a QP per agent) and rigid halo spacecraft (nonlinear): the batched
    optimum equals IPOPT's to 1e-10, gradient included."""
    for problem in (point_masses(8), halo_example(agents=4, intervals=10)):
        tasks = formation_tasks(problem, solver=solver)
        batched = solve_tasks(tasks)
        ipopt_shape = dataclasses.replace(problem.shape, solver="ipopt")
        one_by_one = [solve_task(dataclasses.replace(t, shape=ipopt_shape)) for t in tasks]
        assert all(s.success and s.attempts == 1 for s in batched)
        for b, i in zip(batched, one_by_one, strict=True):
            assert b.cost == pytest.approx(i.cost, rel=1e-10)
            np.testing.assert_allclose(b.cost_gradient, i.cost_gradient, rtol=1e-8,
                                       atol=1e-8 * np.max(np.abs(i.cost_gradient)))
            np.testing.assert_allclose(b.q, i.q, atol=1e-8)


@BATCHED
def test_tasks_failing_the_kkt_check_are_solved_one_by_one(solver):
    """With an unattainable KKT tolerance every batched attempt is rejected: each task is
    then solved by the one-task policy (IPOPT), so its solution is solve_task's, bitwise, after
    one more attempt."""
    strict = dataclasses.replace(point_masses(5).shape, kkt_tol=1e-300, solver=solver)
    tasks = [dataclasses.replace(t, shape=strict) for t in formation_tasks(point_masses(5))]
    batched = solve_tasks(tasks)
    for task, solution in zip(tasks, batched, strict=True):
        alone = solve_task(task)
        assert solution.success and solution.attempts == alone.attempts + 1
        assert payload(dataclasses.replace(solution, attempts=alone.attempts)) == payload(alone)


def test_non_finite_tasks_are_failures_in_a_batch():
    tasks = formation_tasks(point_masses(3))
    bad = [dataclasses.replace(tasks[0], params=np.full(8, np.nan)),
           dataclasses.replace(tasks[1], warm_start=np.full(38, np.nan)), tasks[2]]
    first, second, third = solve_tasks(bad)
    assert not first.success and first.status == "Invalid_Parameters"
    assert second.success and second.attempts == 2  # the guess failed, the fallback solved it
    assert payload(third) == payload(solve_tasks([tasks[2]])[0])


def test_mixed_shapes_in_one_chunk_keep_their_order():
    small, halo = point_masses(3), halo_example(agents=2, intervals=10)
    tasks = formation_tasks(small) + formation_tasks(halo)
    order = [4, 0, 3, 1, 2]
    mixed = solve_tasks([tasks[i] for i in order])
    assert [payload(s) for s in mixed] == [payload(solve_tasks([tasks[i]])[0]) for i in order]


def test_end_hessian_matches_finite_differences_of_the_gradient():
    """d²J*/dq_N² from the KKT system against central differences of dJ*/dq_N (multipliers),
    for a point mass (J* quadratic in p) and a rigid spacecraft (nonlinear)."""
    for problem in (point_masses(2), halo_example(agents=2, intervals=10)):
        task = formation_tasks(problem)[1]
        nlp = dmoc_problem(task.shape)
        solution = solve_tasks([task])[0]
        nq, eps = nlp.nq, 1e-5
        columns = []
        for j in range(nq):
            step = np.zeros(4 * nq)
            step[2 * nq + j] = eps
            up, down = (solve_task(dataclasses.replace(task, params=task.params + s))
                        for s in (step, -step))
            columns.append((up.cost_gradient - down.cost_gradient)[2 * nq:3 * nq] / (2 * eps))
        finite = np.array(columns).T
        np.testing.assert_allclose(solution.end_hessian, finite, rtol=1e-6,
                                   atol=1e-6 * np.max(np.abs(finite)))
        np.testing.assert_allclose(solution.end_hessian, solution.end_hessian.T,
                                   atol=1e-9 * np.max(np.abs(finite)))


def test_mapped_nlp_checks_each_column():
    """min (x − p)⁴ + x² s.t. x ≥ 0 … one sqpmethod iteration cannot reach the optimum of a
    quartic: the check rejects those columns; enough iterations pass it, and columns with p
    below the bound end on it with a positive multiplier (complementarity)."""
    x, p = ca.SX.sym("x"), ca.SX.sym("p")
    f, g = (x - p) ** 4 + 0.1 * (x - p) ** 2, ca.SX.zeros(0)
    params = np.array([[2.0], [-1.0], [0.5]])
    lam = np.zeros((3, 0))
    bounds = (np.zeros(0), np.zeros(0), np.zeros(1), np.full(1, np.inf))
    rough = MappedNlp("quartic1", x, p, f, g, 1e-12, 1, 1e-8).solve(np.ones((3, 1)), params,
                                                                     lam, *bounds)
    assert not rough.success[0]
    exact = MappedNlp("quartic", x, p, f, g, 1e-12, 50, 1e-8).solve(np.ones((3, 1)), params,
                                                                    lam, *bounds)
    assert exact.success.all()
    np.testing.assert_allclose(exact.x.ravel(), [2.0, 0.0, 0.5], atol=1e-7)


def test_a_batch_packs_into_columns():
    """Batched solutions are instances of one dataclass: they travel as columns."""
    solutions = solve_tasks(formation_tasks(point_masses(4)))
    columns = to_columns(solutions)
    assert np.asarray(columns.column("end_hessian")).shape == (4, 2, 2)


def test_the_solver_option_is_checked():
    with pytest.raises(ValueError, match="unknown DMOC solver 'fatrop'"):
        DmocShape(point_masses(2).shape.model, solver="fatrop")


@pytest.mark.parametrize("columns", [1, 5, 64])
def test_a_constant_kkt_matrix_factorised_once_gives_the_per_column_bits(columns):
    """A point-mass DMOC is a QP: its KKT matrix is constant, and a batch factorises it once.
    From random iterates, multipliers and boundary data, every output of the batched Newton
    step (iterate, multipliers, cost, constraints, dual residual, dJ/dp) is bitwise that of
    the per-column Newton step mapped over the columns; the end Hessian is constant."""
    transcription = dmoc_problem(point_masses(4).shape)
    x, p = transcription._w, transcription._p
    f, g = transcription.cost(x, p), transcription.constraints(x, p)
    system = KktSystem.of(x, p, f, g)
    matrix = system.constant_matrix()
    assert matrix is not None
    assert constant_outputs(transcription.end_hessian)
    rng = np.random.default_rng(3)
    inputs = [rng.standard_normal((n, columns)) * 10 for n in (x.numel(), g.numel(), p.numel())]
    per_column = system.newton("pc", 2).map(columns, "serial")(*inputs)
    batched = system.batched_newton("b", 2, matrix, columns)(*inputs)
    for one, other in zip(per_column, batched, strict=True):
        assert np.asarray(one).tobytes() == np.asarray(other).tobytes()


def test_a_nonlinear_problem_keeps_its_per_column_factorisation():
    """Rigid spacecraft (attitude dynamics): the KKT matrix depends on the iterate, so there
    is no constant matrix, and the end Hessian depends on the solution."""
    transcription = dmoc_problem(halo_example(agents=2, intervals=10).shape)
    x, p = transcription._w, transcription._p
    assert KktSystem.of(x, p, transcription.cost(x, p),
                        transcription.constraints(x, p)).constant_matrix() is None
    assert not constant_outputs(transcription.end_hessian)


@pytest.mark.parametrize(("upper", "accepted"), [(np.inf, [True, True, False]),
                                                 (1.0, [True, False, False])])
def test_the_newton_kernel_accepts_columns_within_their_bounds(upper, accepted):
    """min (x₀ − p)² + (x₁ − p)² s.t. x₀ = x₁: one Newton step reaches x = (p, p). A column is
    accepted where that lies within lbx ≤ x ≤ ubx: p = 2 exceeds a finite x₀ ≤ 1, p = NaN
    never passes."""
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    newton = KktNewton("bounds", x, p, (x[0] - p) ** 2 + (x[1] - p) ** 2, x[0] - x[1], 1, 1e-10)
    params = np.array([[0.5], [2.0], [np.nan]])
    batch = newton.solve(np.zeros((3, 2)), params, np.zeros((3, 1)), np.full(2, -np.inf),
                         np.array([upper, np.inf]))
    assert batch.success.tolist() == accepted
    np.testing.assert_allclose(batch.x[:2], [[0.5, 0.5], [2.0, 2.0]], rtol=1e-14)
