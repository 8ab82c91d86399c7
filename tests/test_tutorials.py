"""The tutorials run as the pages show them (issue 41): through ``scripts/tutorials.py``, every
file of docs/tutorials/{formation,pursuit,macs}.md written into a fresh directory and every
command run there in one shell; each command ends with status 0 and prints what the page
shows (numbers to 1e-9 relative; wall times, memory, dates and job ids aside), and the figures
the prose quotes of runs it shows no output of are those runs'. Steps 4–6 (``mpirun``, a Dask
cluster and detached jobs) run in the slow test."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from conftest import script_module

import ocpar

tutorials = script_module("tutorials")


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
    """A tutorial's name, its directory and its commands as run (steps 1–3, 7, 8)."""
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
    assert {run.command.section[:2] for run in runs} >= {"2.", "3.", "7.", "8."}
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
    else:
        (extra,) = _quoted(name, r"from its own point and from its neighbours' on the front, "
                                 r"(\d+) more evaluations")
        summary = json.loads((directory / "runs" / "cart" / "result.json").read_text())
        assert summary["evaluations"] - summary["history"][-1]["evaluations"] == extra
        ds, _ = ocpar.load(directory / "runs" / "cart-cli")
        np.testing.assert_array_equal(ds["front"].values, np.array(summary["front"]))


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
