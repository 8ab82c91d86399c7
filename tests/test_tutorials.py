"""The tutorials run as the pages show them (issue 41): through ``scripts/tutorials.py``, every
file of docs/tutorials/{formation,pursuit,macs,own-dynamics}.md written into a fresh directory
and every command run there in one shell; each command ends with status 0 and prints what the
page shows (numbers to 1e-9 relative; wall times, memory, dates and job ids aside), and the
figures the prose quotes of runs it shows no output of are those runs'. Steps 4–6 (``mpirun``,
a Dask cluster and detached jobs) run in the slow test."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import script_module

import ocpar

tutorials = script_module("tutorials")
#: The steps of each page that run in the default test (the others need a cluster).
DEFAULT_STEPS = {"own-dynamics": {"2.", "3.", "6.", "7."}}


def _problems(name: str, runs) -> list[str]:
    """What went wrong in tutorial ``name``'s runs: a command that failed, or printed other
    than the page shows."""
    found = []
    for run in runs:
        where = f"{name}.md, {run.command.section}: {run.command.text.strip()}"
        if run.exit_status != 0:
            found.append(f"{where}\nexit status {run.exit_status}:\n{run.printed}")
        elif run.command.shown is not None:
            found += [f"{where}\n{d}" for d in tutorials.differences(run.command.shown,
                                                                      run.printed)]
    return found


@pytest.fixture(scope="module", params=tutorials.TUTORIALS)
def tutorial(request, tmp_path_factory):
    """A tutorial's name, its directory and its commands as run (those without a cluster)."""
    directory = tmp_path_factory.mktemp(request.param)
    return request.param, directory, tutorials.run_tutorial(request.param, directory)


def _quoted(name: str, pattern: str) -> tuple[float, ...]:
    """The figures the page ``name`` quotes where ``pattern`` (with groups) matches."""
    text = " ".join((tutorials.DOCS / f"{name}.md").read_text().split())
    match = re.search(pattern, text)
    assert match, f"{name}.md no longer says {pattern!r}"
    return tuple(float(figure) for figure in match.groups())


def test_every_command_ends_and_prints_what_the_page_shows(tutorial):
    name, _, runs = tutorial
    assert {run.command.section[:2] for run in runs} >= DEFAULT_STEPS.get(
        name, {"2.", "3.", "7.", "8."})
    problems = _problems(name, runs)
    assert not problems, "\n\n".join(problems)


def test_the_figures_quoted_are_the_runs(tutorial):
    name, directory, _ = tutorial
    if name == "formation":
        (cost,) = _quoted(name, r"the second \(2 × 4 agents\) ends at total cost (\S+)\.")
        for run in ("lobes-8", "lobes-8-toml"):
            summary = json.loads((directory / "runs" / run / "result.json").read_text())
            assert summary["agents"] == 8
            assert summary["total_cost"] == pytest.approx(cost, rel=1e-12)
        peak, free = _quoted(name, r"the agents peak at ([\d.]+) and the cost is ([\d.]+);")
        ds, summary = ocpar.load(directory / "runs" / "lobes-cli")
        assert float(ds["peak_thrust"].max()) == pytest.approx(peak, abs=0.05)
        assert summary["total_cost"] == pytest.approx(free, abs=5e-4)
    elif name == "pursuit":
        cost, train = _quoted(name, r"it returns ([\d.]+) after agent 1, the full-horizon MS "
                                    r"of that discretisation \(the train's agent 1: ([\d.]+)\)")
        summary = json.loads((directory / "runs" / "pendulum-121" / "result.json").read_text())
        assert (summary["samples"], summary["window"], summary["update"]) == (121, 41, 20)
        assert summary["cost"] == pytest.approx(cost, abs=5e-7)
        assert summary["train_cost"] == pytest.approx(train, abs=5e-7)
        assert summary["agents"] == 1
    elif name == "own-dynamics":
        _own_dynamics_figures(directory)
    else:
        (extra,) = _quoted(name, r"from its own point and from its neighbours' on the front, "
                                 r"(\d+) more evaluations")
        summary = json.loads((directory / "runs" / "cart" / "result.json").read_text())
        assert summary["evaluations"] - summary["history"][-1]["evaluations"] == extra
        ds, _ = ocpar.load(directory / "runs" / "cart-cli")
        np.testing.assert_array_equal(ds["front"].values, np.array(summary["front"]))


