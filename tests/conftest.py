"""Shared fixtures: paths of the tools the tests launch, a user's package of problems for
every scheme, and small problems."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import re
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ocpar.result_files import RUNTIME_FIELDS

#: The suite runs its inner functions on CasADi's virtual machine (the same bits): its many
#: small shapes would otherwise compile tens of libraries into an empty cache, ~70 s of gcc
#: on a fresh machine. tests/test_compiled.py and the Riccati test compile on purpose.
os.environ["OCPAR_COMPILE"] = "0"

BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]


def tool(name: str) -> str:
    """A console script installed beside this Python (mpirun, dask)."""
    path = BIN / name
    if not path.exists():
        pytest.fail(f"{name} not found beside {sys.executable}; install the package first")
    return str(path)


def run_cli(
    *args: str, mpi_ranks: int | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """Run ``python -m ...`` (optionally under ``mpirun -n``) and capture its output."""
    cmd = [sys.executable, *args]
    if mpi_ranks is not None:
        cmd = [tool("mpirun"), "-n", str(mpi_ranks), *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=REPO)


def assert_result_contract(directory: Path) -> None:
    """Run the shared ``check-result`` tool on a run's output, where the checkout has it
    beside it (as CI does)."""
    checker = REPO.parent / "shared" / "tools" / "check-result"
    if checker.exists():
        check = subprocess.run([sys.executable, str(checker), str(directory)],
                               capture_output=True, text=True)
        assert check.returncode == 0, check.stdout


def assert_no_sentinel(summary: str) -> None:
    """No figure line of ``summary`` (its status line quotes the message) prints a sentinel:
    no -1, nan or inf standing for a number the run has not got."""
    for line in summary.splitlines()[1:]:
        assert not re.search(r"(?<![\w.])(-1|nan|inf)(?![\w.])", line), line


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def local_cluster(extra_env: dict[str, str] | None = None) -> Iterator[str]:
    """A real ``dask scheduler`` and two single-threaded ``dask worker`` processes started by
    ``workers/start-dask-worker.sh`` on 127.0.0.1 (``extra_env`` added to their environment);
    yields the scheduler address."""
    from distributed import Client

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, OMP_NUM_THREADS="1", **(extra_env or {}))
    dask = tool("dask")
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        wait_for_port(port, procs[0], 60, "dask scheduler did not start")
        # the workers start exactly as on a cluster node (and in docker/compose.yaml)
        env["PATH"] = f"{Path(dask).parent}{os.pathsep}{env.get('PATH', '')}"
        procs.append(subprocess.Popen([str(REPO / "workers" / "start-dask-worker.sh"), address,
                                       "2"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        stop_processes(procs)


def wait_for_port(port: int, proc: subprocess.Popen, timeout_s: float,
                  message: str | Callable[[], str]) -> None:
    """Wait until 127.0.0.1:``port`` accepts connections; fail the test with ``message`` (or
    what it returns) if ``proc`` ends or ``timeout_s`` passes first."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return
        except OSError:
            if time.monotonic() > deadline or proc.poll() is not None:
                pytest.fail(message() if callable(message) else message)
            time.sleep(0.2)


def stop_processes(procs: list[subprocess.Popen]) -> None:
    """Terminate ``procs`` (last started first) and wait for them, killing any that hang."""
    for proc in reversed(procs):
        proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()


@dataclass(frozen=True)
class Golden:
    """One figure of tests/golden/paper_examples.toml: ``value`` with its tolerance ``rel`` /
    ``abs``, or a bound ``at_most``; ``source`` where it comes from."""

    source: str
    value: float | None = None
    rel: float | None = None
    abs: float | None = None
    at_most: float | None = None
    paper: float | None = None

    def approx(self):
        """``pytest.approx`` of the value within the file's tolerance."""
        return pytest.approx(self.value, rel=self.rel, abs=self.abs)


def golden(key: str) -> Golden:
    """The figure ``EXAMPLE.FIGURE`` (e.g. ``formation-60.total_cost``) of the golden file."""
    example, figure = key.split(".")
    with open(REPO / "tests" / "golden" / "paper_examples.toml", "rb") as f:
        return Golden(**tomllib.load(f)[example][figure])


@pytest.fixture(scope="session")
def dask_cluster():
    """:func:`local_cluster` for the whole session."""
    with local_cluster() as address:
        yield address


# --- a user's package: problems for every scheme, not part of ocpar ----------------------------

