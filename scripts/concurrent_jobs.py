#!/usr/bin/env python
"""Many jobs of all three schemes at once on one shared Dask cluster, each against its direct
run (issue 40: jobs sharing a cluster sometimes failed or came back with another round's
results).

    python scripts/concurrent_jobs.py --path serve --batches 10 --jobs 20 --tokens 4 --load 2 \\
        --output runs/concurrent-serve
    python scripts/concurrent_jobs.py --path serve submit --jobs 50 --tokens 5 --load 2 \\
        --output runs/concurrent-50
    python scripts/concurrent_jobs.py --path submit --stealing --mix small --output DIR

Runs ``--batches`` consecutive batches of ``--jobs`` jobs, job k of a batch running entry
k mod len(mix) of the mix (``--mix issue``: the 60-agent formation at 12, 24, 36, 48 and 60
agents, ``macs-goddard`` with max_evals 1500 and seeds 1 and 2, ``pursuit-case1`` with its
default finish; ``--mix small``: the small configurations of tests/test_web_service.py), from
``--tokens`` clients (job k from client k mod T), on each ``--path``:

* ``serve``: a real ``python -m ocpar serve`` on its default backend, the embedded Dask cluster
  of ``--workers`` workers (work stealing off, as ocpar starts it), ``--max-running`` jobs at
  once, one token per client (``--max-jobs`` running at once each); every batch's jobs are
  POSTed at once (one thread each) and followed through :class:`ocpar.service.http_client.Server`;
* ``submit``: a real ``dask scheduler`` and ``workers/start-dask-worker.sh`` workers on
  127.0.0.1 (``DASK_DISTRIBUTED__SCHEDULER__WORK_STEALING=False`` as docs/clusters.md
  recommends; ``--stealing`` leaves it on, which exercises the replay of a moved chunk's
  agents), each client submitting its jobs one after another with ``ocpar submit --scheduler``
  (no tokens on this path), followed and fetched through :mod:`ocpar.service.client`.

Meanwhile ``--load K`` processes burn CPU. Every job's result is compared with its direct run
(``ocpar run`` of the same configuration, serially, once per configuration before the
batches): result.json without the fields that say where and how long it ran (:data:`RUNTIME`)
and the array file's variables bit for bit. Per batch: jobs, succeeded, failed (with the
reason and the tail of the job's log), mismatched (with the differing fields), and the latency
from submission to the final state (p50/p95; the final state's time is the server's or the
job's ``state.json``'s). Writes ``concurrent_jobs.json`` (the machine, the load, the command,
every batch and every job) and ``concurrent_jobs.png`` (per batch: failures and mismatches,
latency percentiles). The functions that start a server or a cluster, submit, wait and compare
are used by ``tests/test_concurrent_jobs.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ocpar.result_files import RUNTIME_FIELDS

REPO = Path(__file__).resolve().parents[1]
PATHS = ("serve", "submit")
#: Fields of result.json that say where and how long a run ran, not what it computed.
RUNTIME = RUNTIME_FIELDS

#: What the jobs run: requests as ``POST /jobs`` takes them (``config``: an example's name or
#: the keys of a TOML configuration; ``set``: keys as ``ocpar run --set``).
MIXES: dict[str, list[dict]] = {
    # issue 40's batch: formation-60 at 12...60 agents, MACS goddard with max_evals 1500,
    # pursuit-case1 with its default finish (9097 supersteps, ~20 s serially)
    "issue": [
        {"config": "formation-60", "set": {"agents": 12}},
        {"config": "formation-60", "set": {"agents": 24}},
        {"config": "macs-goddard", "set": {"max_evals": 1500, "seed": 1}},
        {"config": "formation-60", "set": {"agents": 36}},
        {"config": "formation-60", "set": {"agents": 48}},
        {"config": "pursuit-case1", "set": {}},
        {"config": "formation-60", "set": {}},
        {"config": "macs-goddard", "set": {"max_evals": 1500, "seed": 2}},
    ],
    # tests/test_web_service.py's five: a few seconds each
    "small": [
        {"config": "formation-60", "set": {"agents": 8}},
        {"config": {"scheme": "formation", "agents": 10, "radius": 5.0, "outer": "sqp"},
         "set": {}},
        {"config": "formation-60", "set": {"agents": 12, "ordering": "keep"}},
        {"config": "macs-goddard", "set": {"max_evals": 120, "seed": 1}},
        {"config": "pursuit-case1", "set": {"samples": 31, "window": 10, "update": 5,
                                           "max_agents": 20}},
    ],
}


# --- configurations and their direct runs ------------------------------------------------------

def label(request: dict) -> str:
    """A short name of a request: ``formation-60 agents=12``."""
    config = request["config"]
    name = config if isinstance(config, str) else "{" + " ".join(
        f"{k}={v}" for k, v in config.items()) + "}"
    return " ".join([name, *(f"{k}={v}" for k, v in request.get("set", {}).items())])


def slug(request: dict) -> str:
    """``label`` as a file name."""
    return re.sub(r"[^A-Za-z0-9.=-]+", "_", label(request)).strip("_")


def toml_value(value: Any) -> str:
    return str(value).lower() if isinstance(value, bool) else json.dumps(value)


def command_config(request: dict, configs: Path) -> list[str]:
    """The request as ``CONFIG [--set KEY=VALUE ...]`` of ``ocpar run`` / ``ocpar submit``
    (a configuration given by its keys is written as a TOML file into ``configs``)."""
    config = request["config"]
    if isinstance(config, dict):
        configs.mkdir(parents=True, exist_ok=True)
        path = configs / f"{slug(request)}.toml"
        path.write_text("".join(f"{k} = {toml_value(v)}\n" for k, v in config.items()))
        config = str(path)
    sets = [f"{k}={toml_value(v)}" for k, v in request.get("set", {}).items()]
    return [config, *(["--set", *sets] if sets else [])]


def job_environment() -> dict[str, str]:
    """The environment of every process started here: one BLAS/OpenMP thread."""
    return dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                MKL_NUM_THREADS="1")


def direct_run(request: dict, out: Path, timeout: float = 3600) -> float:
    """``ocpar run`` of ``request`` serially into ``out``; returns its wall time in s (a
    RuntimeError with its output if it fails)."""
    config = command_config(request, out.parent / "configs")
    sets = config[2:] if len(config) > 1 else []
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "ocpar", "run", config[0], "--set", *sets,
                           f"output={out}", "quiet=true"], capture_output=True, text=True,
                          timeout=timeout, env=job_environment())
    if proc.returncode != 0:
        raise RuntimeError(f"ocpar run {label(request)}: exit {proc.returncode}\n"
                           f"{proc.stdout[-2000:]}{proc.stderr[-4000:]}")
    return time.perf_counter() - start


def direct_runs(mix: list[dict], directory: Path) -> dict[str, dict]:
    """Each configuration of ``mix`` run directly once (serially, one after another) into
    ``directory/SLUG``: ``{label: {"dir", "wall_s"}}``."""
    runs = {}
    for request in mix:
        out = directory / slug(request)
        shutil.rmtree(out, ignore_errors=True)
        runs[label(request)] = {"dir": str(out), "wall_s": direct_run(request, out)}
    return runs


def differences(got: Path, expected: Path) -> list[str]:
    """What differs between two runs' output directories: the fields of result.json
    outside :data:`RUNTIME`, and the array file's variables (names, dtypes, shapes and bits;
    its attributes carry run-time figures and are not compared). Empty: the same results."""
    import ocpar

    a = json.loads((got / "result.json").read_text())
    b = json.loads((expected / "result.json").read_text())
    diffs = [f"result.json {key}: {a.get(key)!r:.80} != {b.get(key)!r:.80}"
             for key in sorted((set(a) | set(b)) - RUNTIME) if a.get(key) != b.get(key)]
    if not (got / b.get("arrays", "result.nc")).exists():
        return [*diffs, f"no array file {b.get('arrays')}"]
    x, y = ocpar.load(got).dataset, ocpar.load(expected).dataset
    if sorted(x.variables) != sorted(y.variables):
        return [*diffs, f"array variables {sorted(x.variables)} != {sorted(y.variables)}"]
    for name in y.variables:
        u, v = x[name].values, y[name].values
        if u.dtype != v.dtype or u.shape != v.shape:
            diffs.append(f"array {name}: {u.dtype}{u.shape} != {v.dtype}{v.shape}")
        elif (u.tolist() != v.tolist()) if u.dtype.kind == "O" else (u.tobytes() != v.tobytes()):
            diffs.append(f"array {name}: bits differ")
    return diffs


# --- the load --------------------------------------------------------------------------------

@contextlib.contextmanager
def cpu_load(count: int) -> Iterator[list[int]]:
    """``count`` processes that burn CPU until the block ends; yields their pids."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                              stdin=subprocess.DEVNULL) for _ in range(count)]
    try:
        yield [proc.pid for proc in procs]
    finally:
        stop_processes(procs)


