"""Checkpoints: a run killed (SIGKILL) after superstep k and resumed gives the result of an
uninterrupted run; a checkpoint of another run or format is refused with one line."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, run_cli

from ocpar.bsp.journal import INTERVAL_ENV, LOG, MANIFEST, CheckpointError, Journal
from ocpar.bsp.serial import SerialBackend
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation


def supersteps_recorded(directory: Path) -> int:
    try:
        return json.loads((directory / MANIFEST).read_text())["supersteps"]
    except (OSError, ValueError, KeyError):
        return 0


def kill_after(args: list[str], checkpoint: Path, k: int, timeout: float = 120,
               interval: str | None = "0") -> int:
    """Start ``python -m ...args --checkpoint DIR`` syncing every ``interval`` seconds (0:
    every superstep synced and counted in the manifest as it completes; None: the default),
    SIGKILL it once DIR's manifest counts k supersteps; return how many it counts after the
    kill."""
    env = {key: value for key, value in os.environ.items() if key != INTERVAL_ENV}
    if interval is not None:
        env[INTERVAL_ENV] = interval
    proc = subprocess.Popen([sys.executable, "-m", *args, "--checkpoint", str(checkpoint)],
                            cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + timeout
    while supersteps_recorded(checkpoint) < k:
        assert proc.poll() is None, f"run ended before superstep {k}: {proc.stderr.read()}"
        assert time.monotonic() < deadline, "no checkpoint progress"
        time.sleep(0.002)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return supersteps_recorded(checkpoint)


@pytest.mark.parametrize("args, k, same, interval", [
    (["ocpar.formation", "--agents", "60", "--quiet"], 3,
     lambda a, b: a["total_cost"] == b["total_cost"] and a["phi"] == b["phi"], "0"),
    pytest.param(
        ["ocpar.macs", "--problem", "goddard", "--max-evals", "1500", "--seed", "7", "--quiet"],
        6, lambda a, b: a["front"] == b["front"] and a["hv"] == b["hv"], "0",
        marks=pytest.mark.slow),  # 35 s; formation and pursuit resume in the default run
    # synced once a second (the default): the kill lands between syncs, the log keeps more
    (["ocpar.pursuit", "--samples", "601", "--window", "12", "--update", "6", "--quiet",
      "--plot", "none"], 3,
     lambda a, b: all(a[key] == b[key] for key in
                      ("final_mass_kg", "train_final_mass_kg", "constraint_violation")), None),
], ids=["formation", "macs", "pursuit-default-interval"])
def test_killed_run_resumes_to_the_uninterrupted_result(tmp_path, args, k, same, interval):
    whole = tmp_path / "whole"
    proc = run_cli("-m", *args, "--output", str(whole), "--checkpoint", str(tmp_path / "ck"))
    assert proc.returncode == 0, proc.stderr
    expected = json.loads((whole / "result.json").read_text())
    journaled = supersteps_recorded(tmp_path / "ck")  # pursuit's finish is one more
    assert journaled >= expected["supersteps"]

    checkpoint = tmp_path / "checkpoint"
    kept = kill_after(args, checkpoint, k, interval=interval)
    assert k <= kept < expected["supersteps"]  # killed in the middle, checkpoint intact
    resumed = tmp_path / "resumed"
    proc = run_cli("-m", *args, "--resume", str(checkpoint), "--output", str(resumed))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((resumed / "result.json").read_text())
    assert same(result, expected)
    assert result["supersteps"] == expected["supersteps"]
    assert supersteps_recorded(checkpoint) == journaled


def test_a_checkpoint_of_another_run_or_format_is_refused(tmp_path):
    checkpoint = tmp_path / "ck"
    proc = run_cli("-m", "ocpar.formation", "--agents", "6", "--quiet", "--checkpoint",
                   str(checkpoint))
    assert proc.returncode == 0, proc.stderr
    cases = [
        (["--agents", "7", "--resume", str(checkpoint)], "checkpoint of another run"),
        (["--agents", "6", "--checkpoint", str(checkpoint)], "already holds a checkpoint"),
        (["--agents", "6", "--resume", str(tmp_path / "none")], "holds no checkpoint"),
        (["--agents", "6", "--resume", str(checkpoint), "--checkpoint", str(checkpoint)],
         "not both"),
    ]
    for extra, needle in cases:
        proc = run_cli("-m", "ocpar.formation", "--quiet", *extra)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], proc.stderr
    manifest = checkpoint / MANIFEST
    data = json.loads(manifest.read_text())
    manifest.write_text(json.dumps(data | {"version": 999}))
    proc = run_cli("-m", "ocpar.formation", "--agents", "6", "--quiet", "--resume",
                   str(checkpoint))
    assert proc.returncode == 2 and "format version" in proc.stderr


def test_replay_refuses_a_superstep_with_other_tasks(tmp_path):
    """The journal also checks each superstep's tasks: a coordinator that would ask for other
    work than the recorded run (e.g. another problem with the same options) is stopped."""
    journal = Journal(tmp_path, {"run": "x"}, resume=False)
    backend = SerialBackend()
    backend.journal = journal
    solve_formation(paper_example(6), backend)
    resumed = SerialBackend()
    resumed.journal = Journal(tmp_path, {"run": "x"}, resume=True)
    with pytest.raises(CheckpointError, match="other tasks"):
        solve_formation(paper_example(6, radius=11.0), resumed)


def test_checkpoint_files_hold_no_pickles(tmp_path):
    """Each entry of the log: its length, its SHA-256, then JSON and the raw bytes of arrays of
    plain dtypes (described as in .npy files), which add up to the entry exactly."""
    with SerialBackend() as backend:  # its exit counts every superstep in the manifest
        backend.journal = Journal(tmp_path, {"run": "y"}, resume=False)
        solve_formation(paper_example(6), backend)
    log = (tmp_path / LOG).read_bytes()
    entries = 0
    while log:
        length, sha = int.from_bytes(log[:8], "little"), log[8:40]
        data, log = log[40:40 + length], log[40 + length:]
        assert hashlib.sha256(data).digest() == sha
        size = int.from_bytes(data[:8], "little")
        meta = json.loads(data[8:8 + size])
        dtypes = [(np.lib.format.descr_to_dtype(d), shape) for d, shape in meta["arrays"]]
        assert not any(dtype.hasobject for dtype, _ in dtypes)
        assert 8 + size + sum(d.itemsize * int(np.prod(shape)) for d, shape in dtypes) == length
        entries += 1
    assert entries == supersteps_recorded(tmp_path) == len(backend.traces)


MPI_HANG = """
from ocpar.bsp.mpi import MpiBackend
backend = MpiBackend(timeout_s=1.0)
if backend.is_coordinator:
    backend.superstep("ocpar.bsp.workload:spin", [0.01, 30.0])   # rank 1 'hangs' for 30 s
    print("not reached")
