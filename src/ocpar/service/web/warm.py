"""Warm runners of ``ocpar serve``: processes that have imported ocpar, the three schemes and
Distributed once, and run the server's jobs one at a time, in process.

A runner is ``python -m ocpar.service.web.warm STATE_DIR ROLE ...`` (:func:`main`), a process
group of its own, started by the server (:class:`WarmPool`, as many as jobs may run at once,
and one that draws their plots), warmed up by a small run on the server's backend
(:func:`warm_up`) before it says it is ready. It reads one
request per line on its standard input (the job's directory and the scheme's command line
of :func:`ocpar.service.jobs.run_command`), runs it as ``python -m ocpar.<scheme>`` would
(:func:`ocpar.driver.run_scheme`: the same checkpoint, output, stop file and exit status),
its file descriptors 1 and 2 (Python's, IPOPT's) on the job's ``log.txt`` and its working
directory the job's, and answers ``{"exit": STATUS}`` on a line. It draws no plot: it keeps
the result for the drawing runner (:func:`keep_for_picture`, :func:`draw`;
:mod:`ocpar.service.web.figures`). Its client of the cluster's
scheduler is connected by the first job and kept for the next ones
(:func:`ocpar.bsp.dask.keep_clients`); the inner solvers stay cached on the workers as for
any run.

Isolation: a job that crashes its runner (a segfault, ``os._exit``, an out-of-memory kill,
the wall-time kill) ends that process only; the server records the job ``failed`` (or
``cancelled``) with the exit status and the log's last line, as for a job of its own process,
and starts a new runner in its place. A runner ends when the server that started it is gone
(its standard input closes, or its parent changes), so no run of a killed server writes on.
What one job leaves in a runner's process (imported user modules, caches) the next sees:
the operator restarts the server to load changed problem modules.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import pickle
import subprocess
import sys
import threading
import time
import traceback
import warnings
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import IO, Any

log = logging.getLogger("ocpar.serve")

#: Jobs a runner runs before the pool replaces it (bounds what jobs leave in a process).
JOBS_PER_RUNNER = 200
#: A finished job's result, kept in its directory (beside ``output/``) for its plots, which
#: are drawn when first asked for (:func:`draw`), and the names of those plots (JSON list).
PICTURE_INPUT = "picture.pickle"
PICTURE_NAMES = "picture.json"
#: The niceness of every process that runs jobs (warm runners, the embedded cluster and its
#: workers, ``mpirun``): the server's own process, which answers the HTTP requests, comes
#: first on a machine its jobs keep busy.
JOB_NICENESS = 5
#: Seconds a runner has to start (imports) before the pool gives up on it and starts another.
START_TIMEOUT_S = 120.0


def lower_priority(group: int) -> None:
    """Give the process group ``group`` (and the processes it starts) :data:`JOB_NICENESS`."""
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PGRP, group, JOB_NICENESS)


class WarmJob:
    """A job running on a :class:`WarmRunner`: ``pid`` (the runner's, the leader of its
    process group) and :meth:`poll`, as :class:`subprocess.Popen` has them."""

    def __init__(self, runner: WarmRunner) -> None:
        self.runner = runner
        self.pid = runner.proc.pid
        self.code: int | None = None

    def poll(self) -> int | None:
        """The job's exit status (a crashed runner's: negative for a signal), None while it
        runs."""
        if self.code is None:
            self.code = self.runner.result(self)
        return self.code


class WarmRunner:
    """The server's side of one runner process."""

    def __init__(self, state_dir: Path, env: dict[str, str], wake: threading.Event,
                 role: list[str]) -> None:
        self.wake = wake
        self.started = time.monotonic()
        with open(state_dir / "runners.log", "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "ocpar.service.web.warm", str(state_dir), *role],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=out,
                start_new_session=True, env=env)
        lower_priority(self.proc.pid)
        self.ready = False
        self.jobs = 0
        self.job: WarmJob | None = None
        self._answers: list[int] = []
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True,
                                        name=f"ocpar-runner-{self.proc.pid}")
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            with self._lock:
                if message.get("ready"):
                    self.ready = True
                elif "exit" in message:
                    self._answers.append(int(message["exit"]))
            self.wake.set()
        self.wake.set()  # the runner is gone

    @property
    def idle(self) -> bool:
        """Started, alive and running no job."""
        return self.ready and self.job is None and self.proc.poll() is None

    @property
    def dead(self) -> bool:
        """Exited, or not ready within :data:`START_TIMEOUT_S`."""
        return self.proc.poll() is not None or (
            not self.ready and time.monotonic() - self.started > START_TIMEOUT_S)

    def run(self, path: Path, command: list[str], draw: bool = False) -> WarmJob:
        """Start the job in ``path`` whose command line (``python -m ocpar.SCHEME ...``) is
        ``command`` (``draw``: draw its plots instead, :func:`draw`)."""
        assert self.idle and command[1:2] == ["-m"]
        self.job = job = WarmJob(self)
        self.jobs += 1
        request = {"dir": str(path), "module": command[2], "argv": command[3:], "draw": draw}
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(json.dumps(request).encode() + b"\n")
            self.proc.stdin.flush()
        except OSError:
            pass  # the runner died: poll() says how
        return job

    def result(self, job: WarmJob) -> int | None:
        """``job``'s exit status once it ended (see :meth:`WarmJob.poll`)."""
        with self._lock:
            if self._answers:
                self.job = None
                return self._answers.pop(0)
        code = self.proc.poll()
        if code is None:
            return None
        self.proc.wait()
        self._reader.join(5)  # the rest of its output read
        with self._lock:  # an answer that came just before the exit
            self.job = None
            return self._answers.pop(0) if self._answers else code

    def stop(self) -> None:
        """End the runner (its standard input closed, then SIGTERM to its group)."""
        with contextlib.suppress(OSError):
            assert self.proc.stdin is not None
            self.proc.stdin.close()
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.proc.pid, 15)


