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

from ocpar.examples import macs_double_integrator, macs_thrust_limited
from ocpar.macs import MacsProblem, MacsSettings, Objective, make_problem, solve_macs
from ocpar.macs.archive import Member, dominates
from ocpar.macs.local_search import STATIONARITY_TOL, SearchTask, inner_solvers, run_search
from ocpar.macs.metrics import igd_floor, inverted_generational_distance, normalise
from ocpar.macs.objectives import objective_functions
from ocpar.macs.plot import plot_controls, plot_front
from ocpar.macs.solve import run_status
from ocpar.ocp import dfet_problem
from ocpar.ocp.constraints import NormSquared, PathConstraint

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


SHORT = MacsSettings(max_evaluations=1500, archive_size=20, seed=0)


@pytest.fixture(scope="module")
def short_runs():
    """The double integrator, 1,500 evaluations, archive 20, without and with the final
    placement and refinement (the same loop: they only follow it)."""
    problem = make_problem("double-integrator")
    return (solve_macs(problem, dataclasses.replace(SHORT, no_refine=True, no_spread=True)),
            solve_macs(problem, SHORT))


def excess(front: np.ndarray) -> np.ndarray:
    """How far each member (k, 2) lies above the closed-form front, relative."""
    return front[:, 1] / (12 * DISTANCE**2 / front[:, 0] ** 3) - 1


def test_double_integrator_front_short_run(short_runs):
    """A short run (1,500 evaluations, archive 20): no member beats the closed-form front, all
    are on it after the refinement, and IGD against it is ≤ 0.06 (the 10,000-evaluation
    target, 0.03, is in the slow test)."""
    _, result = short_runs
    problem = make_problem("double-integrator")
    assert excess(result.front).min() >= -1e-7 and excess(result.front).max() <= 1e-7
    lo, hi = problem.final_time
    reference = closed_form_front(lo, hi)
    assert inverted_generational_distance(result.front, reference) <= 0.06
    assert result.igd == pytest.approx(inverted_generational_distance(result.front, reference),
                                       abs=1e-3)


def test_refinement_puts_every_member_on_the_front_and_reports_it(short_runs, tmp_path):
    """Without the refinement two members of this run lie 1.5e-4 and 2e-4 above the closed-form
    front; with it every one is on it to 1e-7 and is stationary, each member of the archive
    refined from its own point (no neighbour's start beat one: none moved), in two more
    supersteps (one round of starts, the stationarity measure); its evaluations (three starts
    per inner member, two per end) are reported and counted in the total. result.json
    carries the flags, residuals and weights (null without the refinement)."""
    plain, refined = short_runs
    assert excess(plain.front).max() > 1e-4 and plain.stationarity is None
    # the placement's superstep, one round of starts, the stationarity measure
    assert refined.supersteps == plain.supersteps + 3 and refined.refinement_rounds == 1
    assert refined.evaluations == (plain.evaluations + refined.refinement_evaluations
                                   + refined.spread["evaluations"])
    assert 0 < refined.refinement_evaluations <= 3 * 20 * len(refined.front)
    assert not refined.moved.any() and refined.settled.all() and not refined.improvement.any()
    assert np.abs(excess(refined.front)).max() <= 1e-7
    assert refined.refined.all() and refined.converged.all()
    assert refined.stationarity.max() <= 1e-8 and refined.tradeoff.shape == (len(refined.front), 2)
    data = refined.to_dict()["refinement"]
    assert data["converged"] == [True] * len(refined.front)
    assert data["evaluations"] == refined.refinement_evaluations
    assert plain.to_dict()["refinement"] is None
    plot_front(refined, tmp_path / "front.png")  # converged members drawn filled
    # the status means every member converged: the refined run is, the plain one is not
    # (nothing checked its members), and says why
    assert refined.status == "converged" and refined.to_dict()["igd"] is not None
    assert plain.status == "not_converged" and plain.to_dict()["igd"] is None
    assert "refinement was skipped" in plain.message


def test_placement_brings_the_front_to_its_floor(short_runs):
    """On the double integrator's closed-form front J2 = 12 d²/J1³ the placed archive's IGD is
    within 10 % of the best 20 points of that front (measured 0.0198 against 0.0182; the
    loop's own archive 0.034), every target reached; the placement's evaluations are
    reported beside the budget, and the floor estimated from the members alone is close to
    the one of the reference."""
    plain, placed = short_runs
    problem = make_problem("double-integrator")
    floor = igd_floor(problem.reference_front, 20)
    assert placed.igd <= 1.1 * floor
    assert 1.1 * floor < inverted_generational_distance(plain.front, problem.reference_front)
    spread = placed.to_dict()["spread"]
    assert spread["placed"] == spread["targets"] == 18 and spread["evaluations"] > 0
    assert len(spread["gaps"]) == len(placed.front) - 1
    assert spread["igd"] <= 1.1 * spread["floor"]
    assert spread["floor"] == pytest.approx(floor, rel=0.1)
    assert plain.spread is None and plain.to_dict()["spread"] is None


