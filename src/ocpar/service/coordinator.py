"""The detached coordinator of one job: ``python -m ocpar.service.coordinator JOB_DIR``.

Runs ``python -m ocpar.<scheme>`` with the job's options against the cluster's scheduler,
checkpointing into ``JOB_DIR/checkpoint``, writing ``JOB_DIR/output``, stopping at a
superstep boundary once ``JOB_DIR/cancel`` exists, its tasks named after the job on the
dashboard; records the job's state before and after (see :mod:`ocpar.service.jobs`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from ocpar.service.jobs import log_last_line, outcome, run_command, write_state


def dask_options(scheduler: str, job_id: str, tls: dict | None = None,
                 dispatch: str = "tasks") -> list[str]:
    """The backend options of a job's run on the cluster at ``scheduler``: its tasks go
    through the scheduler, named after the job (``dispatch`` ``direct``: straight to the
    workers, which must be reachable from here); ``tls``: the certificate files it
    presents."""
    return ["--backend", "dask", "--scheduler", scheduler, "--dispatch", dispatch,
            "--job-name", job_id,
            *(arg for name, path in (tls or {}).items()
              for arg in ("--" + name.replace("_", "-"), path))]


def command(path: Path, job: dict) -> list[str]:
    """The scheme's command line for the job in ``path``."""
    return run_command(path, job["scheme"], job["argv"],
                       dask_options(job["scheduler"], job["id"], job.get("tls")))


def main(argv: list[str] | None = None) -> int:
    path = Path((argv if argv is not None else sys.argv[1:])[0]).resolve()
    job = json.loads((path / "job.json").read_text())
    write_state(path, "running", pid=os.getpid())
    with open(path / "log.txt", "ab") as log:
        status = subprocess.run(command(path, job), stdout=log, stderr=log,
                                stdin=subprocess.DEVNULL).returncode
    state, result_status = outcome(path, status)
    details = ({"result_status": result_status} if state == "finished" else
               {"reason": f"exit status {status}; {log_last_line(path)}"} if state == "failed"
               else {})
    write_state(path, state, exit_status=status, **details)
    return 0


if __name__ == "__main__":
    sys.exit(main())
