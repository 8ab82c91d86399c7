"""The supervisor of ``ocpar serve``: starts queued jobs within the limits, watches their
processes and records how they end.

Each job runs the scheme's command line (:func:`ocpar.service.jobs.run_command`:
checkpoint, output and stop file in the job's directory) on the server's backend: the
embedded Dask cluster (a process of its own, :mod:`ocpar.service.web.cluster`, started and
owned by the server), an existing cluster (``--scheduler``), ``mpirun -n W`` (``--backend
mpi``) or serially. On the Dask and serial backends it runs in a warm runner
(:mod:`ocpar.service.web.warm`: a process group of its own that has imported ocpar and keeps
its cluster connection, one job at a time, ``max_running`` of them); under ``mpirun`` as a
process group of its own, started for it. Pursuit jobs run serially in their warm runner on
a Dask server (:data:`SERIAL_ON_DASK`). Every process that runs jobs has
:data:`~ocpar.service.web.warm.JOB_NICENESS`: the server answers first.

A job's state: ``queued`` → ``running`` → ``succeeded`` (its ``result.json`` has status
converged), ``failed`` (any other result status, or no result: the reason says why) or
``cancelled`` (stopped by ``DELETE``, or by its token's wall-time limit: the stop file is
touched, and the process group killed if it still runs ``grace`` seconds later).

On start-up every job the database has as ``running`` (the server was stopped or killed
while it ran) has any surviving process group of its own killed and is queued again: it
resumes from its checkpoint, or starts afresh if it wrote none; a job whose directory is
gone is marked failed. None is lost, none is left ``running``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ocpar.service.coordinator import dask_options
from ocpar.service.jobs import has_checkpoint, outcome, run_command, supersteps_done
from ocpar.service.web.store import DEFAULT_SOLVER_OPTIONS, Store
from ocpar.service.web.warm import PICTURE_INPUT, PICTURE_NAMES, WarmPool, lower_priority

log = logging.getLogger("ocpar.serve")

#: The server's backends, and those whose jobs run in warm runners.
BACKENDS = ("dask", "mpi", "serial")
WARM_BACKENDS = ("dask", "serial")
#: Schemes whose jobs a Dask server runs serially in their warm runner: a pursuit superstep
#: holds the few agents in flight (up to ~5 inner solves of about a millisecond), less work
#: than one round trip to the workers (a 300-agent train of ``pursuit-case1``, 609
#: supersteps, solved in 3.7-4.5 s serially, 6-10 s with chunks sent directly to 2 workers,
#: 23-28 s through the scheduler, on a busy 2-core machine).
SERIAL_ON_DASK = frozenset({"pursuit"})


@dataclass(frozen=True)
class Settings:
    """How ``ocpar serve`` runs jobs and whom it serves."""

    state_dir: Path
    backend: str = "dask"
    workers: int = 2               # dask: the embedded cluster's workers; mpi: ranks per job
    scheduler: str | None = None   # an existing Dask cluster instead of the embedded one
    max_running: int = 2           # jobs running at once, over all tokens
    allow_problem: tuple[str, ...] = ()  # fnmatch patterns of module:factory references
    # fnmatch patterns of the solver options (SOLVER.NAME) a job may set
    allow_solver_option: tuple[str, ...] = DEFAULT_SOLVER_OPTIONS
    grace: float = 30.0            # s between a wall-time stop request and the kill
    max_job_memory: int | None = None  # bytes a job's estimate may reach (None: no limit)
    poll: float = 0.2              # s between the supervisor's rounds


class Runner:
    """Starts and watches the jobs of ``store`` (a thread of the server's process)."""

    def __init__(self, store: Store, settings: Settings) -> None:
        self.store = store
        self.settings = settings
        self.procs: dict[str, Any] = {}  # subprocess.Popen or WarmJob, by job id
        self.cluster: subprocess.Popen | None = None
        self.address = settings.scheduler
        self._stop = threading.Event()
        #: Set to start the supervisor's next round now (a job submitted, or one ended).
        self.wake = threading.Event()
        role = (["dask", str(self._address_file), self.dispatch]
                if settings.backend == "dask" else [settings.backend])
        self.pool = (WarmPool(store.state_dir, settings.max_running, _job_environment(),
                              self.wake, role) if settings.backend in WARM_BACKENDS else None)
        self._thread = threading.Thread(target=self._loop, name="ocpar-runner", daemon=True)

    # life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Recover the jobs a previous server left running, start the embedded cluster if
        it is the backend and the warm runners (neither waited for: the first Dask job starts
        once the cluster has said its address), then supervise."""
        self.recover()
        if self.settings.backend == "dask" and self.address is None:
            self._start_cluster()
        elif self.address is not None:  # an existing cluster's, for the warm runners
            self._address_file.write_text(self.address)
        if self.pool is not None:
            self.pool.maintain()
        self._thread.start()

    def stop(self) -> None:
        """Stop supervising: the running jobs' processes are ended and stay ``running`` in
        the database, so that the next start resumes them from their checkpoints."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        for proc in self.procs.values():
            _kill_group(proc.pid, signal.SIGTERM)
        for proc in self.procs.values():
            if isinstance(proc, subprocess.Popen):
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    _kill_group(proc.pid, signal.SIGKILL)
                    proc.wait()
        if self.pool is not None:
            self.pool.stop()
        if self.cluster is not None:
            self.cluster.terminate()
            try:
                self.cluster.wait(20)
            except subprocess.TimeoutExpired:
                _kill_group(self.cluster.pid, signal.SIGKILL)

    def _start_cluster(self) -> None:
        self._address_file.unlink(missing_ok=True)
        with open(self.store.state_dir / "cluster.log", "ab") as out:
            self.cluster = subprocess.Popen(
                [sys.executable, "-m", "ocpar.service.web.cluster", str(self._address_file),
                 str(self.settings.workers)], stdin=subprocess.DEVNULL, stdout=out,
                stderr=out, start_new_session=True, env=_job_environment())
        lower_priority(self.cluster.pid)
        self._cluster_deadline = time.monotonic() + 120

    @property
    def _address_file(self) -> Path:
        return self.store.state_dir / "cluster-address"

    def cluster_address(self) -> str | None:
        """The Dask scheduler's address, None while the embedded cluster starts; a
        RuntimeError if it did not start."""
        if self.address is None and self.cluster is not None:
            if self._address_file.exists():
                self.address = self._address_file.read_text().strip()
            elif self.cluster.poll() is not None or time.monotonic() > self._cluster_deadline:
                raise RuntimeError("the embedded Dask cluster did not start (see "
                                   f"{self.store.state_dir / 'cluster.log'})")
        return self.address

    @property
    def ready(self) -> bool:
        """Whether a job submitted now starts at once on warm processes: the cluster is up
        (Dask) and every warm runner has made its warm-up run."""
        try:
            cluster = self.settings.backend != "dask" or self.cluster_address() is not None
        except RuntimeError:
            return False
        return cluster and (self.pool is None or self.pool.ready)

    def recover(self) -> None:
        """Queue again every job left ``running`` by a server that was stopped or killed,
        its surviving processes killed first (see the module's docstring)."""
        for row in self.store.jobs(state="running"):
            path = self.store.job_dir(row["id"])
            if row["pid"] and _is_job_process(row["pid"], path):
                _kill_group(row["pid"], signal.SIGKILL)
                _wait_gone(row["pid"])
            if not path.is_dir():
                self.store.update(row["id"], state="failed", finished=time.time(), pid=None,
                                  reason="the server restarted and the job's directory "
                                  f"{path} is gone")
                continue
            resume = has_checkpoint(path)
            reason = (f"the server restarted; resumed from its checkpoint after "
                      f"{supersteps_done(path)} superstep(s)" if resume else
                      "the server restarted before its first checkpoint; started afresh")
            self.store.update(row["id"], state="queued", pid=None, resume=int(resume),
                              reason=reason)
            log.warning("job %s: %s", row["id"], reason)

    # supervision --------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.wake.wait(self.settings.poll)
            self.wake.clear()
            if self._stop.is_set():
                return
            try:
                self.step()
            except Exception:  # keep supervising; the error is the operator's to see
                log.exception("supervisor round failed")

    def step(self) -> None:
        """One round: record the jobs that ended, enforce wall times, start queued jobs."""
        for job_id, proc in list(self.procs.items()):
            code = proc.poll()
            if code is None:
                self._enforce_wall_time(job_id, proc)
            else:
                del self.procs[job_id]
                self._finish(job_id, code)
        if self.pool is not None:
            self.pool.maintain()
        self._start_queued()

    def _enforce_wall_time(self, job_id: str, proc: subprocess.Popen) -> None:
        row = self.store.job(job_id)
        token = self.store.token(row["owner"]) if row else None
        if row is None or token is None or token.wall_time is None or not row["started"]:
            return
        ran = time.time() - row["started"]
        if ran > token.wall_time and row["stop_reason"] is None:
            (self.store.job_dir(job_id) / "cancel").touch()
            self.store.update(job_id, stop_reason=f"wall-time limit of {token.wall_time:g} s "
                              "exceeded")
        elif ran > token.wall_time + self.settings.grace:
            _kill_group(proc.pid, signal.SIGKILL)

    def _finish(self, job_id: str, code: int) -> None:
        row = self.store.job(job_id)
        path = self.store.job_dir(job_id)
        ended, result_status = outcome(path, code)
        reason = None
        if row["stop_reason"] and ended != "finished":
            state = "cancelled"
            reason = row["stop_reason"] + ("" if ended == "cancelled" else
                                           f"; killed {self.settings.grace:g} s after the "
                                           "stop request")
        elif ended == "cancelled":
            state, reason = "cancelled", "cancelled by request"
        elif ended == "finished" and result_status == "converged":
            state, reason = "succeeded", row["reason"]  # a restart's note, if any
        else:
            state = "failed"
            reason = _failure(path, code, result_status)
        self.store.update(job_id, state=state, reason=reason, finished=time.time(),
                          exit_status=code, result_status=result_status,
                          headline=_title(path) if result_status is not None else None)
        log.info("job %s: %s%s", job_id, state, f" ({reason})" if reason else "")

    def _start_queued(self) -> None:
        running = self.store.jobs(state="running")
        if len(running) >= self.settings.max_running:
            return
        per_owner: dict[str, int] = {}
        for row in running:
            per_owner[row["owner"]] = per_owner.get(row["owner"], 0) + 1
        for row in reversed(self.store.jobs(state="queued")):  # oldest first
            if len(running) >= self.settings.max_running:
                return
            token = self.store.token(row["owner"])
            if token and token.max_jobs and per_owner.get(row["owner"], 0) >= token.max_jobs:
                continue
            if self._launch(row):
                running.append(row)
                per_owner[row["owner"]] = per_owner.get(row["owner"], 0) + 1

    def _launch(self, row: dict) -> bool:
        job_id = row["id"]
        if self.settings.backend == "dask" and self.cluster_address() is None:
            return False  # the embedded cluster is starting
        warm = self.pool.idle() if self.pool is not None else None
        if self.pool is not None and warm is None:
            return False  # every runner busy or starting
        if not self.store.update(job_id, only_if="queued", state="running",
                                 started=time.time(), finished=None, stop_reason=None,
                                 exit_status=None, result_status=None, headline=None):
            return False  # cancelled meanwhile
        path = self.store.job_dir(job_id)
        (path / "output").mkdir(parents=True, exist_ok=True)
        for previous in (path / "output" / "result.json", path / PICTURE_NAMES,
                         path / PICTURE_INPUT):  # a previous run's
            previous.unlink(missing_ok=True)
        backend, launcher = self._backend(job_id, row["scheme"])
        command = run_command(path, row["scheme"], json.loads(row["argv"]), backend,
                              resume=bool(row["resume"]), launcher=launcher)
        if warm is not None:
            self.procs[job_id] = warm.run(path, command)
            self.store.update(job_id, pid=warm.proc.pid)
            return True
        with open(path / "log.txt", "ab") as out:
            try:
                proc = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=out,
                                        stderr=subprocess.STDOUT, start_new_session=True,
                                        cwd=path, env=_job_environment())
            except OSError as exc:
                self.store.update(job_id, state="failed", finished=time.time(),
                                  reason=f"cannot start {command[0]}: {exc.strerror or exc}")
                return False
        lower_priority(proc.pid)
        self.procs[job_id] = proc
        self.store.update(job_id, pid=proc.pid)
        return True

    def _backend(self, job_id: str, scheme: str) -> tuple[list[str], list[str] | None]:
        """The backend options of a job's command line and its launcher (mpirun) if any."""
        if self.settings.backend == "serial" or (self.settings.backend == "dask"
                                                 and scheme in SERIAL_ON_DASK):
            return ["--backend", "serial"], None
        if self.settings.backend == "mpi":
            mpirun = Path(sys.executable).with_name("mpirun")
            return [], [str(mpirun) if mpirun.exists() else "mpirun", "-n",
                        str(self.settings.workers)]
        assert self.address is not None
        return dask_options(self.address, job_id, dispatch=self.dispatch), None

    @property
    def dispatch(self) -> str:
        """How Dask jobs hand their chunks to the workers: ``direct`` on the embedded
        cluster (its workers on this host), through the scheduler (``tasks``) on another."""
        return "tasks" if self.settings.scheduler else "direct"


