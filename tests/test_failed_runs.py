"""A run reports no figure it did not reach, in every scheme: made to fail or stopped early
honestly through the public API, its Python result holds no headline figure (NaN or None, the
last iterate's kept apart in ``last_iterate``), its result file has null headline figures,
its summary says "not reached" and prints no sentinel number,
its status line names the first failed solve and how many, and its plots' titles say its
status and why. (The formation's: tests/test_verify.py,
test_a_failed_run_reports_no_cost_and_its_plot_says_why.)"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import assert_no_sentinel

import ocpar
import ocpar.macs.plot
import ocpar.pursuit.plot
from ocpar.examples import formation_point_masses, macs_double_integrator, pursuit_van_der_pol
from ocpar.formation import FormationOptions, solve_formation
from ocpar.macs import MacsSettings, solve_macs
from ocpar.macs.run import MacsRun
from ocpar.pursuit import PursuitSettings, solve_pursuit
from ocpar.result_files import write_result


def record_titles(monkeypatch, module) -> list[str]:
    """The titles (axes and figure) of every figure ``module``'s plot functions save."""
    titles: list[str] = []
    save = module.save

    def recording(fig, path):
        titles.extend(ax.get_title() for ax in fig.axes)
        if fig._suptitle is not None:
            titles.append(fig._suptitle.get_text())
        return save(fig, path)

    monkeypatch.setattr(module, "save", recording)
    return titles


def test_a_pursuit_run_to_an_unreachable_target_reports_no_cost(tmp_path, monkeypatch):
    """van der Pol to x(4) = (50, 0) with |u| ≤ 1: every free-running solve to the target set
    is infeasible (agent 1's first, at sample N − N_Δ = 20), and so is the certificate."""
    problem = dataclasses.replace(pursuit_van_der_pol.make(), target=np.array([50.0, 0.0]))
    result = solve_pursuit(problem, PursuitSettings(window=21, update=10, max_agents=6),
                           reference=False)
    assert result.status != "converged" and result.failed_solves > 0
    assert abs(result.x[-1, 0] - 50) > 10  # the returned trajectory misses the target
    write_result(result, tmp_path)
    ds, data = ocpar.load(tmp_path)
    assert data["status"] == result.status
    assert data["cost"] is None and data[result.cost_key] is None
    assert ds.sizes["agent"] == 7  # the train's history stays: agents 0 to 6
    assert "not reached (not_converged: " in result.summary()
    assert math.isnan(result.headline) and math.isnan(result.cost)
    assert_no_sentinel(result.summary())
    why = (f"{result.failed_solves} of {result.subproblem_solves} subproblem solves failed, "
           f"the first agent 1 at sample 20: Infeasible_Problem_Detected")
    assert result.message.startswith(why)
    assert result.title() == f"not converged: {why}"
    titles = record_titles(monkeypatch, ocpar.pursuit.plot)
    for path in (ocpar.pursuit.plot.plot_trajectories(problem, result, tmp_path / "p.png"),
                 ocpar.pursuit.plot.plot_convergence(result, tmp_path / "c.png")):
        assert path.stat().st_size > 0
    assert len(titles) >= 2
    for title in (titles[0], titles[-1]):  # the first panel's and the convergence plot's
        assert "not converged: " in title and "Infeasible_Problem_Detected" in title
    assert not any("cost " in t for t in titles)


def test_a_macs_run_with_no_feasible_point_reports_no_front_metrics(tmp_path, monkeypatch):
    """The double integrator rest to rest over d = 1 with |u| ≤ 1 but t_f ≤ 1: the farthest
    it can go is t_f²/4 = 0.25 (bang-bang), so every search fails and the archive stays
    empty."""
    problem = dataclasses.replace(macs_double_integrator.make(), final_time=(0.5, 1.0))
    assert max(problem.final_time) ** 2 / 4 < 1.0
    result = solve_macs(problem, MacsSettings(max_evaluations=100, archive_size=5, seed=1))
    assert result.status == "failed" and len(result.front) == 0
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["status"] == "failed"
    assert data["gd"] is None and data["igd"] is None and data["hv"] is None
    summary = result.summary()
    assert "not reached (failed: no feasible archive member" in summary
    assert result.gd is None and result.hv is None
    assert result.last_iterate == {"hv": 0.0}   # an empty archive's: no GD, IGD against it
    assert_no_sentinel(summary)
    assert "HV 0" not in summary
    why = (f"no feasible archive member: all {result.failed_searches} searches failed "
           f"({result.evaluations} evaluations), the first Infeasible_Problem_Detected")
    assert result.failed_searches > 0 and result.message == why
    assert result.title() == f"failed: {why}"
    titles = record_titles(monkeypatch, ocpar.macs.plot)
    # the driver's plots: the (empty) front titled failed and why, no members' controls
    assert MacsRun().plot(problem, result, tmp_path) == [tmp_path / "front.png"]
    assert (tmp_path / "front.png").stat().st_size > 0
    (suptitle,) = [t for t in titles if t]
    assert "failed: no feasible archive member" in suptitle.replace("\n", " ")
    assert "HV" not in suptitle


