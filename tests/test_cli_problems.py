"""Problems by reference: a formation problem defined in a package that is not part of ocpar
(written to a temporary directory here) runs through ``ocpar run my.toml`` serially, under
``mpirun -n 2``, on a real two-worker Dask cluster and as an ``ocpar submit`` job, with the
same result; bad references and bad factories get one line and exit status 2 before anything
starts."""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import assert_result_contract, local_cluster, tool
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from ocpar import driver
from ocpar.__main__ import main as ocpar_main
from ocpar.references import REFERENCE

PROBLEMS_PY = '''
"""A user's formation problems, built with ocpar's public API only."""
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.models import PointMass

NOT_CALLABLE = 3


def make(agents: int = 3, radius: float = 2.0) -> FormationProblem:
    """``agents`` point masses on a bent line below the origin, onto a circle of ``radius``."""
    x = np.linspace(-1.0, 1.0, agents)
    starts = np.column_stack([x, -3.0 + 0.2 * x**2])
    return FormationProblem(name=f"line-{agents}", starts=starts,
                            shape=DmocShape(PointMass(dim=2, mass=1.0), 10, 1.0),
                            curve=Circle(radius=radius, center=np.zeros(2)))


def raises():
    raise RuntimeError("boom")


def wrong_type():
    return {"agents": 3}
'''
BROKEN_PY = 'raise ImportError("needs a library that is not installed")\n'
CONFIG = """\
scheme = "formation"
problem = "mypkg.problems:make"
output = "ignored"      # every run below sets --output after the file
quiet = true

[problem_args]
agents = 3
radius = 2.0
"""
#: Fields of result.json that say where and how long a run ran, not what it computed.
RUNTIME = {"backend", "workers", "wall_time_s", "trace"}


@pytest.fixture(scope="module")
def user_package(tmp_path_factory) -> Path:
    """The directory holding the package ``mypkg`` (to put on PYTHONPATH)."""
    site = tmp_path_factory.mktemp("site")
    (site / "mypkg").mkdir()
    (site / "mypkg" / "__init__.py").write_text('"""Not part of ocpar."""\n')
    (site / "mypkg" / "problems.py").write_text(PROBLEMS_PY)
    (site / "mypkg" / "broken.py").write_text(BROKEN_PY)
    return site


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The runs' working directory, with the configuration my.toml (and no mypkg)."""
    work = tmp_path_factory.mktemp("work")
    (work / "my.toml").write_text(CONFIG)
    return work


def environment(site: Path) -> dict[str, str]:
    paths = [str(site), *filter(None, [os.environ.get("PYTHONPATH")])]
    return dict(os.environ, PYTHONPATH=os.pathsep.join(paths), OMP_NUM_THREADS="1")


def ocpar(site: Path, cwd: Path, *args: str, mpi_ranks: int | None = None,
          timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "ocpar", *args]
    if mpi_ranks is not None:
        cmd = [tool("mpirun"), "-n", str(mpi_ranks), *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env=environment(site))


def computed(result: dict) -> dict:
    return {key: value for key, value in result.items() if key not in RUNTIME}


@pytest.fixture(scope="module")
def serial_result(user_package, workdir) -> dict:
    out = workdir / "serial"
    proc = ocpar(user_package, workdir, "run", "my.toml", "--output", str(out))
    assert proc.returncode == 0, proc.stderr
    assert_result_contract(out)
    assert not (workdir / "ignored").exists()  # --output after CONFIG overrode its output
    return json.loads((out / "result.json").read_text())


def test_serial_run_is_the_factorys_problem(serial_result, user_package, monkeypatch):
    """The command line's result is the Python API's solve of ``make(agents=3, radius=2.0)``
    (so the reference and its [problem_args] reached the factory)."""
    monkeypatch.syspath_prepend(str(user_package))
    from ocpar.formation import solve_formation

    expected = solve_formation(importlib.import_module("mypkg.problems").make(3, 2.0))
    assert serial_result["status"] == "converged" and serial_result["problem"] == "line-3"
    assert serial_result["total_cost"] == expected.total_cost
    assert serial_result["phi"] == [float(p) for p in expected.phi]
    assert serial_result["agents"] == 3 and serial_result["backend"] == "serial"


def test_python_api_gives_the_serial_result(serial_result, user_package, tmp_path,
                                            monkeypatch, capsys):
    """The options dataclass is the Python face of the same command line."""
    from ocpar.driver import run_scheme
    from ocpar.formation.run import FormationRun

    monkeypatch.syspath_prepend(str(user_package))
    options = FormationRun(problem="mypkg.problems:make", problem_args={"agents": 3,
                           "radius": 2.0}, output=str(tmp_path), quiet=True)
    assert run_scheme(options) == 0
    result = json.loads((tmp_path / "result.json").read_text())
    assert computed(result) == computed(serial_result)