else:
    backend.serve()
"""


def test_an_mpi_superstep_past_its_deadline_aborts_with_a_clear_message(tmp_path):
    script = tmp_path / "hang.py"
    script.write_text(MPI_HANG)
    start = time.monotonic()
    proc = run_cli(str(script), mpi_ranks=2, timeout=60)
    assert time.monotonic() - start < 25  # aborted at the deadline, not after the 30 s task
    assert proc.returncode != 0 and "not reached" not in proc.stdout
    assert "no result from MPI rank(s) 1 within 1 s" in proc.stderr


@pytest.mark.slow
def test_killing_an_mpi_rank_ends_the_run_and_keeps_the_checkpoint(tmp_path):
    """SIGKILL of rank 1 mid-run: mpirun ends the job (no hang), the checkpoint holds the
    supersteps before, and resuming on two ranks gives the uninterrupted result. IPOPT inner
    solves make each superstep ~0.4 s, so the rank dies mid-run (the default solver ends
    the run's 5 supersteps in ~0.1 s, sometimes before the kill lands)."""
    args = ["ocpar.formation", "--agents", "300", "--inner-solver", "ipopt", "--quiet"]
    whole = tmp_path / "whole"
    proc = run_cli("-m", *args, "--output", str(whole), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    expected = json.loads((whole / "result.json").read_text())

    checkpoint = tmp_path / "ck"
    launcher = subprocess.Popen([str(Path(sys.executable).parent / "mpirun"), "-n", "2",
                                 sys.executable, "-m", *args, "--checkpoint", str(checkpoint)],
                                cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while supersteps_recorded(checkpoint) < 3:
        assert launcher.poll() is None and time.monotonic() < deadline
        time.sleep(0.002)
    ranks = subprocess.run(["pgrep", "-f", f"{' '.join(args)} --checkpoint {checkpoint}"],
                           capture_output=True, text=True).stdout.split()
    os.kill(int(max(ranks, key=int)), signal.SIGKILL)  # the last started: a rank, not mpirun
    launcher.wait(timeout=60)
    assert launcher.returncode != 0
    kept = supersteps_recorded(checkpoint)
    assert 3 <= kept < expected["supersteps"]
    resumed = tmp_path / "resumed"
    proc = run_cli("-m", *args, "--resume", str(checkpoint), "--output", str(resumed),
                   mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((resumed / "result.json").read_text())
    assert result["total_cost"] == expected["total_cost"] and result["phi"] == expected["phi"]


class Crash(Exception):
    """Stands in for the coordinator dying between supersteps."""


def crash_after(backend, supersteps: int) -> None:
    """Make ``backend`` die when it starts superstep ``supersteps`` + 1 (the run's own, which
    it traces: not the work before and after them, e.g. preparing the workers' solvers)."""
    run = backend._run_chunks

    def run_or_crash(name, chunks):
        if len(backend.traces) >= supersteps:
            raise Crash
        return run(name, chunks)

    backend._run_chunks = run_or_crash


def test_pursuit_resumes_to_the_uninterrupted_train(tmp_path):
    """The pursuit scheme through the Python API: the agent train (positions, plans, warm
    starts) is rebuilt by replay, and the final trajectory is identical."""
    from ocpar.examples.pursuit_orbit_transfer import make
    from ocpar.pursuit import PursuitSettings, solve_pursuit

    problem = make(case=1, samples=101)
    settings = PursuitSettings(window=32, update=16, max_agents=12)
    expected = solve_pursuit(problem, settings, reference=False)
    backend = SerialBackend()
    backend.journal = Journal(tmp_path, {"run": "pursuit"}, resume=False)
    crash_after(backend, 7)
    with pytest.raises(Crash):
        solve_pursuit(problem, settings, backend, reference=False)
    resumed = SerialBackend()
    resumed.journal = Journal(tmp_path, {"run": "pursuit"}, resume=True)
    assert resumed.journal.recorded_supersteps == 7
    result = solve_pursuit(problem, settings, resumed, reference=False)
    assert np.array_equal(result.x, expected.x) and np.array_equal(result.u, expected.u)
    assert result.supersteps == expected.supersteps


def test_pursuit_resumes_across_its_full_horizon_certificate(tmp_path):
    """The van der Pol example with ε = 1e-4: the full-horizon certificate (a superstep of its
    own) is replayed with the train, and the resumed run stops where the uninterrupted one
    did, on the same certified figure."""
    from ocpar.examples.pursuit_van_der_pol import make
    from ocpar.pursuit import PursuitSettings, solve_pursuit

    problem = make()
    settings = PursuitSettings(window=21, update=10, epsilon=1e-4, finish="train")
    expected = solve_pursuit(problem, settings, reference=False)
    assert expected.stop_reason == "certified_within_epsilon"
    backend = SerialBackend()
    backend.journal = Journal(tmp_path, {"run": "pursuit"}, resume=False)
    crash_after(backend, expected.supersteps - 1)  # after the certificate
    with pytest.raises(Crash):
        solve_pursuit(problem, settings, backend, reference=False)
    resumed = SerialBackend()
    resumed.journal = Journal(tmp_path, {"run": "pursuit"}, resume=True)
    result = solve_pursuit(problem, settings, resumed, reference=False)
    assert np.array_equal(result.u, expected.u) and result.agents == expected.agents
    assert result.certificate_headline == expected.certificate_headline
    assert result.estimated_remaining == expected.estimated_remaining