@pytest.mark.parametrize("status", ["not_converged", "failed"])
def test_the_title_is_the_headline_only_if_converged(status):
    """The one title rule (RunResult.title) on a pursuit result: converged → the headline."""
    problem = pursuit_van_der_pol.make()
    result = solve_pursuit(problem, PursuitSettings(window=21, update=10, max_agents=2),
                           mode="ms", reference=False)
    assert result.status == "converged"
    assert result.title() == f"cost {result.headline:.6f}"
    other = dataclasses.replace(result, status=status, message="why; more")
    assert other.title() == f"{status.replace('_', ' ')}: why"


def test_a_formation_run_capped_at_too_few_outer_iterations_holds_no_cost(tmp_path):
    """The paper's point masses (12) with one outer iteration where the optimum takes 4: not
    converged, and no total cost anywhere as a headline: NaN in Python (and each cost part),
    null in result.json, "not reached" in the summary; the last iterate's cost is kept
    apart (``last_iterate``): the sum of the returned paths' costs, above the optimum."""
    problem = formation_point_masses.make(agents=12)
    optimum = solve_formation(problem)
    assert optimum.converged and optimum.outer_iterations > 1
    result = solve_formation(problem, options=FormationOptions(max_outer_iterations=1))
    assert result.status == "not_converged" and result.outer_iterations == 1
    assert math.isnan(result.total_cost) and math.isnan(result.unconstrained_cost)
    assert all(math.isnan(v) for v in result.cost_parts.values())
    reached = result.last_iterate["total_cost"]
    assert reached == pytest.approx(float(np.sum(result.agent_costs)), rel=1e-12)
    assert reached > optimum.total_cost * (1 + 1e-6)   # not the optimum: no headline
    assert set(result.last_iterate) == {"total_cost"}   # no separation: no unconstrained cost
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["total_cost"] is None and data["outer_iterations"] == 1
    summary = result.summary()
    assert "total cost — not reached (not_converged: iteration limit reached)" in summary
    assert "outer iterations 1 " in summary
    assert_no_sentinel(summary)
    assert optimum.last_iterate == {}   # a converged run keeps its figures as headlines
    assert "not reached" not in optimum.summary()


def test_a_macs_run_stopped_before_its_refinement_holds_no_front_metrics(tmp_path):
    """The double integrator with the final refinement skipped (no member's stationarity
    checked): not converged; GD, IGD and HV are None in Python and null in result.json, the
    last iterate's kept apart, equal to the metrics of the front it returned."""
    from ocpar.macs.metrics import generational_distance, hypervolume

    problem = macs_double_integrator.make()
    result = solve_macs(problem, MacsSettings(max_evaluations=150, archive_size=5, seed=1,
                                              no_refine=True))
    assert result.status == "not_converged" and len(result.front) >= 2
    assert result.gd is None and result.igd is None and result.hv is None
    assert set(result.last_iterate) == {"gd", "igd", "hv"}
    assert result.last_iterate["gd"] == generational_distance(
        result.front, problem.reference_front, interpolate=True)
    assert result.last_iterate["hv"] == hypervolume(result.front, problem.reference_front)
    data = json.loads(write_result(result, tmp_path)[0].read_text())
    assert data["gd"] is None and data["igd"] is None and data["hv"] is None
    summary = result.summary()
    assert "GD, IGD, HV not reached (not_converged: the final refinement was skipped" in summary
    assert "HV of the objectives" not in summary
    assert_no_sentinel(summary)
