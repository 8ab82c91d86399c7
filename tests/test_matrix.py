"""The scheme × backend matrix: small instances of every scheme, a built-in example and a
problem from a user's package that is not part of ocpar (``mypkg``, written to a temporary
directory by conftest), each run by ``ocpar run my.toml`` serially, under ``mpirun -n 2`` and on
a real two-worker Dask cluster, with identical results (every computed field of result.json);
the user's problems also as ``ocpar submit`` jobs. The built-in rows are slow: their backends are
also compared in the default run by test_backends, test_pursuit and test_macs."""

from __future__ import annotations

import importlib
import json
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import (
    assert_result_contract,
    computed,
    local_cluster,
    read_result,
    run_ocpar,
    user_environment,
)

#: Each case's configuration (its ``output`` is overridden by ``--output`` after the file).
CONFIGS = {
    "formation-user": """\
scheme = "formation"
problem = "mypkg.problems:make_formation"
output = "ignored"
quiet = true

[problem_args]
agents = 3
radius = 2.0
""",
    "pursuit-user": """\
scheme = "pursuit"
problem = "mypkg.problems:make_pursuit"
window = 11
update = 5
epsilon = 1e-4
quiet = true

[problem_args]
samples = 21
duration = 4.0
""",
    "macs-user": """\
scheme = "macs"
problem = "mypkg.problems:make_macs"
max_evals = 300
seed = 1
quiet = true

[problem_args]
distance = 1.0
""",
    "formation-builtin": """\
scheme = "formation"
agents = 6
quiet = true
""",
    "pursuit-builtin": """\
scheme = "pursuit"
samples = 61
window = 20
update = 10
epsilon = 0.1
no_reference = true
quiet = true
""",
    "macs-builtin": """\
scheme = "macs"
problem = "goddard"
max_evals = 150
archive = 10
seed = 7
quiet = true
""",
}
USER = [case for case in CONFIGS if case.endswith("-user")]
#: The shared check-result knows the paper examples' fields only: every pursuit run's final mass,
#: MACS's GD and IGD as numbers; these problems have no mass and no reference front.
NO_CONTRACT = {"pursuit-user", "macs-user"}
CASES = [pytest.param(case, marks=[] if case in USER else [pytest.mark.slow])
         for case in CONFIGS]
#: On MPI and Dask: the user's formation in the default run, every other case slow (each
#: scheme's own tests run its examples on every backend).
PARALLEL = [pytest.param(case, marks=[] if case == "formation-user" else [pytest.mark.slow])
            for case in CONFIGS]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """The runs' working directory, with one CASE.toml per case (and no mypkg)."""
    work = tmp_path_factory.mktemp("work")
    for case, text in CONFIGS.items():
        (work / f"{case}.toml").write_text(text)
    return work


def run(site: Path, work: Path, case: str, backend: str, *args: str, **kwargs) -> dict:
    """``ocpar run CASE.toml --output WORK/CASE-BACKEND ARGS``: its result.json."""
    out = work / f"{case}-{backend}"
    proc = run_ocpar(site, work, "run", f"{case}.toml", "--output", str(out), *args, **kwargs)
    assert proc.returncode == 0, proc.stderr
    return read_result(out)


@pytest.fixture(scope="module")
def serial(user_package, workdir):
    """Each case's serial result.json, run once on first use."""
    results: dict[str, dict] = {}

    def result(case: str) -> dict:
        if case not in results:
            results[case] = run(user_package, workdir, case, "serial")
            if case not in NO_CONTRACT:
                assert_result_contract(workdir / f"{case}-serial")
        return results[case]

    return result


@pytest.fixture(scope="module")
def cluster(user_package, tmp_path_factory):
    """One two-worker cluster for every case, whose scheduler and workers import mypkg, keeping
    its jobs in a temporary directory."""
    jobs_dir = tmp_path_factory.mktemp("jobs")
    pythonpath = user_environment(user_package)["PYTHONPATH"]
    with local_cluster({"OCPAR_JOBS_DIR": str(jobs_dir), "PYTHONPATH": pythonpath}) as address:
        yield address


@pytest.mark.parametrize("case", CASES)
def test_serial_run(case, serial, workdir):
    result = serial(case)
    assert result["scheme"] == case.split("-")[0] and result["backend"] == "serial"
    assert result["status"] == "converged" and result["failed_solves"] == 0
    assert not (workdir / "ignored").exists()  # --output after CONFIG overrode its output
    # where the time went: every phase, disjoint parts of the process's life
    timings = result["timings"]
    phases = ["startup_s", "build_s", "solve_s", "verification_s", "files_s", "picture_s"]
    assert [key for key in timings if key in phases] == phases and "total_s" in timings
    assert timings["solve_s"] == result["wall_time_s"]
    assert all(value >= 0 for value in timings.values())
    assert sum(timings[key] for key in phases) <= timings["total_s"] + 1e-6


@pytest.mark.parametrize("case", PARALLEL)
def test_mpirun_gives_the_serial_result(case, serial, user_package, workdir):
    result = run(user_package, workdir, case, "mpi", mpi_ranks=2)
    assert result["backend"] == "mpi" and result["workers"] == 2
    assert computed(result) == computed(serial(case))