def test_mpirun_gives_the_serial_result(serial_result, user_package, workdir):
    out = workdir / "mpi"
    proc = ocpar(user_package, workdir, "run", "my.toml", "--output", str(out), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["backend"] == "mpi" and result["workers"] == 2
    assert computed(result) == computed(serial_result)


@pytest.fixture(scope="module")
def cluster(user_package, tmp_path_factory):
    """A two-worker cluster whose scheduler and workers import mypkg, keeping its jobs in a
    temporary directory."""
    jobs_dir = tmp_path_factory.mktemp("jobs")
    env = environment(user_package)
    with local_cluster({"OCPAR_JOBS_DIR": str(jobs_dir), "PYTHONPATH": env["PYTHONPATH"]}) \
            as address:
        yield address


def test_dask_and_submit_give_the_serial_result(serial_result, user_package, workdir, cluster):
    out = workdir / "dask"
    proc = ocpar(user_package, workdir, "run", "my.toml", "--output", str(out),
                 "--scheduler", cluster)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["backend"] == "dask" and result["workers"] == 2
    assert computed(result) == computed(serial_result)

    # the same configuration as a detached job: the reference travels with it; a scheme
    # option after CONFIG overrides it, as for ocpar run
    proc = ocpar(user_package, workdir, "submit", "my.toml", "--scheduler", cluster,
                 "--problem-arg", "agents=3", "--problem-arg", "radius=2.0")
    assert proc.returncode == 0, proc.stderr
    job = proc.stdout.strip()
    deadline = time.monotonic() + 180
    while True:
        proc = ocpar(user_package, workdir, "status", job, "--scheduler", cluster, "--json")
        assert proc.returncode == 0, proc.stderr
        state = json.loads(proc.stdout)
        if state["state"] in ("finished", "failed", "cancelled"):
            break
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    assert state["state"] == "finished", state
    fetched = workdir / "fetched"
    proc = ocpar(user_package, workdir, "result", job, "--scheduler", cluster, "--output",
                 str(fetched))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((fetched / "result.json").read_text())
    assert computed(result) == computed(serial_result)


# --- flags after CONFIG ----------------------------------------------------------------------

def test_flags_after_the_configuration_override_its_keys(workdir, capsys, monkeypatch):
    """Scheme options after CONFIG replace the file's keys (--problem-arg its whole table)."""
    monkeypatch.chdir(workdir)
    assert ocpar_main(["run", "my.toml", "--output", "elsewhere", "--problem-arg", "agents=4",
                       "--problem-arg", 'tag="a b"', "--print-argv"]) == 0
    words = shlex.split(capsys.readouterr().out)
    assert words == ["python", "-m", "ocpar.formation", "--problem", "mypkg.problems:make",
                     "--quiet", "--output", "elsewhere", "--problem-arg", "agents=4",
                     "--problem-arg", 'tag="a b"']


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
    ("formation", "mypkg.problems:make", 'colour = "red"',
     "make(colour='red') raised TypeError"),
    ("formation", "mypkg.problems:make", "agents = 1",
     "make(agents=1) raised ValueError: starts: a formation needs at least 2 agents"),
    ("formation", "mypkg.problems:wrong_type", "", "wrong_type() returned an object of type "
                                                   "dict, not FormationProblem"),
    ("pursuit", "mypkg.problems:make", "", "make() returned an object of type "
                                           "FormationProblem, not PursuitProblem"),
    ("macs", "mypkg.problems:make", "", "make() returned an object of type FormationProblem, "
                                        "not MacsProblem"),
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
    line = refused(["run", "formation-60", "--problem", "mypkg.problems:make"], capsys)
    assert "--agents only applies to the built-in examples" in line


def test_a_bad_reference_from_a_separate_process(user_package, workdir, tmp_path):
    path = config(tmp_path, "formation", "mypkg.problems:raises")
    proc = ocpar(user_package, workdir, "run", path, "--output", str(tmp_path / "out"))
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
           and text not in ("goddard", "orbit-raising"))
    if REFERENCE.match(text):  # well formed: must name no importable module
        assume(importlib.util.find_spec(text.split(".")[0].split(":")[0]) is None)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        importlib.import_module(f"ocpar.{scheme}.__main__").main(["--problem", text])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "" and "Traceback" not in err, (text, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ocpar.{scheme}: error: "), (text, err)
