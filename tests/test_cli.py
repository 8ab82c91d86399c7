"""The command line contract: result.json fields, plot, one-line errors with exit status 2."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import assert_result_contract, run_cli

from ocpar.result_files import load_trace

REQUIRED = {
    "scheme": str, "problem": str, "agents": int, "backend": str, "workers": int, "mode": str,
    "status": str, "total_cost": float, "phi": list, "equidistance_error": float,
    "outer_iterations": int, "supersteps": int, "inner_solves": int, "failed_solves": int,
    "wall_time_s": float, "title": str, "arrays": str, "trace_file": str,
}


def test_small_run_writes_result_and_plot(tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--agents", "8", "--radius", "5",
                   "--output", str(tmp_path / "run"))
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "run" / "result.json").read_text())
    for key, typ in REQUIRED.items():
        assert isinstance(data[key], typ), key
    assert data["scheme"] == "formation" and data["agents"] == 8 and len(data["phi"]) == 8
    assert data["backend"] == "serial" and data["mode"] == "hierarchical"
    assert data["equidistance_error"] <= 1e-9
    trace = load_trace(tmp_path / "run")
    assert data["supersteps"] == len(trace) == proc.stdout.count("superstep ")
    assert data["inner_solves"] == 8 * data["supersteps"]  # no superstep gathers the paths
    assert {"wall_s", "overhead_s", "worker_busy_s", "task_cpu_s"} <= set(trace[0])
    png = (tmp_path / "run" / "formation.png").read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000
    assert "total cost" in proc.stdout and "wall time" in proc.stdout
    # the last line: where the time went, the figures of result.json's timings
    last = proc.stdout.strip().splitlines()[-1]
    timings = data["timings"]
    assert last == ("timings: " + ", ".join(
        f"{name} {timings[key]:.2f} s" for key, name in (
            ("startup_s", "start-up"), ("build_s", "build"), ("solve_s", "solve"),
            ("verification_s", "verification"), ("files_s", "files"),
            ("picture_s", "picture"))) + f"; total {timings['total_s']:.2f} s")
    assert_result_contract(tmp_path / "run")


def test_monolithic_mode_from_the_command_line(tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--agents", "8", "--radius", "5", "--mode",
                   "monolithic", "--quiet", "--output", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["mode"] == "monolithic" and data["supersteps"] == 0
    assert load_trace(tmp_path) == []
    assert math.isfinite(data["total_cost"]) and data["equidistance_error"] <= 1e-9


def _unwritable_dir(tmp_path: Path) -> str:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    return str(blocker / "out")


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--agents", "1"], "--agents"),
        (["--agents", "many"], "--agents"),
        (["--radius", "0"], "--radius"),
        (["--radius", "nan"], "--radius"),
        (["--radius", "-2"], "--radius"),
        (["--backend", "threads"], "--backend"),
        (["--mode", "parallel"], "--mode"),
        (["--workers", "0"], "--workers"),
        (["--backend", "serial", "--workers", "3"], "serial"),
        (["--backend", "mpi"], "mpirun"),
        (["--scheduler", "not-an-address"], "--scheduler"),
        # (10 s of connection retries; an unreachable scheduler's one line is also in
        # test_service.py's default run)
        pytest.param(["--backend", "dask", "--scheduler", "tcp://127.0.0.1:9"], "scheduler",
                     marks=pytest.mark.slow),
        (["--output", "UNWRITABLE"], "not writable"),
        (["--agnets", "3"], "unrecognized"),
    ],
)
def test_bad_input_gets_one_line_and_status_2(args, needle, tmp_path):
    args = [_unwritable_dir(tmp_path) if a == "UNWRITABLE" else a for a in args]
    proc = run_cli("-m", "ocpar.formation", *args, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("ocpar.formation: error:") and needle in lines[0]
    assert "Traceback" not in proc.stderr + proc.stdout


def test_bad_input_under_mpirun_ends_every_rank(tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--agents", "1", mpi_ranks=2, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.count("error: argument --agents") == 1 and "Traceback" not in proc.stderr




def test_a_command_line_process_leaves_its_objects_out_of_the_exit_collections():
    """The exit handler runs after every exit handler registered before the command line ran
    (here: the one that reports what the interpreter's teardown will collect)."""
    script = ("import atexit, gc\n"
              "atexit.register(lambda: print(gc.get_freeze_count() > 0, gc.get_count()[2]))\n"
              "from ocpar import driver\n"
              "from ocpar.formation.run import FormationRun\n"
              "driver.main(FormationRun, ['--agents', '3', '--quiet'])\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.split()[-2:] == ["True", "0"]
