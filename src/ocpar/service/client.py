"""The Python API behind ``ocpar submit|jobs|status|result|cancel``: talk to a Dask cluster's
scheduler, which keeps the jobs (:mod:`ocpar.service.jobs`). Every function takes
``security``, this client's :class:`distributed.Security` (e.g. from
:func:`ocpar.bsp.dask.tls_security`), for a cluster secured with TLS.

>>> job = submit("formation", ["--agents", "60"], "tcp://HOST:8786")    # doctest: +SKIP
>>> status(job, "tcp://HOST:8786")["state"]                             # doctest: +SKIP
'running'
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from ocpar import driver
from ocpar.config import SCHEMES, scheme_class
from ocpar.references import is_reference
from ocpar.service import jobs
from ocpar.service.check import check_and_start

#: Options of a scheme's command line that the service sets for a submitted job.
SERVICE_OPTIONS = ("--backend", "--scheduler", "--output", "--checkpoint", "--resume",
                   "--stop-file", "--dispatch", "--job-name", "--tls-ca-file", "--tls-cert",
                   "--tls-key")
T = TypeVar("T")


class ServiceError(RuntimeError):
    """The scheduler cannot be reached, or refused the request (one-line message)."""


def on_scheduler(scheduler: str, function: Callable[..., T], *args: Any,
                 security: Any = None, timeout_s: float = 10.0) -> T:
    """Run ``function(*args)`` in the scheduler's process of the cluster at ``scheduler``
    (``security``: this client's :class:`distributed.Security` for a ``tls://`` one)."""
    from ocpar.bsp.backend import BackendError
    from ocpar.bsp.dask import connect_client

    try:
        client = connect_client(scheduler, security, timeout_s)
    except BackendError as exc:
        raise ServiceError(str(exc)) from None
    with client:
        try:
            return client.run_on_scheduler(function, *args)
        except jobs.JobError as exc:
            raise ServiceError(str(exc)) from None


def checked_id(job_id: str) -> str:
    """``job_id`` if it is one (checked here, before the scheduler is asked); a
    ServiceError with one line otherwise."""
    try:
        return jobs.check_job_id(job_id)
    except jobs.JobError as exc:
        raise ServiceError(str(exc)) from None


def check_run(scheme: str, argv: list[str]) -> driver.SchemeRun:
    """Validate the scheme's options as its command line would (raises SystemExit(2) with a
    one-line message on bad input), before anything is sent to the cluster; returns them."""
    if scheme not in SCHEMES:
        raise ServiceError(f"unknown scheme {scheme!r}; choose one of {', '.join(SCHEMES)}")
    given = {arg.split("=", 1)[0] for arg in argv}
    for option in SERVICE_OPTIONS:
        if option in given:
            raise ServiceError(f"{option} is set by the service for a submitted job; leave "
                               "it out")
    options, _ = driver.parse_options(scheme_class(scheme),
                                      [*argv, "--backend", "dask", "--scheduler", "tcp://host:1"])
    return options


def submit(scheme: str, argv: list[str], scheduler: str, security: Any = None) -> str:
    """Start ``python -m ocpar.<scheme> argv`` as a detached job on the cluster at
    ``scheduler`` (its coordinator runs on the scheduler's host, and on a ``tls://`` cluster
    presents the scheduler's certificate); returns the job id at once. A
    ``package.module:factory`` problem is loaded on the scheduler's host first, where the
    job's coordinator loads it (:func:`ocpar.service.check.check_and_start`): one that does not
    load is a ServiceError and no job."""
    options = check_run(scheme, argv)
    start = check_and_start if is_reference(options.problem) else jobs.create_and_start
    return on_scheduler(scheduler, start, scheme, list(argv), scheduler, security=security)


def list_jobs(scheduler: str, security: Any = None) -> list[dict]:
    """Every job of the cluster with its state (see :func:`ocpar.service.jobs.job_status`)."""
    return on_scheduler(scheduler, jobs.list_jobs, security=security)


def status(job_id: str, scheduler: str, security: Any = None) -> dict:
    """One job's state, supersteps done and last progress line."""
    checked_id(job_id)
    return on_scheduler(scheduler, jobs.job_status, job_id, security=security)


def result(job_id: str, scheduler: str, output: str | Path,
           security: Any = None) -> list[Path]:
    """Fetch a finished job's ``result.json`` and plots into ``output``; returns the paths."""
    checked_id(job_id)
    files = on_scheduler(scheduler, jobs.result_files, job_id, security=security)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, data in files.items():
        (out / name).write_bytes(data)
        paths.append(out / name)
    return paths


def cancel(job_id: str, scheduler: str, security: Any = None) -> dict:
    """Ask a job to stop at its next superstep boundary (its checkpoint stays)."""
    checked_id(job_id)
    return on_scheduler(scheduler, jobs.cancel, job_id, security=security)
