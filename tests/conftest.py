"""Shared fixtures: paths of the tools the tests launch, and small problems."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

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


@pytest.fixture(scope="session")
def dask_cluster():
    """:func:`local_cluster` for the whole session."""
    with local_cluster() as address:
        yield address