def stop_processes(procs: list[subprocess.Popen], timeout: float = 30) -> None:
    """Terminate ``procs`` (last started first), killing any that hang."""
    for proc in reversed(procs):
        if proc.poll() is None:
            proc.terminate()
    for proc in procs:
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


# --- the two paths' servers --------------------------------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def issue_tokens(state_dir: Path, count: int, max_jobs: int | None) -> dict[str, str]:
    """``count`` tokens ``t0``, ``t1``, ... of the server in ``state_dir`` (created), each
    with at most ``max_jobs`` jobs running at once: ``{name: token}``."""
    from ocpar.service.web.store import Store, Token
    from ocpar.service.web.tokens import issue

    state_dir.mkdir(parents=True, exist_ok=True)
    store = Store(state_dir)
    return {f"t{k}": issue(store, Token(f"t{k}", max_jobs=max_jobs)) for k in range(count)}


@contextlib.contextmanager
def ocpar_serve(state_dir: Path, *options: str, timeout: float = 180) -> Iterator[str]:
    """``python -m ocpar serve OPTIONS`` on a free port of 127.0.0.1 with its state in
    ``state_dir`` (its output in ``state_dir/../server.log``); yields its URL once it
    answers, and stops it (SIGTERM) at the end."""
    import httpx

    state_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log_path = state_dir.parent / "server.log"
    with open(log_path, "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "ocpar", "serve", "--port", str(port),
                                 "--state-dir", str(state_dir), *options],
                                stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                env=job_environment())
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                if httpx.get(url + "/openapi.json", timeout=5).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ocpar serve did not start:\n{log_path.read_text()[-3000:]}")
            time.sleep(0.3)
        yield url
    finally:
        stop_processes([proc], timeout=90)