def _job_environment() -> dict[str, str]:
    """A job's (and the embedded cluster's) environment: one BLAS/OpenMP thread, progress
    lines unbuffered."""
    from ocpar.bsp.dask import WORKER_ENV

    return {**os.environ, **WORKER_ENV, "PYTHONUNBUFFERED": "1"}


def _title(path: Path) -> str | None:
    """The headline of the job's result (``result.json``'s title), if it has one."""
    try:
        title = json.loads((path / "output" / "result.json").read_text()).get("title")
    except (OSError, ValueError, AttributeError):
        return None
    return title if isinstance(title, str) else None


def _failure(path: Path, code: int, result_status: str | None) -> str:
    """Why a run failed: its result's status and message, else its log's last line."""
    if result_status is not None:
        try:
            message = json.loads((path / "output" / "result.json").read_text()).get("message")
        except (OSError, ValueError):
            message = None
        return f"result status {result_status}" + (f": {message}" if message else "")
    lines = []
    if (path / "log.txt").exists():
        lines = [line.strip() for line in (path / "log.txt").read_text(
            errors="replace").splitlines() if line.strip()]
    last = lines[-1] if lines else "no output"
    how = f"killed by signal {-code}" if code < 0 else f"exit status {code}"
    return f"{how}: {last}"[:500]


def _is_job_process(pid: int, path: Path) -> bool:
    """Whether process ``pid`` lives and runs the job in ``path`` (not a reused pid): its
    command line names the job's directory, or it is a warm runner of this server's state
    directory."""
    try:
        command = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return False
    warm = command.split("\0")[1:4] == ["-m", "ocpar.service.web.warm",
                                        str(path.parent.parent)]
    return str(path) in command or warm


def _kill_group(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, sig)


def _wait_gone(pid: int, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(pid, 0)
        except (ProcessLookupError, PermissionError):
            return
        time.sleep(0.05)