def _own_dynamics_figures(directory) -> None:
    """The free final time's figures the page quotes are the runs': T and the effort of the
    command line's run, the fixed T's cost of the Python run's file; the acceleration bound
    binds and the robots end on the circle, at rest (from the array file)."""
    name = "own-dynamics"
    free_time, fixed_effort, free_effort = _quoted(
        name, r"the robot takes ([\d.]+) s instead of 6, and its effort ∫ a² \+ ω² dt falls "
              r"from ([\d.]+) to ([\d.]+):")
    free = json.loads((directory / "runs" / "robot-free" / "result.json").read_text())
    fixed = json.loads((directory / "runs" / "robot-fixed" / "result.json").read_text())
    assert free["status"] == fixed["status"] == "converged" and free["free_final_time"]
    assert free["final_time"] == pytest.approx(free_time, abs=5e-3)
    assert free["cost"] - 0.1 * free["final_time"] == pytest.approx(free_effort, abs=5e-5)
    assert fixed["cost"] == pytest.approx(fixed_effort, abs=5e-5)
    assert fixed["final_time"] == 6.0 and free_effort < fixed_effort
    ds, _ = ocpar.load(directory / "runs" / "robot-free")
    assert ds["time"].values[-1] == pytest.approx(free["final_time"], rel=1e-12)
    assert ds["time"].attrs["units"] == "s"
    assert ds["state_component_units"].values.tolist() == ["m", "m", "rad", "m/s"]
    assert ds["control_component_units"].values.tolist() == ["m/s^2", "rad/s"]
    ds, summary = ocpar.load(directory / "runs" / "robots-limited")
    unbounded = json.loads((directory / "runs" / "robots-cli" / "result.json").read_text())
    assert summary["total_cost"] > unbounded["total_cost"]      # the bound binds...
    accel = ds["control"].sel(u_component="acceleration").values
    assert np.abs(accel).max() == pytest.approx(1.0, abs=1e-8)  # ...at |a| = 1
    end = ds["configuration"].isel(time=-1)
    np.testing.assert_allclose(np.hypot(end.sel(q_component="x"), end.sel(q_component="y")),
                               3.0, atol=1e-9)
    np.testing.assert_allclose(end.sel(q_component="speed"), 0.0, atol=1e-9)


def test_a_changed_figure_is_caught():
    """The comparison is not vacuous: a number off in its 6th digit, a word changed or a line
    missing is reported; the wall time and a job id are not."""
    shown = ("cost 1.249977, train 1.299885\nwall time 0.51 s on 1 serial worker(s)\n"
             "pursuit-20261201-181940-bf1139  running")
    assert not tutorials.differences(shown, shown.replace("0.51", "7.25").replace(
        "20261201-181940-bf1139", "20270101-000000-0a0b0c"))
    assert tutorials.differences(shown, shown.replace("1.249977", "1.249978"))
    assert tutorials.differences(shown, shown.replace("train", "agent"))
    assert tutorials.differences(shown, shown.rsplit("\n", 1)[0])


@pytest.mark.slow
@pytest.mark.parametrize("name", tutorials.TUTORIALS)
def test_every_step_on_mpi_and_a_dask_cluster(name, tmp_path):
    """Every command of the page, steps 4–6 included: ``mpirun -n 2``, the set-up's Dask
    scheduler and two workers (on a free port), a detached job."""
    runs = tutorials.run_tutorial(name, tmp_path, cluster=True)
    assert any("--scheduler" in run.command.text for run in runs)
    problems = _problems(name, runs)
    assert not problems, "\n\n".join(problems)
