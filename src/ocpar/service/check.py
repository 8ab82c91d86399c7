"""A submitted job's problem loaded where the job will run, before the job exists.

``python -m ocpar.service.check SCHEME ARGV...`` loads the problem of ``python -m
ocpar.<scheme> ARGV`` as the run would (a ``package.module:factory`` imported and called, the
result checked against the scheme's problem type and options): one line on stderr and exit
status 2 if it does not load. :func:`check_and_start` runs it on a Dask cluster's scheduler
(``ocpar submit --scheduler``), whose host runs the job's coordinator.
"""

from __future__ import annotations

import asyncio
import subprocess
import sys
from typing import Any

from ocpar import driver
from ocpar.cli import fail
from ocpar.config import scheme_class
from ocpar.service.jobs import JobError, create_and_start, jobs_root

#: Seconds a submitted job's problem may take to load on the scheduler's host.
CHECK_TIMEOUT_S = 120.0


async def check_problem(scheme: str, argv: list[str]) -> None:
    """Load the problem of ``python -m ocpar.<scheme> argv`` in a separate process on this
    host (the scheduler's event loop runs on meanwhile); a JobError with its one-line cause
    if it does not load within :data:`CHECK_TIMEOUT_S`."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "ocpar.service.check", scheme, *argv,
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        cwd=jobs_root())  # as a job's coordinator: not in the scheduler's directory
    try:
        _, err = await asyncio.wait_for(proc.communicate(), CHECK_TIMEOUT_S)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise JobError(f"the problem did not load within {CHECK_TIMEOUT_S:g} s on the "
                       "scheduler's host") from None
    if proc.returncode != 0:
        lines = err.decode(errors="replace").strip().splitlines() or [
            f"exit status {proc.returncode}"]
        cause = lines[-1].partition(": error: ")[2] or lines[-1]  # without the "prog: error: "
        raise JobError(f"on the scheduler's host: {cause}")


async def check_and_start(scheme: str, argv: list[str], scheduler: str,
                          dask_scheduler: Any = None) -> str:
    """:func:`check_problem`, then :func:`ocpar.service.jobs.create_and_start` (runs in the
    scheduler's process); returns the job id."""
    await check_problem(scheme, argv)
    return create_and_start(scheme, argv, scheduler, dask_scheduler)


def main(argv: list[str] | None = None) -> int:
    """Load the problem of ``python -m ocpar.<scheme> ARGV`` (one line and exit status 2 if
    it does not load); 0."""
    scheme, *args = sys.argv[1:] if argv is None else argv
    options, _ = driver.parse_options(scheme_class(scheme), args)
    try:
        driver.checked_problem(options)
    except ValueError as exc:
        fail(options.prog, str(exc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
