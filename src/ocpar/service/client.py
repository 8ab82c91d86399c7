"""The Python API behind ``ocpar submit|jobs|status|result|cancel``: talk to a Dask cluster's
scheduler, which keeps the jobs (:mod:`ocpar.service.jobs`).

>>> job = submit("formation", ["--agents", "60"], "tcp://HOST:8786")    # doctest: +SKIP
>>> status(job, "tcp://HOST:8786")["state"]                             # doctest: +SKIP
'running'
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from ocpar.service import jobs

SCHEMES = ("formation", "pursuit", "macs")
T = TypeVar("T")


class ServiceError(RuntimeError):
    """The scheduler cannot be reached, or refused the request (one-line message)."""


def on_scheduler(scheduler: str, function: Callable[..., T], *args: Any,
                 timeout_s: float = 10.0) -> T:
    """Run ``function(*args)`` in the scheduler's process of the cluster at ``scheduler``."""
    from distributed import Client

    try:
        client = Client(scheduler, timeout=f"{timeout_s}s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise ServiceError(f"cannot reach Dask scheduler {scheduler}: {exc}") from None
    with client:
        try:
            return client.run_on_scheduler(function, *args)
        except jobs.JobError as exc:
            raise ServiceError(str(exc)) from None


def check_run(scheme: str, argv: list[str]) -> None:
    """Validate the scheme's options as its command line would (raises SystemExit(2) with a
    one-line message on bad input), before anything is sent to the cluster."""
    if scheme not in SCHEMES:
        raise ServiceError(f"unknown scheme {scheme!r}; choose one of {', '.join(SCHEMES)}")
    module = importlib.import_module(f"ocpar.{scheme}.__main__")
    args = module.parse_args([*argv, "--backend", "dask", "--scheduler", "tcp://host:1"])
    for option in ("output", "checkpoint", "resume", "stop_file", "job_name"):
        if getattr(args, option, None) is not None:
            raise ServiceError(f"--{option.replace('_', '-')} is set by the service for a "
                               "submitted job; leave it out")


def submit(scheme: str, argv: list[str], scheduler: str) -> str:
    """Start ``python -m ocpar.<scheme> argv`` as a detached job on the cluster at
    ``scheduler`` (its coordinator runs on the scheduler's host); returns the job id at once."""
    check_run(scheme, argv)
    return on_scheduler(scheduler, jobs.create_and_start, scheme, list(argv), scheduler)


def list_jobs(scheduler: str) -> list[dict]:
    """Every job of the cluster with its state (see :func:`ocpar.service.jobs.job_status`)."""
    return on_scheduler(scheduler, jobs.list_jobs)


def status(job_id: str, scheduler: str) -> dict:
    """One job's state, supersteps done and last progress line."""
    return on_scheduler(scheduler, jobs.job_status, job_id)


def result(job_id: str, scheduler: str, output: str | Path) -> list[Path]:
    """Fetch a finished job's ``result.json`` and plots into ``output``; returns the paths."""
    files = on_scheduler(scheduler, jobs.result_files, job_id)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, data in files.items():
        (out / name).write_bytes(data)
        paths.append(out / name)
    return paths


def cancel(job_id: str, scheduler: str) -> dict:
    """Ask a job to stop at its next superstep boundary (its checkpoint stays)."""
    return on_scheduler(scheduler, jobs.cancel, job_id)