@contextlib.contextmanager
def dask_cluster(jobs_dir: Path, workers: int = 2, stealing: bool = False,
                 timeout: float = 120) -> Iterator[str]:
    """A real ``dask scheduler`` (keeping its jobs in ``jobs_dir``; work stealing off unless
    ``stealing``) and ``workers`` single-threaded workers from
    ``workers/start-dask-worker.sh`` on 127.0.0.1, as tests/conftest.py's ``local_cluster``
    starts them; yields the scheduler's address. Their output goes to
    ``jobs_dir/../cluster.log``."""
    from distributed import Client

    jobs_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = Path(sys.executable).with_name("dask")
    env = dict(job_environment(), OCPAR_JOBS_DIR=str(jobs_dir),
               DASK_DISTRIBUTED__SCHEDULER__WORK_STEALING=str(stealing),
               PATH=f"{dask.parent}{os.pathsep}{os.environ.get('PATH', '')}")
    procs = []
    with open(jobs_dir.parent / "cluster.log", "ab") as log:
        procs.append(subprocess.Popen([str(dask), "scheduler", "--host", "127.0.0.1",
                                       "--port", str(port), "--no-dashboard"], env=env,
                                      stdin=subprocess.DEVNULL, stdout=log, stderr=log))
        try:
            deadline = time.monotonic() + timeout
            while True:
                try:
                    with socket.create_connection(("127.0.0.1", port), timeout=1):
                        break
                except OSError:
                    if procs[0].poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError("dask scheduler did not start") from None
                    time.sleep(0.2)
            procs.append(subprocess.Popen([str(REPO / "workers" / "start-dask-worker.sh"),
                                           address, str(workers)], env=env,
                                          stdin=subprocess.DEVNULL, stdout=log, stderr=log))
            with Client(address, timeout="30s") as client:
                client.wait_for_workers(workers, timeout=timeout)
            yield address
        finally:
            stop_processes(procs)


