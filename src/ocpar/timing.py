"""Where a run's time goes: the ``timings`` of ``result.json`` and the last progress line.

Every run's result carries, in seconds (:data:`PHASES`, in the order they happen):

* ``startup_s``: from the process's start to the driver's first step (the interpreter and
  the imports; under ``mpirun`` the coordinator rank's own, not the launcher's);
* ``build_s``: checking the options, loading the problem and starting the backend (an
  embedded Dask cluster's start is here);
* ``solve_s``: the solve, every superstep included (the result's ``wall_time_s``; a
  worker's first superstep also builds its inner solvers);
* ``verification_s``: checking the returned answer (:mod:`ocpar.formation.verify`, a pursuit
  trajectory's dynamics and constraints, a MACS front's re-simulation);
* ``files_s``: writing the array file and the trace (the summary's own writing excluded);
* ``picture_s``: drawing the plots;
* ``total_s``: the process's age when the summary was last written.

A warm runner of ``ocpar serve`` (:mod:`ocpar.service.web.warm`) runs many jobs in one
process: it calls :func:`restart_process_clock` as it takes each, so that ``startup_s`` and
``total_s`` count from the job's start, not the process's.

A scheme fills ``verification_s`` (and may add a phase of its own, e.g. a reference solve);
the driver (:mod:`ocpar.driver`) measures the others. ``startup_s`` and ``total_s`` need the
process's start time, which Linux gives (``/proc``); elsewhere they are omitted.
"""

from __future__ import annotations

import os
import time

#: The phases of a run, in order (module docstring).
PHASES = ("startup_s", "build_s", "solve_s", "verification_s", "files_s", "picture_s")
#: Their names in the progress line.
WORDS = {"startup_s": "start-up", "build_s": "build", "solve_s": "solve",
         "verification_s": "verification", "files_s": "files", "picture_s": "picture",
         "reference_s": "reference solve", "total_s": "total"}


_restarted: list[float] = []  # CLOCK_BOOTTIME of the last restart_process_clock()


def restart_process_clock() -> None:
    """Count :func:`process_age` from now on (a warm process that takes a new job)."""
    _restarted[:] = [time.clock_gettime(time.CLOCK_BOOTTIME)]


def process_age() -> float | None:
    """Seconds since this process started (Linux: its start time in ``/proc/self/stat``
    against the boot clock, to 1/CLK_TCK s), or since :func:`restart_process_clock`; None
    where the system does not say."""
    if _restarted:
        return max(time.clock_gettime(time.CLOCK_BOOTTIME) - _restarted[0], 0.0)
    try:
        with open("/proc/self/stat", "rb") as stat:
            fields = stat.read().rsplit(b")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: starttime
        return max(time.clock_gettime(time.CLOCK_BOOTTIME) - started, 0.0)
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def timings_line(timings: dict[str, float | None]) -> str:
    """The progress line of ``timings``: 'timings: start-up 0.62 s, build 0.10 s, ...,
    total 2.97 s' (phases not measured left out)."""
    parts = [f"{WORDS.get(key, key.removesuffix('_s'))} {value:.2f} s"
             for key, value in timings.items() if value is not None and key != "total_s"]
    total = timings.get("total_s")
    return "timings: " + ", ".join(parts) + (f"; total {total:.2f} s" if total is not None
                                             else "")
