"""The front door: each scheme's ``--help`` opens with examples and the options a newcomer
needs, shows every default and keeps its scheme's words to itself; the examples' N and T are
options; ``--plot none`` skips the picture."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from ocpar.driver import build_parser, check_options, run_scheme
from ocpar.formation.run import FormationRun
from ocpar.formation.solve import FormationOptions, solve_formation
from ocpar.macs import MacsSettings, solve_macs
from ocpar.macs.run import MacsRun
from ocpar.options import option_specs, project
from ocpar.pursuit.run import PursuitRun

RUNS = {"formation": FormationRun, "pursuit": PursuitRun, "macs": MacsRun}
#: The lines of a terminal's first screen that must hold the examples and the essentials.
FIRST_SCREEN = 42
#: Words of one scheme that no other scheme's help may use.
OWN_WORDS = {"formation": ("formation", "DMOC"), "pursuit": ("pursuit", "PBMS", "shooting"),
             "macs": ("MACS", "Pareto", "DFET")}
CHECK_RESULT = Path("/work/shared/tools/check-result")


@pytest.fixture(scope="module")
def helps() -> dict[str, str]:
    """Each scheme's ``--help`` as an 80-column terminal shows it."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("COLUMNS", "80")
        return {name: build_parser(run).format_help() for name, run in RUNS.items()}


@pytest.mark.parametrize("scheme", RUNS)
def test_the_first_screen_holds_the_examples_and_the_essentials(scheme, helps):
    run = RUNS[scheme]
    first = "\n".join(helps[scheme].splitlines()[:FIRST_SCREEN])
    assert "examples:" in first and len(run.examples) >= 3
    for example in run.examples:   # each example in full, however it is wrapped
        assert " ".join(example.split()) in " ".join(first.split())
    specs = option_specs(run)
    flags = [specs[key].flag for key in run.essentials]
    assert {"--problem", "--problem-arg", "--output", "--plot", "--backend", "--workers",
            "-h, --help"} <= {*flags, "-h, --help"}
    for flag in [*flags, "-h, --help"]:
        assert re.search(rf"^  {re.escape(flag)}\b", first, re.M), flag
    # the essentials come before every other option
    others = [s.flag for s in specs.values() if s.key not in run.essentials]
    last_essential = max(helps[scheme].index(f"\n  {flag}") for flag in flags)
    assert all(helps[scheme].index(f"\n  {flag} ") > last_essential for flag in others)


@pytest.mark.parametrize("scheme", RUNS)
def test_every_example_is_a_valid_command_line(scheme):
    run = RUNS[scheme]
    for example in run.examples:
        words = shlex.split(example)
        options, _ = check_options(run, words[words.index(f"ocpar.{scheme}") + 1:])
        assert isinstance(options, run)


@pytest.mark.parametrize("scheme", RUNS)
def test_every_default_is_shown(scheme, helps):
    """Each option with a value by default shows it as ``(default VALUE)``, a table ``(default:
    none)``; an option unset by default says what unset means; flags are off unless given."""
    specs = {spec.key: spec for spec in option_specs(RUNS[scheme]).values()}
    shown = {action.dest: " ".join(action.help.split())
             for action in build_parser(RUNS[scheme])._actions if action.dest in specs}
    assert set(shown) == set(specs)
    for key, spec in specs.items():
        if spec.kind == "flag":
            continue
        text = shown[key]
        if spec.kind == "table":
            assert text.endswith("(default: none)"), spec.flag
        elif spec.default is None:
            assert "default" in text, spec.flag
        else:
            assert text.endswith(f"(default {spec.default})"), spec.flag
        # the rendered help holds it
        assert text[-20:] in " ".join(helps[scheme].split())


@pytest.mark.parametrize("scheme", RUNS)
def test_a_schemes_own_words_stay_in_its_help(scheme, helps):
    assert re.search(rf"\b{OWN_WORDS[scheme][0]}\b", helps[scheme], re.I)
    leaked = [word for other, words in OWN_WORDS.items() if other != scheme
              for word in words if re.search(rf"\b{word}\b", helps[scheme], re.I)]
    assert leaked == []