# --- one batch ---------------------------------------------------------------------------------

@dataclass
class Job:
    """One job of a batch and how it ended."""

    index: int
    client: str
    config: str                       # the request's label
    job: str | None = None            # its id (None: not submitted)
    submitted: float = 0.0            # epoch s, when its submission began
    state: str = "pending"            # succeeded, failed, cancelled, timeout, refused
    reason: str | None = None
    finished: float | None = None     # epoch s of its final state
    latency_s: float | None = None
    equal: bool | None = None         # its result equals its direct run's
    differences: list[str] = field(default_factory=list)
    log_tail: list[str] = field(default_factory=list)


def log_tail(path: Path, lines: int = 25) -> list[str]:
    """The last ``lines`` lines of a job's log (where a traceback ends)."""
    try:
        return path.read_text(errors="replace").splitlines()[-lines:]
    except OSError:
        return []


def _epoch(text: str | None) -> float | None:
    if not text:
        return None
    return datetime.datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def _check(job: Job, fetch: Callable[[], Path], direct: dict[str, dict], keep: bool) -> None:
    """Fetch a succeeded job's output (``fetch()`` returns its directory) and compare it
    with its direct run; a fetch that fails counts as a mismatch, saying why."""
    try:
        fetched = fetch()
        job.differences = differences(fetched, Path(direct[job.config]["dir"]))
    except Exception as exc:  # recorded as the job's difference
        job.differences = [f"cannot fetch or read its output: {type(exc).__name__}: {exc}"]
        fetched = None
    job.equal = not job.differences
    if job.equal and not keep and fetched is not None:
        shutil.rmtree(fetched, ignore_errors=True)


