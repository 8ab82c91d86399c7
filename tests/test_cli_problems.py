"""Problems by reference: flags after a configuration override its keys; bad references and bad
factories get one line and exit status 2 before anything starts. (A user's package running for
every scheme on every backend is test_matrix.py.)"""

from __future__ import annotations

import importlib.util
import json
import shlex
import sys
from pathlib import Path

import pytest
from conftest import run_ocpar
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_matrix import CONFIGS

from ocpar import driver
from ocpar.__main__ import main as ocpar_main
from ocpar.config import scheme_class
from ocpar.references import REFERENCE


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The runs' working directory, with the configuration my.toml (and no mypkg)."""
    work = tmp_path_factory.mktemp("work")
    (work / "my.toml").write_text(CONFIGS["formation-user"])
    return work


# --- flags after CONFIG ----------------------------------------------------------------------

def test_flags_after_the_configuration_override_its_keys(workdir, capsys, monkeypatch):
    """Scheme options after CONFIG replace the file's keys (--problem-arg its whole table)."""
    monkeypatch.chdir(workdir)
    assert ocpar_main(["run", "my.toml", "--output", "elsewhere", "--problem-arg", "agents=4",
                       "--problem-arg", 'tag="a b"', "--print-argv"]) == 0
    words = shlex.split(capsys.readouterr().out)
    assert words == ["python", "-m", "ocpar.formation", "--problem",
                     "mypkg.problems:make_formation", "--quiet", "--output", "elsewhere",
                     "--problem-arg", "agents=4", "--problem-arg", 'tag="a b"']


# --- bad references and factories: one line, exit 2, nothing started -------------------------

@pytest.fixture
def guarded(monkeypatch, user_package):
    """mypkg importable in this process; building a built-in example, starting a backend or
    solving fails the test."""
    monkeypatch.syspath_prepend(str(user_package))
    for name in ("build_example", "run_on_backend"):
        monkeypatch.setattr(driver, name, _guard(name))
    for module in [m for m in sys.modules if m == "mypkg" or m.startswith("mypkg.")]:
        monkeypatch.delitem(sys.modules, module)


def _guard(name: str):
    def called(*args, **kwargs):
        raise AssertionError(f"{name} called: the input passed validation")
    return called


def refused(argv: list[str], capsys, prog: str = "ocpar.formation") -> str:
    """``ocpar argv``: exit 2, nothing on stdout, one line ``PROG: error: ...``."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        ocpar_main(argv)
    out, err = capsys.readouterr()
    assert exc.value.code == 2, err
    assert out == "" and "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


def config(tmp_path: Path, scheme: str, problem: str, args: str = "") -> str:
    path = tmp_path / "bad.toml"
    body = f'scheme = "{scheme}"\nproblem = {json.dumps(problem)}\n'
    path.write_text(body + (f"\n[problem_args]\n{args}\n" if args else ""))
    return str(path)


@pytest.mark.parametrize(("scheme", "problem", "args", "needle"), [
    ("formation", "mypkg.nothere:make", "", "no module named 'mypkg.nothere'"),
    ("formation", "nopkg_ocpar_test.problems:make", "", "no module named 'nopkg_ocpar_test'"),
    ("formation", "mypkg.broken:make", "",
     "importing mypkg.broken raised ImportError: needs a library that is not installed"),
    ("formation", "mypkg.problems:missing", "", "module mypkg.problems has no attribute "
                                                "'missing'"),
    ("formation", "mypkg.problems:NOT_CALLABLE", "", "NOT_CALLABLE is an object of type int, "
                                                     "not a function"),
    ("formation", "mypkg.problems:raises", "", "raises() raised RuntimeError: boom"),
    ("formation", "mypkg.problems:make_formation", 'colour = "red"',
     "make_formation(colour='red') raised TypeError"),
    ("formation", "mypkg.problems:make_formation", "agents = 1",
     "make_formation(agents=1) raised ValueError: starts: a formation needs at least 2 agents"),
    ("formation", "mypkg.problems:wrong_type", "", "wrong_type() returned an object of type "
                                                   "dict, not FormationProblem"),
    ("pursuit", "mypkg.problems:make_formation", "", "make_formation() returned an object of "
                                                     "type FormationProblem, not PursuitProblem"),
    ("macs", "mypkg.problems:make_formation", "", "make_formation() returned an object of "
                                                  "type FormationProblem, not MacsProblem"),
    ("formation", "mypkg.problems:make_macs", "", "make_macs() returned an object of type "
                                                  "MacsProblem, not FormationProblem"),
    ("formation", "mypkg.problems:", "", "expected a built-in name or package.module:factory"),
    ("formation", ":make", "", "expected a built-in name or package.module:factory"),
    ("formation", "mypkg..problems:make", "", "expected a built-in name or package.module"),
    ("formation", "mypkg.problems:make:x", "", "expected a built-in name or package.module"),
    ("formation", "point-mass-plane", "agents = 3", "--problem-arg only applies to --problem "
                                                    "package.module:factory"),
])
def test_bad_references_and_factories_are_refused(scheme, problem, args, needle, tmp_path,
                                                  guarded, capsys):
    line = refused(["run", config(tmp_path, scheme, problem, args)], capsys, f"ocpar.{scheme}")
    assert needle in line, line
    if ":" in problem and REFERENCE.match(problem):
        assert repr(problem) in line  # the message names the reference


def test_built_in_options_are_refused_with_a_reference(guarded, capsys):
    line = refused(["run", "formation-60", "--problem", "mypkg.problems:make_formation"], capsys)
    assert "--agents only applies to the built-in examples" in line


def test_a_bad_reference_from_a_separate_process(user_package, workdir, tmp_path):
    path = config(tmp_path, "formation", "mypkg.problems:raises")
    proc = run_ocpar(user_package, workdir, "run", path, "--output", str(tmp_path / "out"))
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert proc.stderr.splitlines() == [
        "ocpar.formation: error: problem 'mypkg.problems:raises': raises() raised "
        "RuntimeError: boom"]
    assert not (tmp_path / "out" / "result.json").exists()


NAME = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True)
JUNK = st.text(alphabet=st.sampled_from(list(":._-/ \t\n\\'\"é0aZ")), max_size=20)


@st.composite
def references(draw) -> str:
    """Strings near the form package.module:factory, and junk."""
    dotted = st.lists(NAME, min_size=1, max_size=3).map(".".join)
    shaped = st.builds(lambda m, f, sep: f"{m}{sep}{f}", dotted, dotted,
                       st.sampled_from([":", "::", ".", ":.", " : ", ""]))
    return draw(st.one_of(shaped, JUNK, st.text(max_size=30),
                          st.builds(str.__add__, shaped, JUNK)))


@pytest.mark.parametrize("scheme", ["formation", "pursuit", "macs"])
@settings(max_examples=100, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=references())
def test_fuzzed_references_are_refused(scheme, text, guarded, capsys):
    module = importlib.import_module(f"ocpar.{scheme}.run")
    assume(text not in vars(module).get("EXAMPLES", {}) and text != "orbit-transfer"
           and text not in ("goddard", "orbit-raising", "double-integrator"))
    if REFERENCE.match(text):  # well formed: must name no importable module
        assume(importlib.util.find_spec(text.split(".")[0].split(":")[0]) is None)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        driver.main(scheme_class(scheme), ["--problem", text])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "" and "Traceback" not in err, (text, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ocpar.{scheme}: error: "), (text, err)