class WarmPool:
    """``size`` warm runners for the jobs of the server whose state is in ``state_dir``, on
    its backend (``role``: ``["serial"]``, or ``["dask", ADDRESS_FILE]``), and one that
    draws their plots (:attr:`drawer`); :meth:`maintain` replaces those that died or ran
    :data:`JOBS_PER_RUNNER` jobs."""

    def __init__(self, state_dir: Path, size: int, env: dict[str, str],
                 wake: threading.Event, role: list[str]) -> None:
        self.state_dir, self.size, self.env, self.wake = state_dir, size, env, wake
        self.role = role
        self.runners: list[WarmRunner] = []
        self.drawer: WarmRunner | None = None

    @property
    def ready(self) -> bool:
        """Whether every runner (the drawer too) is warm and waiting or running a job."""
        return (len(self.runners) == self.size and self.drawer is not None
                and all(runner.ready and runner.proc.poll() is None
                        for runner in [*self.runners, self.drawer]))

    def maintain(self) -> None:
        """Drop the runners that are dead (or worn out and idle) and start new ones up to
        ``size``, and a drawer if it has none."""
        self.runners = self._kept(self.runners)
        while len(self.runners) < self.size:
            self.runners.append(WarmRunner(self.state_dir, self.env, self.wake, self.role))
        if not self._kept([self.drawer] if self.drawer else []):
            self.drawer = WarmRunner(self.state_dir, self.env, self.wake, ["draw"])

    def _kept(self, runners: list[WarmRunner]) -> list[WarmRunner]:
        """Those of ``runners`` that live on (the others stopped)."""
        kept = []
        for runner in runners:
            if runner.job is not None:
                kept.append(runner)  # its job's end is recorded first (poll)
            elif runner.dead or runner.jobs >= JOBS_PER_RUNNER:
                if runner.proc.poll() is None:
                    runner.stop()
                else:
                    runner.proc.wait()
                if runner.proc.returncode not in (None, 0, -15):
                    log.warning("warm runner %d ended with status %s", runner.proc.pid,
                                runner.proc.returncode)
            else:
                kept.append(runner)
        return kept

    def idle(self) -> WarmRunner | None:
        """A runner ready for a job, if any."""
        return next((runner for runner in self.runners if runner.idle), None)

    def stop(self) -> None:
        """End every runner (waiting up to 10 s each, then SIGKILL)."""
        everyone = [*self.runners, *([self.drawer] if self.drawer else [])]
        for runner in everyone:
            runner.stop()
        for runner in everyone:
            try:
                runner.proc.wait(10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(runner.proc.pid, 9)
                runner.proc.wait()
        self.runners, self.drawer = [], None


# the runner's process -----------------------------------------------------------------------

def _schemes() -> dict[str, Any]:
    """The options class of each scheme's module ``ocpar.<scheme>`` (imported now)."""
    from ocpar.config import SCHEMES, scheme_class

    return {f"ocpar.{scheme}": scheme_class(scheme) for scheme in SCHEMES}


#: The small run a runner makes before its first job (0.3 s to 1 s), on the server's backend.
WARM_UP = ("ocpar.formation", ["--agents", "12", "--quiet"])
#: Its name on the cluster's dashboard.
WARM_UP_JOB = "warm-up"


def warm_up(schemes: dict[str, Any], backend: list[str], drawer: bool) -> None:
    """Make the run :data:`WARM_UP` on ``backend`` (its command-line options) in a temporary
    directory, so that what a run imports, builds and connects to on its way (the cluster's
    client, the workers' inner solvers of that shape, the array file) is ready before the
    first job; a ``drawer`` draws its plots too (Matplotlib and its fonts). Its output goes
    to the runner's log."""
    import tempfile

    module, argv = WARM_UP
    with tempfile.TemporaryDirectory(prefix="ocpar-warm-") as tmp:
        request = {"dir": tmp, "module": module,
                   "argv": [*argv, *backend, "--output", f"{tmp}/output"]}
        if run_job(schemes, request) == 0 and drawer:
            run_job(schemes, {**request, "draw": True})


def run_job(schemes: dict[str, Any], request: dict[str, Any]) -> int:
    """Run one request in this process as ``python -m MODULE ARGV`` in the job's directory
    would, its output on the job's ``log.txt``; returns the exit status. Its plots are not
    drawn: the result is kept for :func:`draw` (:func:`keep_for_picture`). A request with
    ``"draw": true`` draws them instead (:func:`draw`, its output on the runner's log)."""
    from ocpar.driver import parse_options, run_scheme
    from ocpar.timing import restart_process_clock

    path = Path(request["dir"])
    drawing = bool(request.get("draw"))
    here = os.getcwd()
    saved = os.dup(1), os.dup(2)
    _flush()
    if not drawing:
        out = os.open(path / "log.txt", os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(out)
    sys.argv = [request["module"], *request["argv"]]
    try:
        os.chdir(path)
        restart_process_clock()
        with warnings.catch_warnings():  # each job says its warnings, as a process of its own
            warnings.onceregistry.clear()
            options, given = parse_options(schemes[request["module"]], request["argv"])
            if drawing:
                code: Any = draw(options, path)
            elif options.output is not None and options.picture != "none":
                code = run_scheme(replace(options, picture="none"), given,
                                  partial(keep_for_picture, path, options))
            else:
                code = run_scheme(options, given)
    except SystemExit as exc:
        code = exc.code
        if code is not None and not isinstance(code, int):
            print(code, file=sys.stderr)
            code = 1
    except BaseException:  # as the interpreter would end: the traceback, status 1
        traceback.print_exc()
        code = 1
    finally:
        _flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)
        os.chdir(here)
    return 0 if code is None else int(code)


def keep_for_picture(path: Path, options: Any, problem: Any, result: Any) -> None:
    """Keep the ``result`` of the job in ``path`` for its plots (:data:`PICTURE_INPUT`) and
    the plots' names (:data:`PICTURE_NAMES`, written last)."""
    for name, data in ((PICTURE_INPUT, pickle.dumps(result, pickle.HIGHEST_PROTOCOL)),
                       (PICTURE_NAMES, json.dumps(list(options.plot_names(result))).encode())):
        tmp = path / f".{name}.tmp"
        tmp.write_bytes(data)
        os.replace(tmp, path / name)


def draw(options: Any, path: Path) -> int:
    """Draw the plots of the job in ``path`` (whose options are ``options``) from the result
    :func:`keep_for_picture` kept, into its output directory; the exit status (0)."""
    from ocpar.driver import checked_problem

    with open(path / PICTURE_INPUT, "rb") as kept:
        result = pickle.load(kept)
    options.plot(checked_problem(options), result, Path(options.output))
    return 0


def _flush() -> None:
    """Flush Python's and C's standard streams (IPOPT prints through C's ``stdout``)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).fflush(None)


def _orphaned(parent: int) -> None:
    """End this process (at once, mid-job too) when the server that started it is gone."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(70)


def scheduler_address(address_file: Path) -> str:
    """The scheduler's address, once the server has written it into ``address_file``
    (SystemExit after :data:`START_TIMEOUT_S`)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while not address_file.exists():
        if time.monotonic() > deadline:
            raise SystemExit(f"no scheduler address in {address_file}")
        time.sleep(0.1)
    return address_file.read_text().strip()


def main(argv: list[str] | None = None) -> int:
    """The runner ``STATE_DIR ROLE [ADDRESS_FILE DISPATCH]`` (ROLE: ``serial`` or ``dask``,
    the backend of its jobs, whose scheduler's address is in ADDRESS_FILE and whose chunks go
    by DISPATCH; or ``draw``, the plots' runner): import, warm up, say ready, then run one
    request per line of standard input."""
    from ocpar.bsp.dask import keep_clients
    from ocpar.cli import freeze_objects_at_exit
    from ocpar.service.coordinator import dask_options

    role, *cluster = (argv if argv is not None else sys.argv[1:])[1:]
    replies: IO[str] = os.fdopen(os.dup(1), "w", buffering=1)
    # between jobs, descriptor 1 is the runner's log (stderr), never the reply channel
    os.dup2(2, 1)
    threading.Thread(target=_orphaned, args=(os.getppid(),), daemon=True).start()
    schemes = _schemes()
    import distributed  # noqa: F401  (the Dask backend's import, once)

    keep_clients()
    backend = (dask_options(scheduler_address(Path(cluster[0])), WARM_UP_JOB,
                            dispatch=cluster[1]) if role == "dask" else ["--backend", "serial"])
    warm_up(schemes, backend, drawer=role == "draw")
    freeze_objects_at_exit()
    print(json.dumps({"ready": True}), file=replies)
    for line in sys.stdin:
        if line.strip():
            try:
                code = run_job(schemes, json.loads(line))
            except Exception:  # e.g. the job's directory is gone: its log cannot be opened
                traceback.print_exc()
                code = 1
            print(json.dumps({"exit": code}), file=replies)
    return 0


if __name__ == "__main__":
    sys.exit(main())