def serve_batch(url: str, tokens: dict[str, str], requests: list[dict], state_dir: Path,
                direct: dict[str, dict], fetch_dir: Path, timeout: float = 3600,
                keep: bool = False, poll: float = 1.0) -> list[Job]:
    """POST ``requests`` at once (one thread each; request k by token k mod len(tokens)) to
    the server at ``url`` (its state in ``state_dir``), wait until every job is in a final
    state (or ``timeout`` s passed), fetch each succeeded job's result.json and array file
    into ``fetch_dir`` and compare them with its direct run (``direct``, by label)."""
    from ocpar.service.http_client import FINAL_STATES, Server, ServiceError

    names = list(tokens)
    jobs = [Job(k, names[k % len(names)], label(r)) for k, r in enumerate(requests)]

    def submit(job: Job, request: dict) -> None:
        job.submitted = time.time()
        try:
            with Server(url, tokens[job.client], timeout_s=120) as server:
                job.job = server.submit(request["config"], request.get("set"))["id"]
        except ServiceError as exc:
            job.state, job.reason = "refused", str(exc)

    threads = [threading.Thread(target=submit, args=(job, request))
               for job, request in zip(jobs, requests, strict=True)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    servers = {name: Server(url, token, timeout_s=120) for name, token in tokens.items()}

    def fetch(server: Server, job: Job) -> Path:
        out = fetch_dir / job.job
        out.mkdir(parents=True, exist_ok=True)
        server.download(job.job, "result.json", out / "result.json")
        arrays = json.loads((out / "result.json").read_text()).get("arrays")
        if arrays:
            server.download(job.job, arrays, out / arrays)
        return out

    try:
        waiting = {job.job: job for job in jobs if job.job is not None}
        deadline = time.monotonic() + timeout
        while waiting:
            for server in servers.values():
                try:
                    records = server.list_jobs()
                except ServiceError:  # a busy server: ask again in the next round
                    continue
                for record in records:
                    job = waiting.get(record["id"])
                    if job is None or record["state"] not in FINAL_STATES:
                        continue
                    del waiting[record["id"]]
                    job.state, job.reason = record["state"], record["reason"]
                    job.finished = _epoch(record["finished"])
                    job.latency_s = job.finished - job.submitted
                    if job.state != "succeeded":
                        job.log_tail = log_tail(state_dir / "jobs" / job.job / "log.txt")
                        continue
                    _check(job, lambda server=server, job=job: fetch(server, job), direct,
                           keep)
            if waiting and time.monotonic() > deadline:
                for job in waiting.values():
                    job.state = "timeout"
                    job.reason = f"no final state after {timeout:g} s"
                    job.log_tail = log_tail(state_dir / "jobs" / job.job / "log.txt")
                break
            time.sleep(poll)
    finally:
        for server in servers.values():
            server.close()
    return jobs


def submit_batch(address: str, clients: int, requests: list[dict], jobs_dir: Path,
                 direct: dict[str, dict], fetch_dir: Path, timeout: float = 3600,
                 keep: bool = False, poll: float = 1.0) -> list[Job]:
    """Submit ``requests`` with ``ocpar submit CONFIG --scheduler ADDRESS`` from ``clients``
    threads at once (request k from client k mod ``clients``, each client's one after
    another), wait until every job is in a final state (the scheduler keeps them in
    ``jobs_dir``) or ``timeout`` s passed, fetch each finished job's files through the
    scheduler (as ``ocpar result``) into ``fetch_dir`` and compare them with its direct run."""
    from ocpar.service import client as dask_client

    jobs = [Job(k, f"c{k % clients}", label(r)) for k, r in enumerate(requests)]
    configs = fetch_dir.parent / "configs"

    commands = [[sys.executable, "-m", "ocpar", "submit", *command_config(request, configs),
                 "--scheduler", address] for request in requests]

    def submit_all(mine: list[tuple[Job, list[str]]]) -> None:
        for job, command in mine:
            job.submitted = time.time()
            proc = subprocess.run(command, capture_output=True, text=True, timeout=600,
                                  env=job_environment())
            if proc.returncode == 0:
                job.job = proc.stdout.strip()
            else:
                job.state = "refused"
                job.reason = f"ocpar submit: exit {proc.returncode}: {proc.stderr.strip()}"

    pairs = list(zip(jobs, commands, strict=True))
    threads = [threading.Thread(target=submit_all, args=(pairs[c::clients],))
               for c in range(clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    def fetch(job: Job) -> Path:
        out = fetch_dir / job.job
        dask_client.result(job.job, address, out)  # what ocpar result fetches
        return out

    waiting = {job.job: job for job in jobs if job.job is not None}
    deadline = time.monotonic() + timeout
    while waiting:
        try:
            records = dask_client.list_jobs(address)
        except dask_client.ServiceError:  # a busy scheduler: ask again in the next round
            records = []
        for record in records:
            job = waiting.get(record["id"])
            if job is None:
                continue
            if record["state"] == "queued" and "Traceback" in "\n".join(
                    tail := log_tail(jobs_dir / job.job / "log.txt")):
                # its coordinator writes "running" first: this one died before it could
                del waiting[record["id"]]
                job.state, job.log_tail = "failed", tail
                job.reason = f"its coordinator died before it started: {record['progress']}"
                continue
            if record["state"] not in ("finished", "failed", "cancelled"):
                continue
            del waiting[record["id"]]
            job.finished = record["time"]
            job.latency_s = job.finished - job.submitted
            converged = record["state"] == "finished" and record.get("result_status") == \
                "converged"
            job.state = "succeeded" if converged else (
                "failed" if record["state"] == "finished" else record["state"])
            if not converged:
                job.reason = (f"result status {record.get('result_status')}"
                              if record["state"] == "finished" else
                              f"exit status {record.get('exit_status')}: {record['progress']}")
                job.log_tail = log_tail(jobs_dir / job.job / "log.txt")
                continue
            _check(job, lambda job=job: fetch(job), direct, keep)
        if waiting and time.monotonic() > deadline:
            for job in waiting.values():
                job.state = "timeout"
                job.reason = f"no final state after {timeout:g} s"
                job.log_tail = log_tail(jobs_dir / job.job / "log.txt")
            break
        time.sleep(poll)
    return jobs


def batch_requests(mix: list[dict], count: int) -> list[dict]:
    """The ``count`` requests of a batch: job k runs ``mix[k mod len(mix)]``."""
    return [mix[k % len(mix)] for k in range(count)]


def summarise(jobs: list[Job], wall_s: float) -> dict:
    """A batch's figures: jobs, succeeded, failed (with reasons), mismatched, latency
    percentiles, wall time."""
    latencies = [job.latency_s for job in jobs if job.latency_s is not None]
    failed = [job for job in jobs if job.state != "succeeded"]
    mismatched = [job for job in jobs if job.equal is False]
    return {
        "jobs": len(jobs),
        "succeeded": sum(job.state == "succeeded" for job in jobs),
        "failed": len(failed),
        "failures": [{"job": j.job, "config": j.config, "state": j.state, "reason": j.reason,
                      "log_tail": j.log_tail} for j in failed],
        "mismatched": len(mismatched),
        "mismatches": [{"job": j.job, "config": j.config, "differences": j.differences}
                       for j in mismatched],
        "equal": sum(job.equal is True for job in jobs),
        "latency_p50_s": float(np.percentile(latencies, 50)) if latencies else None,
        "latency_p95_s": float(np.percentile(latencies, 95)) if latencies else None,
        "latency_max_s": max(latencies) if latencies else None,
        "wall_s": wall_s,
    }


def latency_text(figures: dict) -> str:
    if figures["latency_p50_s"] is None:
        return "no latency"
    return (f"latency p50 {figures['latency_p50_s']:.1f} s p95 "
            f"{figures['latency_p95_s']:.1f} s")


def mem_available_gb() -> float | None:
    """The memory available to new processes (GB), if /proc says."""
    with contextlib.suppress(OSError, StopIteration):
        return int(next(line for line in Path("/proc/meminfo").read_text().splitlines()
                        if line.startswith("MemAvailable:")).split()[1]) / 2**20
    return None


@contextlib.contextmanager
def lowest_memory(every_s: float = 1.0) -> Iterator[list[float]]:
    """Samples :func:`mem_available_gb` every ``every_s`` s while the block runs; the
    yielded list holds the lowest sample (empty if none)."""
    lowest: list[float] = []
    stop = threading.Event()

    def sample() -> None:
        while True:
            value = mem_available_gb()
            if value is not None and (not lowest or value < lowest[0]):
                lowest[:] = [value]
            if stop.wait(every_s):
                return

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield lowest
    finally:
        stop.set()
        thread.join()


def run_batches(path: str, mix: list[dict], direct: dict[str, dict], workdir: Path, *,
                batches: int = 1, jobs: int = 20, tokens: int = 4, workers: int = 2,
                max_running: int = 4, max_jobs: int | None = 2, stealing: bool = False,
                timeout: float = 3600, keep: bool = False,
                report: Any = None) -> dict:
    """``batches`` consecutive batches of ``jobs`` jobs of ``mix`` from ``tokens`` clients on
    ``path`` (``serve`` or ``submit``, see the module's docstring; one server or cluster for
    all batches, its files in ``workdir``), each job compared with its direct run
    (``direct``: :func:`direct_runs` of ``mix``). Returns ``{"settings", "batches": [{...,
    "job_records": [...]}], "totals"}``; ``report(text)`` is called after each batch."""
    workdir.mkdir(parents=True, exist_ok=True)
    settings = {"path": path, "batches": batches, "jobs": jobs, "tokens": tokens,
                "workers": workers}
    if path == "serve":
        settings |= {"max_running": max_running, "max_jobs_per_token": max_jobs,
                     "work_stealing": False}
        state = workdir / "state"
        names = issue_tokens(state, tokens, max_jobs)
        context = ocpar_serve(state, "--workers", str(workers), "--max-running",
                              str(max_running))
    elif path == "submit":
        settings |= {"work_stealing": stealing}
        context = dask_cluster(workdir / "jobs", workers, stealing)
    else:
        raise ValueError(f"unknown path {path!r}; choose one of {', '.join(PATHS)}")
    results = []
    started = time.perf_counter()
    with context as where:
        for b in range(batches):
            requests = batch_requests(mix, jobs)
            load_before = os.getloadavg()
            t0 = time.perf_counter()
            fetch = workdir / f"batch-{b}"
            with lowest_memory() as memory:
                if path == "serve":
                    done = serve_batch(where, names, requests, workdir / "state", direct,
                                       fetch, timeout, keep)
                else:
                    done = submit_batch(where, tokens, requests, workdir / "jobs", direct,
                                        fetch, timeout, keep)
            figures = summarise(done, time.perf_counter() - t0)
            figures |= {"batch": b, "loadavg_before": load_before,
                        "lowest_mem_available_gb": memory[0] if memory else None,
                        "loadavg_after": os.getloadavg(),
                        "job_records": [asdict(job) for job in done]}
            results.append(figures)
            if report is not None:
                report(f"{path} batch {b}: {figures['succeeded']}/{figures['jobs']} succeeded, "
                       f"{figures['failed']} failed, {figures['mismatched']} mismatched, "
                       f"{latency_text(figures)}, wall {figures['wall_s']:.0f} s")
    every = [Job(**r) for b in results for r in b["job_records"]]
    totals = summarise(every, time.perf_counter() - started)
    totals["batches"] = batches
    for key in ("failures", "mismatches"):
        totals[key] = [item for b in results for item in b[key]]
    return {"settings": settings, "batches": results, "totals": totals}


# --- the report --------------------------------------------------------------------------------

def machine() -> dict:
    """What ran it: host, CPU, cores, memory, Python, the checkout's commit."""
    cpu = ""
    with contextlib.suppress(OSError):
        cpu = next((line.split(":", 1)[1].strip() for line in
                    Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name")), "")
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    total = None
    with contextlib.suppress(OSError, StopIteration):
        total = int(next(line for line in Path("/proc/meminfo").read_text().splitlines()
                         if line.startswith("MemTotal:")).split()[1]) / 2**20
    return {"host": platform.node(), "platform": platform.platform(), "cpu": cpu,
            "cores": os.cpu_count(), "memory_gb": total, "python": platform.python_version(),
            "commit": commit, "loadavg": os.getloadavg()}


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = list(report["paths"])
    fig, axes = plt.subplots(len(paths), 2, figsize=(11, 3.4 * len(paths)), squeeze=False)
    for row, name in enumerate(paths):
        batches = report["paths"][name]["batches"]
        x = np.arange(len(batches))
        ax = axes[row][0]
        ax.bar(x - 0.2, [b["failed"] for b in batches], 0.4, color="tab:red", label="failed")
        ax.bar(x + 0.2, [b["mismatched"] for b in batches], 0.4, color="tab:orange",
               label="mismatched")
        ax.set_ylim(0, max([1, *(b["jobs"] for b in batches)]))
        ax.set_xticks(x)
        ax.set_xlabel("batch")
        ax.set_ylabel(f"jobs of {batches[0]['jobs'] if batches else 0}")
        total = report["paths"][name]["totals"]
        ax.set_title(f"{name}: {total['failed']} failed, {total['mismatched']} mismatched of "
                     f"{total['jobs']}")
        ax.legend(loc="upper right")
        ax = axes[row][1]
        for key, style in (("latency_p50_s", "o-"), ("latency_p95_s", "s--"),
                           ("latency_max_s", "^:")):
            ax.plot(x, [b[key] if b[key] is not None else np.nan for b in batches], style,
                    label=key.removeprefix("latency_").removesuffix("_s"))
        ax.set_xticks(x)
        ax.set_xlabel("batch")
        ax.set_ylabel("submit → final state (s)")
        ax.set_ylim(bottom=0)
        ax.set_title(f"{name}: latency (load {report['load']} burning processes)")
        ax.legend()
    fig.suptitle(f"{report['mix']} mix, {report['machine']['cores']} cores", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--path", nargs="+", choices=PATHS, default=["serve"],
                        help="serve: ocpar serve on its embedded cluster; submit: ocpar submit "
                             "--scheduler to a dask scheduler and workers (default serve)")
    parser.add_argument("--batches", type=int, default=1, help="consecutive batches")
    parser.add_argument("--jobs", type=int, default=20, help="jobs per batch")
    parser.add_argument("--tokens", type=int, default=4,
                        help="clients submitting at once (serve: one token each)")
    parser.add_argument("--mix", choices=sorted(MIXES), default="issue",
                        help="the configurations (default issue; small: for tests)")
    parser.add_argument("--load", type=int, default=0, metavar="K",
                        help="CPU-burning processes kept running during the batches")
    parser.add_argument("--workers", type=int, default=2, help="Dask workers (default 2)")
    parser.add_argument("--max-running", type=int, default=4,
                        help="serve: jobs running at once (default 4)")
    parser.add_argument("--max-jobs", type=int, default=2,
                        help="serve: each token's jobs running at once (default 2; 0: no "
                             "limit)")
    parser.add_argument("--stealing", action="store_true",
                        help="submit: leave the scheduler's work stealing on")
    parser.add_argument("--timeout", type=float, default=3600,
                        help="s a batch's jobs may take before they count as failed")
    parser.add_argument("--keep", action="store_true",
                        help="keep the fetched outputs of jobs equal to their direct runs")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)

    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    mix = MIXES[args.mix]
    report: dict[str, Any] = {
        "command": shlex.join(["python", "scripts/concurrent_jobs.py", *argv]),
        "machine": machine(), "load": args.load, "mix": args.mix,
        "configurations": [label(r) for r in mix], "started": time.time(),
    }
    print(f"direct runs of {len(mix)} configurations ...", flush=True)
    direct = direct_runs(mix, out / "direct")
    report["direct"] = {name: {"wall_s": run["wall_s"]} for name, run in direct.items()}
    report["paths"] = {}
    with cpu_load(args.load):
        for path in args.path:
            report["paths"][path] = run_batches(
                path, mix, direct, out / path, batches=args.batches, jobs=args.jobs,
                tokens=args.tokens, workers=args.workers, max_running=args.max_running,
                max_jobs=args.max_jobs or None, stealing=args.stealing,
                timeout=args.timeout, keep=args.keep, report=lambda s: print(s, flush=True))
            report["machine"]["loadavg_end"] = os.getloadavg()
            (out / "concurrent_jobs.json").write_text(json.dumps(report, indent=1))
    report["wall_s"] = time.time() - report["started"]
    (out / "concurrent_jobs.json").write_text(json.dumps(report, indent=1))
    plot(report, out / "concurrent_jobs.png")
    bad = 0
    for path, result in report["paths"].items():
        t = result["totals"]
        bad += t["failed"] + t["mismatched"]
        print(f"{path}: {t['batches']} x {result['settings']['jobs']} jobs, {t['failed']} "
              f"failed, {t['mismatched']} mismatched, {latency_text(t)}, "
              f"wall {t['wall_s']:.0f} s")
        for failure in t["failures"]:
            print(f"  failed {failure['job']} ({failure['config']}): {failure['reason']}")
        for mismatch in t["mismatches"]:
            print(f"  mismatched {mismatch['job']} ({mismatch['config']}): "
                  f"{'; '.join(mismatch['differences'][:3])}")
    print(f"wrote {out / 'concurrent_jobs.json'}, {out / 'concurrent_jobs.png'}")
    return 1 if bad else 0


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # stop the load and servers too
    sys.exit(main())
