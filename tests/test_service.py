"""The solver as a service: detached jobs on a real Dask cluster (``dask scheduler`` and two
workers from ``workers/start-dask-worker.sh`` on 127.0.0.1), submitted, watched, fetched and
cancelled by separate ``ocpar`` processes."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import free_port, local_cluster, run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ocpar.service import client, jobs
from ocpar.service.client import ServiceError

MACS = ["macs-goddard", "--set", "max_evals=1500", "seed=7"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A cluster whose scheduler keeps its jobs in a temporary directory."""
    jobs_dir = tmp_path_factory.mktemp("jobs")
    with local_cluster({"OCPAR_JOBS_DIR": str(jobs_dir)}) as address:
        yield address, jobs_dir


def ocpar(*args: str, timeout: float = 120):
    return run_cli("-m", "ocpar", *args, timeout=timeout)


def submit(address: str, *config: str) -> str:
    proc = ocpar("submit", *config, "--scheduler", address)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def status(address: str, job: str) -> dict:
    proc = ocpar("status", job, "--scheduler", address, "--json")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def wait_for(address: str, job: str, states: tuple[str, ...], timeout: float = 300) -> dict:
    deadline = time.monotonic() + timeout
    while (state := status(address, job))["state"] not in states:
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    return state


def run_here(tmp_path: Path, name: str, *config: str) -> dict:
    """The same configuration through ``ocpar run``, serially, here."""
    out = tmp_path / name
    proc = ocpar("run", *config[:1], "--set", f"output={out}", "quiet=true", *config[2:])
    assert proc.returncode == 0, proc.stderr
    return json.loads((out / "result.json").read_text())


@pytest.mark.slow  # each scheme's job against its serial run is in the default run (test_matrix)
def test_two_jobs_submitted_at_once_finish_and_match_ocpar_run(cluster, tmp_path):
    """The formation (60 agents) and a MACS run are submitted at once on the two-worker
    cluster; the submitting processes exit at once; a later process fetches both results,
    which equal ``ocpar run`` of the same configurations."""
    address, _ = cluster
    formation = submit(address, "formation-60")
    macs = submit(address, *MACS)
    assert formation != macs
    listed = ocpar("jobs", "--scheduler", address)
    assert formation in listed.stdout and macs in listed.stdout

    for job, expected, same in (
        (formation, run_here(tmp_path, "formation", "formation-60"),
         lambda a, b: a["total_cost"] == b["total_cost"] and a["phi"] == b["phi"]),
        (macs, run_here(tmp_path, "macs", *MACS),
         lambda a, b: a["front"] == b["front"] and a["hv"] == b["hv"]),
    ):
        final = wait_for(address, job, ("finished", "failed", "cancelled"))
        assert final["state"] == "finished", final
        assert final["supersteps"] == expected["supersteps"]
        out = tmp_path / f"fetched-{job}"
        proc = ocpar("result", job, "--scheduler", address, "--output", str(out))
        assert proc.returncode == 0, proc.stderr
        result = json.loads((out / "result.json").read_text())
        assert same(result, expected)
        assert result["backend"] == "dask" and result["workers"] == 2
        assert any(p.suffix == ".png" for p in out.iterdir())


@pytest.mark.slow  # (the HTTP service's cancel and resume are in the default run)
def test_cancel_stops_within_a_superstep_and_the_checkpoint_resumes(cluster, tmp_path):
    address, jobs_dir = cluster
    config = ["macs-goddard", "--set", "max_evals=3000", "seed=3"]
    job = submit(address, *config)
    state = wait_for(address, job, ("running",))
    while state["supersteps"] < 5:
        time.sleep(0.2)
        state = status(address, job)
    proc = ocpar("cancel", job, "--scheduler", address)
    assert proc.returncode == 0, proc.stderr
    asked_at = status(address, job)["supersteps"]
    final = wait_for(address, job, ("finished", "failed", "cancelled"), timeout=120)
    assert final["state"] == "cancelled"
    assert final["supersteps"] <= asked_at + 1  # within one superstep
    proc = ocpar("result", job, "--scheduler", address, "--output", str(tmp_path / "none"))
    assert proc.returncode == 2 and "no result yet" in proc.stderr

    expected = run_here(tmp_path, "whole", *config)
    resumed = tmp_path / "resumed"
    proc = run_cli("-m", "ocpar.macs", "--problem", "goddard", "--max-evals", "3000",
                   "--archive", "10", "--seed", "3", "--quiet",
                   "--resume", str(jobs_dir / job / "checkpoint"), "--output", str(resumed))
    assert proc.returncode == 0, proc.stderr
    result = json.loads((resumed / "result.json").read_text())
    assert result["front"] == expected["front"] and result["hv"] == expected["hv"]


