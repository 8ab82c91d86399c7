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

from ocpar.cli import EXIT_CANCELLED
from ocpar.results import EXIT_STATUS
from ocpar.service.jobs import write_state

#: Exit statuses of a run that ended with its result.json (every status but cancelled).
FINISHED = frozenset(code for status, code in EXIT_STATUS.items() if status != "cancelled")


def command(path: Path, job: dict) -> list[str]:
    """The scheme's command line for the job in ``path``."""
    return [sys.executable, "-m", f"ocpar.{job['scheme']}", *job["argv"],
            "--backend", "dask", "--scheduler", job["scheduler"],
            "--checkpoint", str(path / "checkpoint"), "--output", str(path / "output"),
            "--stop-file", str(path / "cancel"), "--dispatch", "tasks",
            "--job-name", job["id"],
            *(arg for name, path in (job.get("tls") or {}).items()
              for arg in ("--" + name.replace("_", "-"), path))]


def main(argv: list[str] | None = None) -> int:
    path = Path((argv if argv is not None else sys.argv[1:])[0]).resolve()
    job = json.loads((path / "job.json").read_text())
    write_state(path, "running", pid=os.getpid())
    with open(path / "log.txt", "ab") as log:
        status = subprocess.run(command(path, job), stdout=log, stderr=log,
                                stdin=subprocess.DEVNULL).returncode
    result = path / "output" / "result.json"
    if status == EXIT_CANCELLED:
        write_state(path, "cancelled", exit_status=status)
    elif result.exists() and status in FINISHED:
        outcome = json.loads(result.read_text()).get("status")
        write_state(path, "finished", exit_status=status, result_status=outcome)
    else:
        write_state(path, "failed", exit_status=status)
    return 0


if __name__ == "__main__":
    sys.exit(main())
