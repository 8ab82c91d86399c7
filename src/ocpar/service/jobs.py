"""Jobs on the scheduler's host: one directory per job under the jobs root.

The jobs root is ``$OCPAR_JOBS_DIR`` in the scheduler's environment (default
``~/.ocpar/jobs`` of the user running the scheduler); clients never read it directly, they
ask the scheduler (``Client.run_on_scheduler``) to run the functions below, so a client needs
no shared file system. A job directory holds

* ``job.json``: id, scheme, the scheme's command line, scheduler address, the paths of the
  certificate files its coordinator presents on a ``tls://`` cluster, submission time;
* ``coordinator.pid``: the pid of the job's coordinator (the leader of its process group),
  written as it starts;
* ``state.json``: ``queued`` → ``running`` (with the coordinator's pid) → ``finished``,
  ``failed`` (with a ``reason``) or ``cancelled`` (with the exit status), written
  atomically. A job whose coordinator is gone while its state says ``queued`` or ``running``
  (killed or crashed at any moment, before its run or during it) is ``failed`` with the
  reason as soon as its status is asked for (:func:`job_status`), the rest of its process
  group killed;
* ``checkpoint/`` (the run's journal: supersteps done, resumable with ``--resume``),
  ``output/`` (``result.json`` and plots), ``log.txt`` (the coordinator's progress lines),
  and ``cancel`` once a cancellation is asked for (the run stops at the next superstep
  boundary).

The coordinator runs as a detached process on the scheduler's host
(:mod:`ocpar.service.coordinator`): it is a Dask client, not a Dask task, so it takes no worker
slot and a one-worker cluster cannot deadlock; it survives the submitting process. On a
cluster secured with TLS it presents the scheduler's own CA file, certificate and key (so that
certificate must be good for both ends, as workers/tls.md makes them).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ocpar.bsp.journal import MANIFEST, recorded_supersteps
from ocpar.cli import EXIT_CANCELLED
from ocpar.results import EXIT_STATUS

JOBS_DIR_ENV = "OCPAR_JOBS_DIR"
#: The file of a job's directory that holds its coordinator's pid.
COORDINATOR_PID = "coordinator.pid"
#: A job's id: its scheme, the submission time and 6 random hex digits.
JOB_ID = re.compile(r"(?:formation|pursuit|macs)-[0-9]{8}-[0-9]{6}-[0-9a-f]{6}", re.ASCII)
#: Files of a finished job that ``ocpar result`` fetches (from ``output/``).
RESULT_SUFFIXES = (".json", ".nc", ".png")


#: Exit statuses of a run that ended with its result.json (every status but cancelled).
FINISHED = frozenset(code for status, code in EXIT_STATUS.items() if status != "cancelled")


class JobError(ValueError):
    """No such job, or an action its state does not allow (one-line message)."""


def jobs_root() -> Path:
    """The jobs root on this host (created if missing), as an absolute path: a relative
    ``$OCPAR_JOBS_DIR`` is taken from the scheduler's working directory (a job's coordinator
    runs in its own directory, so a relative path would not lead it back to its job)."""
    root = Path(os.environ.get(JOBS_DIR_ENV) or Path.home() / ".ocpar" / "jobs"
                ).expanduser().resolve()
    root.mkdir(parents=True, exist_ok=True)
    return root


def check_job_id(job_id: str) -> str:
    """``job_id`` if it has the form of the ids :func:`create_and_start` makes
    (SCHEME-YYYYMMDD-HHMMSS-XXXXXX); a JobError with one line otherwise."""
    if not isinstance(job_id, str) or not JOB_ID.fullmatch(job_id):
        shown = repr(job_id) if len(str(job_id)) <= 60 else f"{str(job_id)[:40]!r}... " \
            f"({len(job_id)} characters)"
        raise JobError(f"not a job id: {shown}; expected SCHEME-YYYYMMDD-HHMMSS-XXXXXX as "
                       "ocpar submit printed it")
    return job_id


def job_dir(job_id: str) -> Path:
    """The directory of ``job_id`` (a JobError if there is none)."""
    path = jobs_root() / check_job_id(job_id)
    if not (path / "job.json").exists():
        raise JobError(f"no job {job_id} on this cluster")
    return path


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def write_state(path: Path, state: str, **details: Any) -> None:
    """Set the state of the job in directory ``path``."""
    _write_json(path / "state.json", {"state": state, "time": time.time(), **details})


def new_job_id(scheme: str) -> str:
    """A fresh job id for a run of ``scheme`` (see :data:`JOB_ID`)."""
    return f"{scheme}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}"


def run_command(path: Path, scheme: str, argv: list[str], backend: list[str],
                resume: bool = False, launcher: list[str] | None = None) -> list[str]:
    """The scheme's command line for the job in directory ``path``: ``argv`` (the run's own
    options), then ``backend`` (where it runs), checkpointing into ``path/checkpoint`` (or
    resuming from it), writing ``path/output`` and stopping at a superstep boundary once
    ``path/cancel`` exists; ``launcher`` (e.g. ``mpirun -n 2``) goes in front."""
    journal = "--resume" if resume else "--checkpoint"
    return [*(launcher or []), sys.executable, "-m", f"ocpar.{scheme}", *argv, *backend,
            journal, str(path / "checkpoint"), "--output", str(path / "output"),
            "--stop-file", str(path / "cancel")]


def supersteps_done(path: Path) -> int:
    """The supersteps recorded in the checkpoint of the job in ``path`` (0 if none yet)."""
    return recorded_supersteps(path / "checkpoint")


def has_checkpoint(path: Path) -> bool:
    """Whether the job in ``path`` has a checkpoint to resume (``--resume``)."""
    return (path / "checkpoint" / MANIFEST).exists()


def outcome(path: Path, exit_status: int) -> tuple[str, str | None]:
    """How the run of the job in ``path`` ended, from its exit status: ``("cancelled",
    None)`` (stopped by its stop file), ``("finished", STATUS)`` (it wrote
    ``output/result.json`` with that status) or ``("failed", None)``."""
    result = path / "output" / "result.json"
    if exit_status == EXIT_CANCELLED:
        return "cancelled", None
    if exit_status in FINISHED and result.exists():
        try:
            return "finished", json.loads(result.read_text()).get("status")
        except ValueError:
            return "failed", None
    return "failed", None


def scheduler_certificate(dask_scheduler: Any) -> dict[str, str]:
    """The CA file, certificate and key of the scheduler ``dask_scheduler`` (absolute paths),
    which the coordinators of a ``tls://`` cluster's jobs present as clients."""
    security = dask_scheduler.security
    files = {"tls_ca_file": security.tls_ca_file, "tls_cert": security.tls_scheduler_cert,
             "tls_key": security.tls_scheduler_key}
    labels = {"tls_ca_file": "CA file", "tls_cert": "certificate", "tls_key": "key"}
    for name, value in files.items():
        if not value or "-----BEGIN" in value or not os.path.isfile(value):
            raise JobError(f"the scheduler's TLS {labels[name]} is not a file "
                           f"({'unset' if not value else 'given inline'}); a job's coordinator "
                           "presents the scheduler's own certificate files (workers/tls.md)")
    return {name: os.path.abspath(value) for name, value in files.items()}