def test_service_commands_refuse_bad_input_with_one_line(cluster):
    address, _ = cluster
    cases = [
        (["submit", "formation-60", "--set", "agents=1", "--scheduler", address], "--agents"),
        (["submit", "no-such-config", "--scheduler", address], "no-such-config"),
        (["status", "formation-19990101-000000-abcdef", "--scheduler", address], "no job"),
        (["cancel", "../etc", "--scheduler", address], "not a job id"),
        (["jobs", "--scheduler", "tcp://127.0.0.1:1"], "cannot reach"),
    ]
    for args, needle in cases:
        proc = ocpar(*args)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], proc.stderr


@pytest.mark.parametrize(("reference", "needle"), [
    ("no_such_pkg.problems:make", "no module named 'no_such_pkg'"),
    ("ocpar.examples.formation_point_masses:no_factory", "has no attribute 'no_factory'"),
    ("ocpar.macs.problems:PROBLEMS", "not a function"),
])
def test_submit_loads_a_problem_reference_on_the_scheduler_before_a_job_exists(
        cluster, reference, needle, tmp_path):
    """A ``module:factory`` that does not load where the job would run (the scheduler's
    host) is refused by ``ocpar submit`` with one line and exit 2, and no job is made."""
    address, jobs_dir = cluster
    config = tmp_path / "mine.toml"
    config.write_text(f'scheme = "formation"\nproblem = "{reference}"\n')
    before = sorted(p.name for p in jobs_dir.iterdir())
    proc = ocpar("submit", str(config), "--scheduler", address)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and proc.stdout == "" and len(lines) == 1, proc.stderr
    assert lines[0].startswith("ocpar submit: error: on the scheduler's host: problem ")
    assert needle in lines[0]
    assert sorted(p.name for p in jobs_dir.iterdir()) == before


@pytest.mark.parametrize("option", ["--output", "--tls-cert=client.pem", "--dispatch",
                                    "--scheduler"])
def test_submit_refuses_options_the_service_sets(option):
    with pytest.raises(ServiceError, match=f"{option.split('=')[0]} is set by the service"):
        client.check_run("formation", ["--agents", "6", option, "x"])


@pytest.mark.parametrize(("files", "needle"), [
    ({"tls_ca_file": "-----BEGIN CERTIFICATE-----\n..."}, "CA file is not a file (given inline)"),
    ({"tls_scheduler_key": None}, "key is not a file (unset)"),
])
def test_a_tls_scheduler_without_certificate_files_cannot_start_jobs(tmp_path, files, needle):
    paths = {name: str(tmp_path / name) for name in
             ("tls_ca_file", "tls_scheduler_cert", "tls_scheduler_key")}
    for path in paths.values():
        Path(path).write_text("PEM")
    scheduler = SimpleNamespace(security=SimpleNamespace(**{**paths, **files}))
    with pytest.raises(jobs.JobError, match=re.escape(needle)):
        jobs.scheduler_certificate(scheduler)
    assert jobs.scheduler_certificate(SimpleNamespace(security=SimpleNamespace(**paths))) == {
        "tls_ca_file": paths["tls_ca_file"], "tls_cert": paths["tls_scheduler_cert"],
        "tls_key": paths["tls_scheduler_key"]}


# --- job ids ---------------------------------------------------------------------------------

LONG_ID = "formation-" + "9" * 290


@pytest.mark.parametrize("command", [["status", LONG_ID], ["status", LONG_ID, "--json"],
                                     ["result", LONG_ID, "--output", "out"],
                                     ["cancel", LONG_ID], ["status", "../../etc/passwd"],
                                     ["cancel", "formation-20260101-000000-ABCDEF"],
                                     ["result", "", "--output", "out"]])
