"""Failed inner solves are data: with the test-only fault injector (``fault_injection``, a
wrapper around the engine's kernels through ``OCPAR_KERNEL_WRAPPER``) failing the first
attempt of a fraction of inner solves, every scheme's failure policy still gets it to its
answer, and the failures are counted."""

from __future__ import annotations

import json
import os
import signal
import threading
from functools import partial

import fault_injection
import pytest
from conftest import run_cli

from ocpar.bsp.dask import DaskBackend
from ocpar.bsp.kernel import WRAPPER_VARIABLE, resolve_kernel
from ocpar.bsp.serial import SerialBackend
from ocpar.bsp.workload import Delayed
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.examples.pursuit_orbit_transfer import make as orbit_transfer
from ocpar.formation import solve_formation
from ocpar.macs import MacsSettings, make_problem, solve_macs
from ocpar.ocp import solve_task
from ocpar.pursuit import PursuitSettings, solve_pursuit


@pytest.fixture
def inject(monkeypatch):
    """inject("0.3:1") switches the injector on for one test, in this process and the
    processes it starts."""
    yield partial(fault_injection.enable, monkeypatch)
    fault_injection.enable(monkeypatch, None)


def test_the_injector_is_off_by_default_and_checks_its_setting(inject):
    assert not any(fault_injection.injected(bytes([k])) for k in range(256))
    assert resolve_kernel("ocpar.ocp:solve_task") is solve_task  # no wrapper: the kernel
    inject("0.5:3")
    hits = sum(fault_injection.injected(bytes([k, j])) for k in range(64) for j in range(16))
    assert 400 < hits < 624  # about half of 1024, and the same in every process
    assert resolve_kernel("ocpar.ocp:solve_task") is not solve_task
    inject("2")
    with pytest.raises(ValueError, match="rate"):
        fault_injection.injected(b"x")


def test_a_bad_wrapper_reference_is_refused(monkeypatch):
    monkeypatch.setenv(WRAPPER_VARIABLE, "no_colon")
    resolve_kernel.cache_clear()
    try:
        with pytest.raises(ValueError, match="OCPAR_KERNEL_WRAPPER"):
            resolve_kernel("ocpar.ocp:solve_task")
    finally:
        monkeypatch.delenv(WRAPPER_VARIABLE)
        resolve_kernel.cache_clear()


def test_formation_retries_failed_solves_and_reaches_the_same_optimum(inject):
    problem = paper_example(12)
    clean = solve_formation(problem)
    inject("0.3:1")
    faulty = solve_formation(problem)
    assert faulty.converged and faulty.failed_solves == 0
    assert faulty.retries > 10  # ~30% of 108 first attempts failed and were retried
    assert faulty.total_cost == pytest.approx(clean.total_cost, rel=1e-10)
    assert clean.retries == 0


def test_formation_faults_are_the_same_under_mpirun(tmp_path, inject):
    """The injector reaches MPI ranks through the environment and fails the same solves: the
    serial and the 2-rank runs retry equally often and agree."""
    inject("0.3:1")
    serial = solve_formation(paper_example(12))
    out = tmp_path / "mpi"
    proc = run_cli("-m", "ocpar.formation", "--agents", "12", "--quiet", "--output", str(out),
                   mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["retries"] == serial.retries and result["failed_solves"] == 0
    assert result["total_cost"] == pytest.approx(serial.total_cost, rel=1e-12)


def test_formation_faults_are_the_same_on_dask_workers(inject):
    """The injector reaches embedded Dask worker processes (environment and PYTHONPATH) and
    fails the same solves as in a serial run: same retries, same cost bit for bit."""
    inject("0.3:1")
    serial = solve_formation(paper_example(12))
    with DaskBackend(workers=2) as backend:
        dask = solve_formation(paper_example(12), backend)
    assert serial.retries > 10 and dask.retries == serial.retries
    assert dask.failed_solves == 0 and dask.total_cost == serial.total_cost


def test_pursuit_retries_from_the_leaders_trajectory(inject):
    problem = orbit_transfer(case=1, samples=101)
    settings = PursuitSettings(window=32, update=16, max_agents=12, certify_samples=0)
    clean = solve_pursuit(problem, settings, reference=False)
    inject("0.3:2")
    faulty = solve_pursuit(problem, settings, reference=False)
    assert faulty.retries > 0 and faulty.failed_solves == 0
    # stopped at its agent budget: no headline; the train's last agent's final mass, kg
    assert clean.status == faulty.status == "not_converged"
    assert faulty.train_headline == pytest.approx(clean.train_headline, abs=1e-6)


def test_macs_rejects_failed_searches_and_still_finds_the_front(inject):
    settings = MacsSettings(max_evaluations=1500, archive_size=10, seed=7)
    inject("0.2:4")
    result = solve_macs(make_problem("goddard"), settings)
    assert result.failed_searches > 5
    assert result.to_dict()["failed_solves"] == result.failed_searches
    # 1,500 evaluations leave some members short of Pareto stationarity: not converged, so
    # the front's quality is no headline (None), but the front found is kept beside it
    assert result.status == "not_converged" and result.gd is None
    front = result.last_iterate
    assert front["gd"] < 0.05 and front["hv"] > 0.7


def test_a_dask_worker_killed_in_the_middle_of_a_superstep_is_replaced():
    """Six DMOC solves of the formation, each made to take 0.4 s, on two Dask workers: one
    worker is killed (SIGKILL) 0.5 s into the superstep; its chunk runs again on a live
    worker and the results equal the serial ones bit for bit. The next superstep runs on the
    workers that are left."""
    problem = paper_example(6)
    tasks = problem.tasks(problem.initial_phi()).items()
    slow = [Delayed(0.4, "ocpar.ocp:solve_task", task) for task in tasks]
    with SerialBackend() as serial:
        expected = [s.cost for s in serial.superstep(solve_task, tasks)]
    with DaskBackend(workers=2) as backend:
        pids = backend.client.run(os.getpid)
        victim = pids[backend.addresses[1]]
        threading.Timer(0.5, os.kill, (victim, signal.SIGKILL)).start()
        got = backend.superstep("ocpar.bsp.workload:delayed", slow)
        assert [s.cost for s in got] == expected
        assert backend.lost_chunks == 1
        again = backend.superstep(solve_task, tasks)
        assert [s.cost for s in again] == expected
