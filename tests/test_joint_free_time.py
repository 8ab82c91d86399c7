"""The free common final time as an outer variable (ocpar.formation.joint_time): the sums
one superstep returns at (θ, T) (J, its first and second derivatives in θ and T and the cross
term, from the inner problems' multipliers and KKT systems, reduced on the workers) against
central differences of those sums; the joint search in a few supersteps more than a fixed-T
solve; the formation solve per T (kept where no shift family is searched) reaching the
same T; a common T's KKT matrix factorised once per block."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ocpar.bsp.serial import SerialBackend
from ocpar.examples import formation_minimum_time, formation_point_masses, formation_unicycles
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.final_time import at_duration
from ocpar.formation.hierarchical import OuterObjective
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, transcription

WEIGHT = 1e3


@pytest.mark.parametrize("mixed", [False, True], ids=["unicycles", "mixed"])
def test_superstep_sums_are_the_finite_differences(mixed):
    """4 unicycles (every second a DMOC point mass where ``mixed``) at a shift θ and T:
    J as with T fixed; dJ/dθ, dJ/dT, d²J/dθ², d²J/dT² and d²J/dθ dT (both ways) against
    central differences of J and of the returned first derivatives."""
    problem = formation_unicycles.make(agents=4, mixed=mixed)
    theta, duration, step = 0.3, 5.0, 1e-4
    timed = problem.with_shapes(lambda shape: dataclasses.replace(
        shape, free_duration=True, duration=duration))
    family = problem.coupling.family(problem.initial_phi(), problem.curve)
    objective = OuterObjective(timed, SerialBackend())
    try:
        def at(d_theta: float, d_time: float):
            return objective.shifted(family, theta + d_theta, duration + d_time)

        here = at(0.0, 0.0)
        plus_t, minus_t = at(step, 0.0), at(-step, 0.0)
        plus_T, minus_T = at(0.0, step), at(0.0, -step)
    finally:
        objective.close()
    fixed = OuterObjective(at_duration(problem, duration), SerialBackend())
    try:   # the same J with T a constant of the inner problems
        assert here.value == pytest.approx(fixed.shifted(family, theta).value, rel=1e-9)
    finally:
        fixed.close()

    def central(plus: float, minus: float) -> float:
        return (plus - minus) / (2 * step)

    assert here.slope == pytest.approx(central(plus_t.value, minus_t.value), rel=1e-6)
    assert here.time_slope == pytest.approx(central(plus_T.value, minus_T.value), rel=1e-6)
    assert here.curvature == pytest.approx(central(plus_t.slope, minus_t.slope), rel=1e-5)
    assert here.time_curvature == pytest.approx(
        central(plus_T.time_slope, minus_T.time_slope), rel=1e-5)
    assert here.cross == pytest.approx(central(plus_t.time_slope, minus_t.time_slope),
                                       rel=1e-5)
    assert here.cross == pytest.approx(central(plus_T.slope, minus_T.slope), rel=1e-5)
    assert abs(here.cross) > 1e-3 * abs(here.time_slope)   # a term that could be wrong


def test_joint_search_takes_a_few_supersteps_more_than_a_fixed_solve():
    """60 point masses: the joint (θ, T) search and the answer's solve at T* take at most
    two supersteps more than the fixed-T solve from the same start, and reach the closed
    form T* = (3 J_1 / w)^¼."""
    problem = formation_point_masses.make()
    fixed = solve_formation(problem)
    result = solve_formation(problem, options=FormationOptions(
        final_time="free", time_bounds=(0.5, 100.0), time_weight=WEIGHT, time_tol=1e-10))
    assert result.converged and result.final_time["method"] == "joint"
    expected = (3 * fixed.total_cost / WEIGHT) ** 0.25
    assert abs(result.final_time["T"] - expected) <= 1e-9 * expected
    assert len(result.trace) <= len(fixed.trace) + 2


def test_a_formation_solve_per_t_reaches_the_same_t():
    """The outer solver ``offset`` searches no shift family: T by a formation solve per T,
    the same T as the joint search's (12 point masses)."""
    problem = formation_point_masses.make(agents=12)
    found = {}
    for outer in ("newton", "offset"):
        result = solve_formation(problem, options=FormationOptions(
            outer=outer, final_time="free", time_bounds=(0.5, 100.0), time_weight=WEIGHT,
            time_tol=1e-10))
        assert result.converged, result.message
        found[result.final_time["method"]] = result
    assert set(found) == {"joint", "sequence"}
    assert found["sequence"].final_time["T"] == pytest.approx(found["joint"].final_time["T"],
                                                              rel=1e-10)
    assert len(found["joint"].trace) < len(found["sequence"].trace)


@pytest.mark.slow
def test_an_infeasible_first_t_is_left_by_the_sequence():
    """Thrust limits: where no formation is within reach at the first T (7.3), the
    formation solves per T find one, then the same T as the joint search from T = 10."""
    found = {}
    for duration in (10.0, 7.3):
        problem = at_duration(formation_minimum_time.make(), duration)
        result = solve_formation(problem, options=FormationOptions(
            final_time="free", time_bounds=(7.26, 100.0), time_weight=100.0, time_tol=1e-9))
        assert result.converged, result.message
        found[result.final_time["method"]] = result.final_time["T"]
    assert set(found) == {"joint", "sequence"}
    assert found["sequence"] == pytest.approx(found["joint"], rel=1e-8)


def test_a_common_t_factorises_the_kkt_matrix_once_per_block():
    """Point masses with T a parameter: the KKT matrix depends on T alone, so a block of
    columns of one T shares its factorisation (Newton step and end Hessian): the same bits
    as factorising it column by column."""
    shape = DmocShape(PointMass(dim=2, mass=1.0), duration=3.0, free_duration=True)
    solver = transcription(shape).batch_solver
    assert solver.shared_rows == [shape.n_params - 1]
    params = np.zeros((40, shape.n_params))
    params[:, 4:6] = np.random.default_rng(0).normal(size=(40, 2))
    params[:, -1] = 2.5
    guesses = [None] * len(params)
    shared = transcription(shape).solve_batch(params, guesses, guesses)
    rows, solver.shared_rows = solver.shared_rows, None
    try:
        alone = transcription(shape).solve_batch(params, guesses, guesses)
    finally:
        solver.shared_rows = rows
    for name in ("cost", "cost_gradient", "end_hessian", "q", "u"):
        np.testing.assert_array_equal(np.asarray(shared.column(name)),
                                      np.asarray(alone.column(name)))
    fixed = transcription(DmocShape(PointMass(dim=2, mass=1.0), duration=2.5)).solve_batch(
        params[:, :-1], guesses, guesses)
    np.testing.assert_allclose(np.asarray(shared.column("cost")),
                               np.asarray(fixed.column("cost")), rtol=1e-12)