def test_a_run_with_a_member_not_converged_is_not_converged(short_runs):
    """The same members, one of them given a stationarity residual above the tolerance and
    another unsettled: the run's status counts and names them."""
    _, refined = short_runs
    members = [Member(z=np.zeros(1), objectives=f, settled=True, stationarity=s)
               for f, s in zip(refined.front, refined.stationarity, strict=True)]
    assert run_status(members, None) == ("converged", "")
    members[3].stationarity = 10 * STATIONARITY_TOL
    members[7].settled = False
    status, message = run_status(members, None)
    assert status == "not_converged"
    assert message.startswith(f"2 of {len(members)} archive members not converged")
    assert message.endswith("members 3, 7")


def test_stationarity_measures_the_fronts_slope_and_its_distance():
    """From a restored point (not optimal) the ε-constraint refinement reaches the transcribed
    front; there the residual is ~0 and the weights are the front's slope, w1/w2 =
    −dJ2/dJ1 · s1/s2 = (36 d²/J1⁴) s1/s2; at the restored point the residual is large."""
    problem = make_problem("double-integrator")
    dfet = dfet_problem(problem.shape)
    start = run_search(SearchTask(problem, "restore", p0=(dfet.p_lower + dfet.p_upper) / 2))
    span = np.array([2.0, 0.5])
    solvers = inner_solvers(problem)
    assert solvers.stationarity(start.z, span)[0] > 1e-4
    result = run_search(SearchTask(problem, "refine", z0=start.z, span=span))
    measured = run_search(SearchTask(problem, "stationarity", z0=result.z, span=span))
    assert result.refined and result.feasible and measured.stationarity <= 1e-8
    assert measured.evaluations == 0 and np.array_equal(measured.z, result.z)
    assert dominates(result.objectives, start.objectives)
    j1 = result.objectives[0]
    assert result.objectives[1] == pytest.approx(12 * DISTANCE**2 / j1**3, rel=1e-8)
    w1, w2 = measured.tradeoff
    assert w1 + w2 == pytest.approx(1.0) and w1 / w2 == pytest.approx(
        36 * DISTANCE**2 / j1**4 * span[0] / span[1], rel=1e-5)


@pytest.mark.slow
def test_double_integrator_front_over_five_seeds():
    """The issue's target: mean IGD ≤ 0.03 (normalised) over 5 seeds, 10,000 evaluations,
    archive 20, against the closed-form front; after the final refinement every member within
    1e-4 of it, relative (measured 1.4e-8 at most), and stationary."""
    problem = make_problem("double-integrator")
    reference = closed_form_front(*problem.final_time)
    results = [solve_macs(problem, MacsSettings(archive_size=20, seed=seed)) for seed in range(5)]
    igd = [inverted_generational_distance(r.front, reference) for r in results]
    assert np.mean(igd) <= golden("macs-double-integrator.mean_igd_5_seeds").at_most, igd
    for result in results:
        assert np.abs(excess(result.front)).max() <= 1e-4 and result.converged.all()


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


# --- path constraints: a norm thrust limit (ocpar.examples.macs_thrust_limited) -----------------

def opti_least_energy(t_f: float, target: np.ndarray, thrust: float, n: int = 400) -> float:
    """An independent solve of the fixed-t_f problem: min ∫|u|² dt of a planar unit mass rest
    to rest onto ``target`` with |u| ≤ ``thrust``, exact zero-order-hold steps of n intervals
    (the control constant per interval, so the limit holds at all times)."""
    opti = ca.Opti()
    u = opti.variable(2, n)
    h = t_f / n
    r, v = ca.DM.zeros(2), ca.DM.zeros(2)
    for k in range(n):
        r, v = r + h * v + h**2 / 2 * u[:, k], v + h * u[:, k]
        opti.subject_to(ca.sumsqr(u[:, k]) <= thrust**2)
    opti.subject_to(r == target)
    opti.subject_to(v == 0)
    opti.minimize(h * ca.sumsqr(u))
    opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes"})
    return float(opti.solve().value(opti.f))


def test_thrust_limited_closed_form_front_matches_an_independent_solve():
    """The example's closed form on both sides of √6 (the limit binds below it): an Opti solve
    of n = 400 zero-order-hold intervals agrees to 1e-4 relative (its O(h²) error)."""
    problem = macs_thrust_limited.make()
    target = np.array([problem.final_state[0], problem.final_state[1]])
    for t_f in (2.2, 2.8):
        (_, expected), = macs_thrust_limited.front(np.array([t_f]))
        assert opti_least_energy(t_f, target, 1.0) == pytest.approx(expected, rel=1e-4)
    free = 12 / 2.2**3
    assert macs_thrust_limited.front(np.array([2.2]))[0, 1] > 1.01 * free  # binds: 1.3 % above


