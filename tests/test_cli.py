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


def test_no_core_is_spare_where_the_run_keeps_them_all_busy():
    """The picture's warm-up (Matplotlib imported beside the solve) never takes a core from a
    run whose workers fill the machine; one more busy process than cores leaves none either."""
    import os

    from ocpar.driver import spare_core

    cores = len(os.sched_getaffinity(0))
    assert not spare_core(cores) and not spare_core(cores + 1)


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


def test_a_negative_number_is_an_options_value(capsys):
    """``--epsilon -1e-6`` reaches the option's own check (argparse before Python 3.13 took
    -1e-6 for an unknown option); negative values parse in every notation."""
    from ocpar.cli import OneLineParser
    from ocpar.driver import parse_options
    from ocpar.pursuit.run import PursuitRun

    parser = OneLineParser(prog="p")
    parser.add_argument("--x", type=float)
    for text, value in (("-1e-6", -1e-6), ("-2", -2.0), ("-.5", -0.5), ("-3.E+2", -300.0),
                        ("-inf", -math.inf)):
        assert parser.parse_args(["--x", text]).x == value
    with pytest.raises(SystemExit) as exit_:
        parse_options(PursuitRun, ["--epsilon", "-1e-6"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err == ("ocpar.pursuit: error: argument --epsilon: expected a "
                                       "positive finite number, got -1e-06\n")


def test_ocpar_warnings_are_one_line_on_the_command_line(monkeypatch, capsys):
    """A command line shows ocpar's own warnings (the norm squared) as ``prog: warning: ...``
    alone, other packages' as Python does; in Python the warning names the user's line."""
    import dataclasses
    import warnings

    import casadi as ca

    from ocpar.cli import one_line_warnings
    from ocpar.ocp import DmocShape
    from ocpar.ocp.constraints import NormSquared, PathConstraint

    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    norm = PathConstraint(lambda u: ca.norm_2(u), upper=2.0, name="thrust")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        from ocpar.models import PointMass
        DmocShape(PointMass(dim=2), path_constraints=(norm,))  # this line
    assert [w.category for w in caught] == [NormSquared]
    assert caught[0].filename == __file__   # the user's line, not ocpar's
    others = []   # what Python's (here: a stand-in's) display of a warning gets
    monkeypatch.setattr(warnings, "showwarning", lambda message, *args: others.append(message))
    stand_in = warnings.showwarning
    with one_line_warnings("ocpar.formation"):
        warnings.simplefilter("always")
        dataclasses.replace(DmocShape(PointMass(dim=2)), path_constraints=(norm,))
        warnings.showwarning("not ocpar's", UserWarning, "user.py", 3)
    assert capsys.readouterr().err == (
        "ocpar.formation: warning: path_constraints[0] (thrust): a norm is not "
        "differentiable at 0; solved exactly as its square (row 0: (sq(u_0)+sq(u_1)) in "
        "[-inf, 4])\n")
    assert others == ["not ocpar's"]
    assert warnings.showwarning is stand_in   # restored on exit


def test_ctrl_c_is_one_line_and_keeps_the_checkpoint(tmp_path):
    """SIGINT to the run's process group (as a terminal's Ctrl-C: the embedded Dask
    cluster's workers get it too): one line on stderr naming the checkpoint, no worker's
    traceback, exit status 130, the checkpoint holds the supersteps done."""
    import os
    import signal

    from ocpar.cli import EXIT_INTERRUPTED

    checkpoint = tmp_path / "ck"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ocpar.macs", "--problem", "goddard", "--max-evals", "1000000",
         "--backend", "dask", "--workers", "2", "--checkpoint", str(checkpoint)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
        start_new_session=True,
        # as a terminal's foreground job: SIGINT not ignored, even where this test run was
        # started in the background (a non-interactive shell's `cmd &` ignores SIGINT, and
        # the run would inherit that)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines = [proc.stdout.readline() for _ in range(3)]  # dashboard, description, iteration
    assert lines[2].startswith("iteration"), lines
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == EXIT_INTERRUPTED == 130
    assert err == (f"ocpar.macs: interrupted (Ctrl-C); the checkpoint {checkpoint} holds every "
                   f"completed superstep (resume with --resume {checkpoint})\n")
    assert (checkpoint / "manifest.json").exists()
    assert len(list(checkpoint.iterdir())) > 1   # supersteps recorded


def test_an_output_directory_of_another_run_is_refused_unless_overwrite(tmp_path, capsys):
    """--output DIR holding another scheme's (or problem's) run: one line, exit 2, nothing
    touched; with --overwrite that run's files are replaced and its plot removed; a rerun of
    the same scheme and problem replaces its own files without --overwrite."""
    from ocpar.driver import main
    from ocpar.formation.run import FormationRun
    from ocpar.pursuit.run import PursuitRun

    out = tmp_path / "run"
    formation = ["--agents", "4", "--radius", "3", "--quiet", "--output", str(out)]
    assert main(FormationRun, formation) == 0
    assert main(FormationRun, formation) == 0           # a rerun: its own files replaced
    before = (out / "result.json").read_text()
    pursuit = ["--samples", "21", "--window", "11", "--update", "5", "--max-agents", "3",
               "--certify-samples", "0", "--no-reference", "--quiet", "--output", str(out)]
    with pytest.raises(SystemExit) as exit_:
        main(PursuitRun, pursuit)
    assert exit_.value.code == 2
    assert capsys.readouterr().err == (
        f"ocpar.pursuit: error: --output {out} holds another run's files (a formation run of "
        "point-mass-plane); give --overwrite to replace them, or another directory\n")
    assert (out / "result.json").read_text() == before
    main(PursuitRun, [*pursuit, "--overwrite"])
    assert json.loads((out / "result.json").read_text())["scheme"] == "pursuit"
    assert (out / "pursuit.png").exists() and not (out / "formation.png").exists()