def create_and_start(scheme: str, argv: list[str], scheduler: str,
                     dask_scheduler: Any = None) -> str:
    """Make a job directory for ``python -m ocpar.<scheme> argv`` against ``scheduler`` and
    start its coordinator, detached (runs in the scheduler's process, ``dask_scheduler``);
    returns the job id. On a ``tls://`` cluster the coordinator connects with the scheduler's
    own certificate files."""
    tls = scheduler_certificate(dask_scheduler) if scheduler.startswith("tls://") else None
    job_id = new_job_id(scheme)
    path = jobs_root() / job_id
    path.mkdir()
    _write_json(path / "job.json", {"id": job_id, "scheme": scheme, "argv": argv,
                                    "scheduler": scheduler, "tls": tls,
                                    "submitted": time.time()})
    write_state(path, "queued")
    with open(path / "log.txt", "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "ocpar.service.coordinator", str(path)],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                start_new_session=True, cwd=path)
    tmp = path / f".{COORDINATOR_PID}"
    tmp.write_text(str(proc.pid))
    os.replace(tmp, path / COORDINATOR_PID)
    return job_id


def coordinator_gone(path: Path) -> str | None:
    """How the coordinator of the job in ``path`` ended (``killed by signal 9``, ``exit status
    1`` where this process started it, else ``ended``), None while it lives or if its pid is
    not known yet."""
    try:
        pid = int((path / COORDINATOR_PID).read_text())
    except (OSError, ValueError):
        return None
    try:  # this process's child (the scheduler started it): its exit status, once reaped
        done, status = os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        done = 0
    else:
        if not done:
            return None
        return (f"killed by signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status)
                else f"exit status {os.WEXITSTATUS(status)}")
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        command = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return "ended"
    alive = stat.rsplit(")", 1)[1].split()[0] != "Z" and str(path) in command
    return None if alive else "ended"


def _fail_if_orphaned(path: Path, state: dict) -> dict:
    """``state``, or the ``failed`` state (recorded, the coordinator's process group killed)
    if it says queued or running but the coordinator is gone."""
    if state.get("state") not in ("queued", "running"):
        return state
    how = coordinator_gone(path)
    if how is None:
        return state
    current = json.loads((path / "state.json").read_text())  # written before it exited?
    if current.get("state") not in ("queued", "running"):
        return current
    with contextlib.suppress(ProcessLookupError, PermissionError, ValueError, OSError):
        os.killpg(int((path / COORDINATOR_PID).read_text()), signal.SIGKILL)
    write_state(path, "failed", reason=f"its coordinator {how} while the job was "
                f"{current['state']} (killed or crashed); {log_last_line(path)}")
    return json.loads((path / "state.json").read_text())


def log_last_line(path: Path) -> str:
    """The last non-blank line of the job's log, for a reason."""
    try:
        lines = (path / "log.txt").read_text(errors="replace").splitlines()
    except OSError:
        lines = []
    last = next((line.strip() for line in reversed(lines) if line.strip()), None)
    return f"its log's last line: {last[:300]}" if last else "its log is empty"


def job_status(job_id: str) -> dict:
    """State, supersteps done and the last progress line of ``job_id``."""
    path = job_dir(job_id)
    job = json.loads((path / "job.json").read_text())
    state = _fail_if_orphaned(path, json.loads((path / "state.json").read_text()))
    supersteps = supersteps_done(path)
    lines = [line for line in (path / "log.txt").read_text(errors="replace").splitlines()
             if line.strip()] if (path / "log.txt").exists() else []
    return {"id": job_id, "scheme": job["scheme"], **state, "supersteps": supersteps,
            "progress": lines[-1] if lines else "", "submitted": job["submitted"],
            "checkpoint": str(path / "checkpoint"), "cancel_requested":
            (path / "cancel").exists()}


def list_jobs() -> list[dict]:
    """The status of every job, oldest first."""
    ids = sorted((p.name for p in jobs_root().iterdir() if (p / "job.json").exists()),
                 key=lambda name: (jobs_root() / name / "job.json").stat().st_mtime)
    return [job_status(job_id) for job_id in ids]


def result_files(job_id: str) -> dict[str, bytes]:
    """``result.json`` and the plots of a finished job, by file name."""
    status = job_status(job_id)
    output = job_dir(job_id) / "output"
    if not (output / "result.json").exists():
        raise JobError(f"job {job_id} has no result yet (state {status['state']})")
    return {p.name: p.read_bytes() for p in sorted(output.iterdir())
            if p.suffix in RESULT_SUFFIXES}


def cancel(job_id: str) -> dict:
    """Ask ``job_id`` to stop at its next superstep boundary; returns its status."""
    status = job_status(job_id)
    if status["state"] in ("finished", "failed", "cancelled"):
        raise JobError(f"job {job_id} is already {status['state']}")
    (job_dir(job_id) / "cancel").touch()
    return job_status(job_id)