@pytest.mark.parametrize("case", PARALLEL)
def test_dask_gives_the_serial_result(case, serial, user_package, workdir, cluster):
    result = run(user_package, workdir, case, "dask", "--scheduler", cluster)
    assert result["backend"] == "dask" and result["workers"] == 2
    assert computed(result) == computed(serial(case))


#: Submitted through the Dask-client path: the formation in the default run, the others slow
#: (the HTTP service's own tests submit every scheme).
SUBMITTED = [case for case in PARALLEL if case.values[0] in USER]


@pytest.mark.parametrize("case", SUBMITTED)
def test_submit_gives_the_serial_result(case, serial, user_package, workdir, cluster):
    """The same configuration as a detached job: the reference travels with it."""
    site = user_package
    proc = run_ocpar(site, workdir, "submit", f"{case}.toml", "--scheduler", cluster)
    assert proc.returncode == 0, proc.stderr
    job = proc.stdout.strip()
    deadline = time.monotonic() + 180
    while True:
        proc = run_ocpar(site, workdir, "status", job, "--scheduler", cluster, "--json")
        assert proc.returncode == 0, proc.stderr
        state = json.loads(proc.stdout)
        if state["state"] in ("finished", "failed", "cancelled"):
            break
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    assert state["state"] == "finished", state
    fetched = workdir / f"{case}-fetched"
    proc = run_ocpar(site, workdir, "result", job, "--scheduler", cluster, "--output",
                     str(fetched))
    assert proc.returncode == 0, proc.stderr
    assert computed(read_result(fetched)) == computed(serial(case))


# --- the user's problems solved: against the Python API and closed forms ----------------------

def test_user_formation_is_the_factorys_problem(serial, user_package, monkeypatch):
    """The command line's result is the Python API's solve of ``make_formation(3, 2.0)`` (so
    the reference and its [problem_args] reached the factory)."""
    monkeypatch.syspath_prepend(str(user_package))
    from ocpar.formation import solve_formation

    factory = importlib.import_module("mypkg.problems").make_formation
    expected = solve_formation(factory(3, 2.0))
    result = serial("formation-user")
    assert result["problem"] == "line-3" and result["agents"] == 3
    assert result["total_cost"] == expected.total_cost
    assert result["phi"] == [float(p) for p in expected.phi]


def test_python_api_gives_the_serial_result(serial, user_package, tmp_path, monkeypatch):
    """The options dataclass is the Python face of the same command line."""
    from ocpar.driver import run_scheme
    from ocpar.formation.run import FormationRun

    monkeypatch.syspath_prepend(str(user_package))
    options = FormationRun(problem="mypkg.problems:make_formation",
                           problem_args={"agents": 3, "radius": 2.0}, output=str(tmp_path),
                           quiet=True)
    assert run_scheme(options) == 0
    assert computed(read_result(tmp_path)) == computed(serial("formation-user"))


def test_user_pursuit_approaches_the_least_energy(serial):
    """Rest to rest over d = 1 in T = 4 with ∫u² dt: the continuous optimum is 12 d²/T³ =
    0.1875 (u linear in t); the discrete problems (u held on each of 20 steps, exact steps and
    costs) can only spend more, the full-horizon MS least, PBMS within 0.1% of it."""
    result = serial("pursuit-user")
    assert result["problem"] == "braking" and result["headline"] == "cost"
    ms, pbms = result["reference_ms_cost"], result["cost"]
    assert 0.1875 < ms <= pbms < 1.001 * ms and ms < 1.003 * 0.1875


def test_user_macs_front_is_on_the_closed_form(serial):
    """The least energy for a given t_f is 12 d²/t_f³ (u linear in t, which DFET with linear
    controls represents exactly): no archive member lies below that front, after 300
    evaluations every one is within 5% of it and most are on it; t_f's range is covered."""
    result = serial("macs-user")
    front = np.array(result["front"])
    assert result["objectives"] == ["t_f", "energy"] and len(front) >= 10
    excess = front[:, 1] * front[:, 0] ** 3 / 12 - 1
    assert excess.min() > -1e-7 and excess.max() < 0.05
    assert np.median(excess) < 1e-3
    assert front[:, 0].min() < 1.1 * 1.02 * np.sqrt(6) and front[:, 0].max() > 4.5


def test_a_module_missing_on_the_workers_is_one_line(user_package, tmp_path, cluster):
    """The user's module importable here but not on the cluster's workers: ``ocpar run
    --scheduler`` ends with one line naming the module (exit 2) as soon as the first
    superstep's chunks reach the workers, not a traceback after the lost-worker wait."""
    import shutil
    import subprocess
    import sys

    from conftest import USER_PROBLEMS_PY

    site = tmp_path / "here-only"
    (site / "herepkg").mkdir(parents=True)
    (site / "herepkg" / "__init__.py").write_text("")
    (site / "herepkg" / "problems.py").write_text(USER_PROBLEMS_PY)
    env = user_environment(user_package)
    env["PYTHONPATH"] = f"{site}:{env['PYTHONPATH']}"
    started = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "ocpar.pursuit", "--problem", "herepkg.problems:make_pursuit",
         "--window", "8", "--update", "4",
         "--scheduler", cluster, "--quiet", "--output", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith("ocpar.pursuit: error: a worker on ")
    assert "cannot import module 'herepkg', which the run's tasks need" in proc.stderr
    assert time.monotonic() - started < 60
    shutil.rmtree(site)