@pytest.fixture(scope="module")
def thrust_limited():
    problem = macs_thrust_limited.make()
    return problem, solve_macs(problem, MacsSettings(max_evaluations=3000, archive_size=20,
                                                     seed=0))


def test_thrust_limited_front_lies_on_the_closed_form_and_keeps_the_limit(thrust_limited):
    """A run of 3000 evaluations: no member below the closed-form front (without the limit the
    members at t_f < √6 would lie up to 4.8 % below it), at least three where the limit binds,
    every member stationary after the final refinement (without it two lay 1.3 % and 3 %
    above the front): on the front to 1e-6 where the limit is inactive, and within 2e-3 where
    it binds, the transcription's own error there (its least energy at a fixed t_f, 8 linear
    elements, is up to 1.15e-3 above the closed form: 2.15, 2.3); and every member's control
    law within |u| ≤ 1.02 everywhere: the limit is imposed at the quadrature points, and a
    linear control reaches past them to the element's ends (measured 1.0146)."""
    problem, result = thrust_limited
    j1, j2 = result.front.T
    excess = j2 / macs_thrust_limited.front(j1)[:, 1] - 1
    assert excess.min() >= -1e-5 and excess.max() <= 2e-3, excess
    binding = j1 < np.sqrt(6) * 0.99
    assert binding.sum() >= 3 and np.median(excess[binding]) <= 1e-3, (j1, excess)
    assert np.abs(excess[j1 > np.sqrt(6) * 1.01]).max() <= 1e-6
    assert result.converged.all(), result.stationarity
    dfet = dfet_problem(problem.shape)
    for p in result.decisions:
        law = dfet.control_law(p)
        t = np.linspace(0, dfet.final_time(p), 400)
        assert max(np.linalg.norm(law(s)) for s in t) <= 1.02
    assert result.igd <= 0.05, result.igd


def test_a_search_that_cannot_meet_a_path_constraint_is_infeasible():
    """With the limit at 0.9 the bang–bang minimum time is 2√(1/0.9) = 2.108: at t_f fixed to
    2.05 no control meets it, the restoration fails and its result is infeasible (never
    archived)."""
    problem = dataclasses.replace(
        macs_thrust_limited.make(), final_time=(2.05, 2.05), reference_front=None,
        path_constraints=(PathConstraint(lambda u: ca.sumsqr(u), upper=0.81, name="thrust"),))
    dfet = dfet_problem(problem.shape)
    result = run_search(SearchTask(problem, "restore", p0=(dfet.p_lower + dfet.p_upper) / 2))
    assert not result.feasible


@pytest.mark.parametrize(("constraints", "message"), [
    ((PathConstraint(lambda q: q[0], name="pos"),), "function takes 'q'"),
    ((PathConstraint(lambda u: u[0] ** 2, upper=-1.0, name="thrust"),), None),
    ((PathConstraint(lambda x: x[0], lower=0.5, upper=np.inf, name="away"),),
     "broken by 0.5 at the initial state"),
    ((PathConstraint(lambda x, u: 1 / (x[0] * u[0]), name="pole"),), "not finite"),
    ((PathConstraint(lambda u: ca.sumsqr(u), upper=(1.0, 2.0), name="thrust"),), "upper"),
    (PathConstraint(lambda u: u[0], name="bare"), "list of PathConstraint"),
])
def test_malformed_path_constraints_are_one_error_naming_the_field(constraints, message):
    """Refused when the problem is built, one line naming MacsProblem.path_constraints; a
    control-only limit that no control can meet (|u|² ≤ −1) is left to the searches (each one
    infeasible: the run ends with an empty front, as an infeasible problem does)."""
    build = lambda: dataclasses.replace(macs_thrust_limited.make(),  # noqa: E731
                                        path_constraints=constraints)
    if message is None:
        build()
        return
    with pytest.raises(ValueError, match=r"^MacsProblem\.path_constraints") as info:
        build()
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_thrust_limit_written_with_norm_2_gives_the_squared_forms_front():
    """``ca.norm_2(u) <= 1`` (no derivative at u = 0, the DFET's default guess) is compiled as
    |u|² ≤ 1 with a NormSquared warning: a short run (400 evaluations, seed 0) returns the
    squared form's front to 1e-8, with members where the limit binds (t_f < √6)."""
    squared = macs_thrust_limited.make()
    with pytest.warns(NormSquared, match="thrust"):
        written = dataclasses.replace(squared, path_constraints=(
            PathConstraint(lambda u: ca.norm_2(u), upper=1.0, name="thrust"),))
    settings = MacsSettings(max_evaluations=400, archive_size=10, seed=0)
    a, b = solve_macs(written, settings), solve_macs(squared, settings)
    assert a.status == b.status == "converged"
    np.testing.assert_allclose(a.front, b.front, rtol=0, atol=1e-8)
    assert np.any(np.asarray(a.front)[:, 0] < math.sqrt(6))