USER_PROBLEMS_PY = '''
"""A user's problems for every scheme, built with ocpar's public API only."""
import os
import signal
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.macs import MacsProblem, Objective
from ocpar.models import PointMass
from ocpar.pursuit import PursuitProblem, SampledPlan

NOT_CALLABLE = 3


@dataclass(frozen=True)
class DoubleIntegrator:
    """ẋ = v, v̇ = u with |u| ≤ 1 and running cost u²."""

    nx: int = 2
    nu: int = 1

    def rhs(self, x, u):
        return ca.vertcat(x[1], u[0])

    def running_cost(self, x, u):
        return u[0] ** 2

    def state_bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)

    def control_bounds(self):
        return np.array([-1.0]), np.array([1.0])


def make_formation(agents: int = 3, radius: float = 2.0) -> FormationProblem:
    """``agents`` point masses on a bent line below the origin, onto a circle of ``radius``."""
    x = np.linspace(-1.0, 1.0, agents)
    starts = np.column_stack([x, -3.0 + 0.2 * x**2])
    return FormationProblem(name=f"line-{agents}", starts=starts,
                            shape=DmocShape(PointMass(dim=2, mass=1.0), 10, 1.0),
                            curve=Circle(radius=radius, center=np.zeros(2)))


def make_pursuit(samples: int = 21, duration: float = 4.0) -> PursuitProblem:
    """The double integrator from (1, 0) to rest at 0, min ∫u²; agent 0 brakes bang-bang
    (sampled exactly: the controls are held on each step)."""
    steps, h = samples - 1, duration / (samples - 1)
    a = 1.0 / (steps // 2 * h) ** 2
    u = np.where(np.arange(steps) < steps // 2, -a, a)
    x = [np.array([1.0, 0.0])]
    for uj in u:
        p, v = x[-1]
        x.append(np.array([p + v * h + uj * h**2 / 2, v + uj * h]))
    return PursuitProblem(name="braking", model=DoubleIntegrator(), duration=duration,
                          samples=samples, initial_state=np.array([1.0, 0.0]),
                          target_components=(0, 1), target=np.zeros(2),
                          plan=SampledPlan(np.array(x), u[:, None]), integrator="rk4")


def make_macs(distance: float = 1.0) -> MacsProblem:
    """Minimum time against minimum energy, the double integrator rest to rest over
    ``distance`` (front J2 = 12 d² / J1³)."""
    t_min = 1.02 * np.sqrt(6 * distance)
    return MacsProblem(
        name="rest-to-rest", model=DoubleIntegrator(),
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=lambda x, u: u[0] ** 2, name="energy")),
        initial_state=(0.0, 0.0), final_time=(t_min, 5.0),
        control_bounds=((-1.0, 1.0),), final_state={0: distance, 1: 0.0},
        elements=4, order=3, control_order=1)


def raises():
    raise RuntimeError("boom")


def crash_in_job(how: str = "exit") -> FormationProblem:
    """make_formation(), but a job's process (working directory: a job's directory of ocpar
    serve) dies loading it: ``how`` exit (os._exit(3)) or segfault (SIGSEGV)."""
    if Path.cwd().parent.name == "jobs":
        print("crash_in_job: " + how, flush=True)
        if how == "segfault":
            os.kill(os.getpid(), signal.SIGSEGV)
        os._exit(3)
    return make_formation()


def wrong_type():
    return {"agents": 3}
'''
USER_BROKEN_PY = 'raise ImportError("needs a library that is not installed")\n'
#: Fields of result.json that say where and how long a run ran, not what it computed.
RUNTIME = RUNTIME_FIELDS


@pytest.fixture(scope="session")
def user_package(tmp_path_factory) -> Path:
    """The directory holding the package ``mypkg`` (to put on PYTHONPATH): problems for every
    scheme in ``mypkg.problems`` (``make_formation``, ``make_pursuit``, ``make_macs``)."""
    site = tmp_path_factory.mktemp("site")
    (site / "mypkg").mkdir()
    (site / "mypkg" / "__init__.py").write_text('"""Not part of ocpar."""\n')
    (site / "mypkg" / "problems.py").write_text(USER_PROBLEMS_PY)
    (site / "mypkg" / "broken.py").write_text(USER_BROKEN_PY)
    return site


def user_environment(site: Path) -> dict[str, str]:
    """This environment with ``site`` (a user's packages) first on PYTHONPATH."""
    paths = [str(site), *filter(None, [os.environ.get("PYTHONPATH")])]
    return dict(os.environ, PYTHONPATH=os.pathsep.join(paths), OMP_NUM_THREADS="1")


def run_ocpar(site: Path, cwd: Path, *args: str, mpi_ranks: int | None = None,
              timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m ocpar ARGS`` in ``cwd`` with the packages in ``site`` importable."""
    cmd = [sys.executable, "-m", "ocpar", *args]
    if mpi_ranks is not None:
        cmd = [tool("mpirun"), "-n", str(mpi_ranks), *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=cwd,
                          env=user_environment(site))


def computed(result: dict) -> dict:
    """result.json without the fields that depend on where and how long it ran."""
    return {key: value for key, value in result.items() if key not in RUNTIME}


def read_result(directory: Path) -> dict:
    return json.loads((directory / "result.json").read_text())


def script_module(name: str):
    """``scripts/NAME.py`` as a module (scripts/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module