def test_job_ids_are_checked_before_the_scheduler_is_asked(command, capsys):
    """A malformed id is refused with one line and exit 2 (the scheduler address is not
    even reachable: the id is checked first)."""
    from ocpar.__main__ import main

    with pytest.raises(SystemExit) as exc:
        main([*command, "--scheduler", "tcp://127.0.0.1:1"])
    out, err = capsys.readouterr()
    assert exc.value.code == 2 and out == "", err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ocpar {command[0]}: error: not a job id")
    assert len(lines[0]) < 200  # a 300-character id is shortened


def test_a_long_job_id_from_a_separate_process():
    proc = ocpar("status", "x" * 300, "--scheduler", "tcp://127.0.0.1:1")
    assert proc.returncode == 2 and proc.stdout == "" and "Traceback" not in proc.stderr
    assert len(proc.stderr.splitlines()) == 1 and "not a job id" in proc.stderr


@settings(max_examples=200, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(job_id=st.one_of(st.text(max_size=400), st.text(alphabet="formation-0123456789abcdef",
                                                       min_size=20, max_size=40)))
def test_the_scheduler_side_refuses_what_is_not_a_job_id(job_id, tmp_path, monkeypatch):
    """On the scheduler, every action on an id is either a JobError (one line) or a real
    job; never an OSError from the file system (File name too long, a path outside)."""
    monkeypatch.setenv(jobs.JOBS_DIR_ENV, str(tmp_path))
    for action in (jobs.job_status, jobs.result_files, jobs.cancel):
        with pytest.raises(jobs.JobError) as exc:
            action(job_id)
        message = str(exc.value)
        assert "\n" not in message
        assert message.startswith("not a job id") == (jobs.JOB_ID.fullmatch(job_id) is None)


def test_a_relative_jobs_dir_is_the_schedulers_directory(tmp_path, monkeypatch):
    """A relative $OCPAR_JOBS_DIR is taken from the scheduler's working directory: job
    directories are absolute, so a coordinator started in its own directory finds its job
    (before: it looked for JOB/JOBS_DIR/JOB/job.json, and the job stayed queued forever)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv(jobs.JOBS_DIR_ENV, "jobs")
    assert jobs.jobs_root() == (tmp_path / "jobs").resolve()
    assert jobs.jobs_root().is_dir()


def test_submit_refuses_service_options_after_the_configuration(capsys):
    from ocpar.__main__ import main

    with pytest.raises(SystemExit) as exc:
        main(["submit", "formation-60", "--scheduler", "tcp://127.0.0.1:1", "--output", "x"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.splitlines() == [
        "ocpar submit: error: --output is set by the service for a submitted job; leave it out"]


@pytest.mark.parametrize("when", ["before its run", "during its run"])
def test_a_job_whose_coordinator_is_killed_ends_failed_with_the_reason(tmp_path, monkeypatch,
                                                                       when):
    """A job's coordinator killed (SIGKILL) before it records ``running``, or while its run
    waits for a scheduler that does not answer: the job's status says ``failed`` within 5 s,
    naming the signal and the state it was in, and no process of the job lives on."""
    monkeypatch.setenv(jobs.JOBS_DIR_ENV, str(tmp_path))
    job = jobs.create_and_start("formation", ["--agents", "4"],
                                f"tcp://127.0.0.1:{free_port()}")  # nobody listens there
    path = tmp_path / job
    pid = int((path / jobs.COORDINATOR_PID).read_text())
    if when == "during its run":
        deadline = time.monotonic() + 60
        while jobs.job_status(job)["state"] != "running" or "ocpar.formation" not in \
                subprocess.run(["ps", "-o", "args=", "-g", str(pid)], capture_output=True,
                               text=True).stdout:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        was = "running"
    else:
        assert jobs.job_status(job)["state"] == "queued"
        was = "queued"
    if was == "queued":
        os.killpg(pid, signal.SIGKILL)
    else:  # the coordinator alone: its run (the scheme's process) lives on until the check
        os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 5
    while (status := jobs.job_status(job))["state"] != "failed":
        assert status["state"] == was and time.monotonic() < deadline, status
        time.sleep(0.05)
    assert status["reason"].startswith(f"its coordinator killed by signal {signal.SIGKILL:d} "
                                       f"while the job was {was}"), status
    deadline = time.monotonic() + 5
    while (left := subprocess.run(["ps", "-o", "stat=", "-g", str(pid)], capture_output=True,
                                  text=True).stdout.split()) and set(left) != {"Z"}:
        assert time.monotonic() < deadline, left  # (zombies wait for their reaper)
        time.sleep(0.05)
