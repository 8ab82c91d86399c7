"""MacsProblem, the public problem of the MACS scheme: checks when it is built, objectives with
running costs against closed forms, and the double-integrator example (a closed-form Pareto
front) with two and three objectives."""

from __future__ import annotations

import dataclasses
import math
import pickle
import re

import casadi as ca
import moocore
import numpy as np
import pytest
from conftest import golden

from ocpar.examples import macs_double_integrator
from ocpar.macs import MacsProblem, MacsSettings, Objective, make_problem, solve_macs
from ocpar.macs.archive import dominates
from ocpar.macs.local_search import SearchTask, run_search
from ocpar.macs.metrics import inverted_generational_distance, normalise
from ocpar.macs.objectives import objective_functions
from ocpar.macs.plot import plot_controls, plot_front
from ocpar.ocp import dfet_problem

DISTANCE, U_MAX = 1.0, 1.0


def closed_form_front(t_lo: float, t_hi: float, n: int = 2000) -> np.ndarray:
    """J2 = 12 d²/J1³: the least ∫u² dt of a rest-to-rest move over d in time J1 (the optimal
    control u = (6d/T²)(1 − 2t/T) is linear in t)."""
    t = np.linspace(t_lo, t_hi, n)
    return np.column_stack([t, 12 * DISTANCE**2 / t**3])


def with_kinetic_objective(problem: MacsProblem) -> MacsProblem:
    """The double integrator with a third objective J3 = ∫v² dt (at least d²/t_f, reached by a
    constant speed that needs infinite acceleration: it conflicts with J2)."""
    third = Objective(running=lambda x, u: x[1] ** 2, name="∫v² dt")
    return dataclasses.replace(problem, name="double-integrator-3",
                               objectives=(*problem.objectives, third), reference_front=None)


def test_running_cost_quadrature_and_resimulation_match_the_closed_form():
    """With the minimum-energy control law of t_f = 3 (linear: exactly a DFET control of order
    1), J = (3, 12/27) on the transcription and when re-simulated."""
    problem = make_problem("double-integrator")
    dfet = dfet_problem(problem.shape)
    t_f = 3.0
    p = dfet.sample_controls(lambda t: 6 / t_f**2 * (1 - 2 * t / t_f), t_f)
    z, ok = dfet.solve_states(p)
    assert ok
    np.testing.assert_allclose(dfet.final_state(z), [DISTANCE, 0.0], atol=1e-10)
    functions = objective_functions(problem)
    transcribed = np.asarray(ca.Function("J", [dfet.z], [functions.symbolic(dfet.z)])(z)).ravel()
    expected = [t_f, 12 * DISTANCE**2 / t_f**3]
    np.testing.assert_allclose(transcribed, expected, rtol=1e-10)
    np.testing.assert_allclose(functions.resimulated(p), expected, rtol=1e-8)


def test_equal_problems_hash_equal_also_after_pickling():
    problem = make_problem("double-integrator")
    copy = pickle.loads(pickle.dumps(problem))
    assert copy == problem and hash(copy) == hash(problem)
    assert make_problem("double-integrator") == problem
    assert with_kinetic_objective(problem) != problem
    assert dataclasses.replace(problem, final_time=(3.0, 4.0)) != problem


def test_a_fixed_final_time_is_kept():
    """t_f fixed (lo == hi): the scalarised search minimises ∫u² dt at t_f = 3."""
    problem = dataclasses.replace(make_problem("double-integrator"), final_time=(3.0, 3.0),
                                  reference_front=None)
    dfet = dfet_problem(problem.shape)
    start = run_search(SearchTask(problem, "restore", p0=(dfet.p_lower + dfet.p_upper) / 2))
    assert start.feasible, start.status
    result = run_search(SearchTask(problem, "scalarised", z0=start.z,
                                   weights=np.array([0.0, 1.0]), utopia=np.array([0.0, 0.0])))
    assert result.feasible, result.status
    assert result.objectives[0] == 3.0
    assert result.objectives[1] == pytest.approx(12 / 27, rel=1e-8)


def test_double_integrator_front_short_run():
    """A short run (1,500 evaluations, archive 20): no member beats the closed-form front, most
    are on it (the others, from restoration only, are not polished yet), and IGD against it is
    ≤ 0.06 (the 10,000-evaluation target, 0.03, is in the slow test)."""
    problem = make_problem("double-integrator")
    result = solve_macs(problem, MacsSettings(max_evaluations=1500, archive_size=20, seed=0))
    j1, j2 = result.front.T
    excess = j2 / (12 * DISTANCE**2 / j1**3) - 1
    assert excess.min() >= -1e-7 and np.median(excess) <= 1e-7, excess
    lo, hi = problem.final_time
    reference = closed_form_front(lo, hi)
    assert inverted_generational_distance(result.front, reference) <= 0.06
    assert result.igd == pytest.approx(inverted_generational_distance(result.front, reference),
                                       abs=1e-3)


@pytest.mark.slow
def test_double_integrator_front_over_five_seeds():
    """The issue's target: mean IGD ≤ 0.03 (normalised) over 5 seeds, 10,000 evaluations,
    archive 20, against the closed-form front."""
    problem = make_problem("double-integrator")
    reference = closed_form_front(*problem.final_time)
    igd = [inverted_generational_distance(
        solve_macs(problem, MacsSettings(archive_size=20, seed=seed)).front, reference)
        for seed in range(5)]
    assert np.mean(igd) <= golden("macs-double-integrator.mean_igd_5_seeds").at_most, igd