def test_max_evals_says_how_the_budget_is_counted(helps):
    text = " ".join(helps["macs"].split())
    assert "the last iteration begun ends past it" in text
    assert "final placement and refinement add theirs" in text


def test_the_examples_n_and_t_are_options():
    """--intervals N and --duration T reach the example's shape; its cost scales as T^-3 (the
    rest-to-rest DMOC of a point mass: u ~ T^-2 on a grid h = T/N, cost sum u^2 h), at equal
    final angles."""
    shape = FormationRun(problem="crtbp-rigid", agents=3, intervals=6,
                         duration=0.5).build_example().shape
    assert (shape.intervals, shape.duration) == (6, 0.5)
    solved = {}
    for duration, intervals in ((1.0, 10), (2.0, 10), (1.0, 20)):
        run = FormationRun(agents=6, duration=duration, intervals=intervals)
        solved[duration, intervals] = solve_formation(run.build_example(),
                                                      options=project(run, FormationOptions))
    base, slow, fine = solved[1.0, 10], solved[2.0, 10], solved[1.0, 20]
    assert {r.status for r in solved.values()} == {"converged"}
    assert slow.total_cost == pytest.approx(base.total_cost / 8, rel=1e-9)
    assert slow.phi == pytest.approx(base.phi, abs=1e-9)
    assert fine.total_cost < base.total_cost * (1 - 1e-3)   # a finer grid: a cheaper path
    with pytest.raises(ValueError, match="--intervals only applies to the built-in"):
        check_options(FormationRun, ["--problem", "mypkg.ships:make", "--intervals", "5"])


def test_macs_elements_reach_the_problem():
    """--elements N: the built-in problem's DFET elements; the double integrator's closed-form
    front is met on a coarse grid too (its optimal control is linear in t: exact on any)."""
    assert MacsRun(problem="orbit-raising").build_example().elements == 30
    assert MacsRun(problem="orbit-raising", elements=12).build_example().elements == 12
    run = MacsRun(problem="double-integrator", elements=2, max_evaluations=60, population=4,
                  archive_size=5)
    problem = run.build_example()
    result = solve_macs(problem, project(run, MacsSettings))
    assert problem.elements == 2 and result.status == "converged" and result.gd < 1e-5
    with pytest.raises(ValueError, match="--elements only applies to the built-in"):
        check_options(MacsRun, ["--problem", "mypkg.rocket:make", "--elements", "5"])


def test_plot_none_writes_no_picture(tmp_path):
    """--plot none in every scheme: result.json, the array file and the trace, no PNG (one
    left by an earlier run of the same problem removed), no picture time; the summary keeps
    its contract."""
    formation = tmp_path / "formation"
    run = FormationRun(agents=4, radius=3.0, quiet=True, output=str(formation))
    assert run_scheme(run) == 0 and (formation / "formation.png").is_file()
    runs = [
        FormationRun(agents=4, radius=3.0, quiet=True, output=str(formation), picture="none"),
        PursuitRun(samples=21, window=11, update=5, max_agents=3, certify_samples=0,
                   no_reference=True, quiet=True, output=str(tmp_path / "pursuit"),
                   picture="none"),
        MacsRun(problem="double-integrator", max_evaluations=60, population=4,
                archive_size=5, quiet=True, output=str(tmp_path / "macs"), picture="none"),
    ]
    for run in runs:
        run_scheme(run)
        out = Path(run.output)
        assert sorted(p.name for p in out.iterdir()) == ["result.json", "result.nc",
                                                         "trace.json"]
        summary = json.loads((out / "result.json").read_text())
        assert summary["scheme"] == run.scheme and "picture_s" not in summary["timings"]
        if CHECK_RESULT.exists():
            check = subprocess.run([sys.executable, str(CHECK_RESULT), str(out)],
                                   capture_output=True, text=True)
            assert check.returncode == 0, check.stdout
    assert check_options(MacsRun, ["--plot", "none"])[0].picture == "none"
    with pytest.raises(ValueError, match="invalid choice 'jpg'"):
        check_options(MacsRun, ["--plot", "jpg"])