@pytest.fixture(scope="module")
def three_objectives():
    problem = with_kinetic_objective(make_problem("double-integrator"))
    return problem, solve_macs(problem, MacsSettings(max_evaluations=1500, archive_size=20,
                                                     seed=1))


def test_three_objectives_archive_filter_and_hypervolume(three_objectives, tmp_path):
    problem, result = three_objectives
    front = result.front_transcribed
    assert front.shape == (20, 3)  # filled, and filtered down to the archive size
    assert not any(dominates(a, b) for a in front for b in front)
    assert moocore.is_nondominated(front).all()
    # on or above the two-objective bounds: J2 ≥ 12 d²/t_f³, J3 ≥ d²/t_f (Cauchy–Schwarz)
    assert np.all(front[:, 1] >= 12 * DISTANCE**2 / front[:, 0] ** 3 * (1 - 1e-6))
    assert np.all(front[:, 2] >= DISTANCE**2 / front[:, 0] * (1 - 1e-6))
    # the three objectives conflict: the front spans each one
    assert np.all(np.ptp(front, axis=0) > 0.1 * np.abs(front).max(axis=0))
    # hypervolume: moocore's on the front normalised to its own ideal and nadir, ref 1.1
    expected = moocore.hypervolume(normalise(result.front, result.front), ref=[1.1] * 3)
    assert result.hv == pytest.approx(expected, rel=1e-12)
    history = [h["hv"] for h in result.history]
    assert history[-1] > history[0]
    assert result.gd is None and result.igd is None
    data = result.to_dict()
    assert data["gd"] is None and data["igd"] is None and len(data["front"][0]) == 3
    assert "GD" not in result.summary() and "HV" in result.summary()
    for picture in (plot_front(result, tmp_path / "front.png"),
                    plot_controls(problem, result, tmp_path / "controls.png")):
        assert picture.read_bytes().startswith(b"\x89PNG")


def _model_without_rhs():
    @dataclasses.dataclass(frozen=True)
    class NoRhs:
        nx: int = 2
        nu: int = 1

        def state_bounds(self):
            return np.full(2, -np.inf), np.full(2, np.inf)

    return NoRhs()


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"initial_state": (0.0, 0.0, 0.0)}, "initial_state"),
        ({"initial_state": (0.0, math.nan)}, "initial_state"),
        ({"final_time": (3.0, 2.0)}, "final_time"),
        ({"final_time": (0.0, 2.0)}, "final_time"),
        ({"control_bounds": ((-1.0, math.inf),)}, "control_bounds"),
        ({"control_bounds": ((1.0, -1.0),)}, "control_bounds"),
        ({"control_bounds": ((-1.0, 1.0), (-1.0, 1.0))}, "control_bounds"),
        ({"final_state": {2: 1.0}}, "final_state"),
        ({"final_state": {0: math.inf}}, "final_state[0]"),
        ({"periodic_controls": (True, False)}, "periodic_controls"),
        ({"elements": 0}, "elements"),
        ({"order": 1.5}, "order"),
        ({"objectives": (Objective(mayer=lambda xf, tf: tf),)}, "objectives"),
        ({"objectives": (Objective(mayer=lambda xf, tf: tf), Objective())}, "objectives[1]"),
        ({"objectives": (Objective(mayer=lambda xf, tf: xf[5]),
                         Objective(running=lambda x, u: u[0] ** 2))}, "objectives[0].mayer"),
        ({"objectives": (Objective(mayer=lambda xf, tf: tf),
                         Objective(running=lambda x, u: x))}, "objectives[1].running"),
        ({"objectives": (Objective(mayer=lambda xf, tf: tf),
                         Objective(mayer=lambda xf, tf: 1 / (tf - tf)))}, "objectives[1].mayer"),
        ({"objectives": (Objective(mayer=lambda xf, tf: tf), "J2")}, "objectives[1]"),
        ({"reference_front": np.ones((5, 3))}, "reference_front"),
        ({"reference_front": np.full((5, 2), np.nan)}, "reference_front"),
        ({"model": _model_without_rhs()}, "model.rhs"),
        ({"model": "double integrator"}, "model"),
        ({"name": ""}, "name"),
    ],
)
def test_malformed_problems_raise_one_error_naming_the_field(change, field):
    with pytest.raises(ValueError, match="^" + re.escape(f"MacsProblem.{field}: ")) as info:
        dataclasses.replace(macs_double_integrator.make(), **change)
    assert "\n" not in str(info.value)


def test_boundary_data_outside_the_state_bounds_is_refused():
    """Orbit raising bounds r ≥ 0.1: a start or a final radius below it is refused."""
    problem = make_problem("orbit-raising")
    with pytest.raises(ValueError, match=r"^MacsProblem\.initial_state: .*state bounds"):
        dataclasses.replace(problem, initial_state=(0.05, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match=r"^MacsProblem\.final_state\[0\]: .*state bounds"):
        dataclasses.replace(problem, final_state={0: 0.05})
