"""A job's memory, estimated before it starts, and the server's limit on it.

:func:`estimate` gives the peak resident set of a job's largest process from its scheme and
problem size: a process's base (the interpreter, CasADi, the scheme's solvers) and a cost
per unit of size, both measured on serial runs (one process holds everything: an upper bound
for a process of a distributed run) by ``scripts/job_memory.py`` on this project's machine
(Linux, x86-64, Python 3.11):

* formation: 111 MiB at 2 agents, 128 MiB at 10,000 and 238 MiB at 40,000 (3.8 KB per
  agent; on ``mpirun -n 2`` 1,000,000 agents peak at 2.6 GB in the largest process);
* pursuit (orbit transfer, N_Δ = 60): 172 MiB at N = 301 samples, 204 MiB at 1,201 and 247
  MiB at 2,401 (linear: 36 KB per sample);
* MACS (Goddard): 191 MiB at 100, 2,000 and 8,000 evaluations alike.

Each model lies at most 20% above these measurements (the tests check it).

``ocpar serve --max-job-memory GB`` refuses a job whose estimate is above it (HTTP 422,
naming both); the default is half of the host's physical memory.
"""

from __future__ import annotations

import os
from typing import Any

from ocpar.references import is_reference

MB = 1 << 20
#: Per scheme: (base bytes, bytes per unit, the unit's name); see the module's docstring.
MODEL = {"formation": (112 * MB, 3_900, "agents"),
         "pursuit": (164 * MB, 37_000, "samples"),
         "macs": (200 * MB, 0, "evaluations")}


def host_memory() -> int:
    """The host's physical memory (bytes)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def default_limit() -> int:
    """The default of ``ocpar serve --max-job-memory``: half of :func:`host_memory`."""
    return host_memory() // 2


def size(scheme: str, options: Any, problem: Any = None) -> int | None:
    """The units of :data:`MODEL` a run of ``options`` has (formation agents, pursuit
    samples, MACS evaluations), from the options or else the loaded ``problem``; None if
    neither says yet."""
    if scheme == "formation":
        agents = getattr(options, "agents", None)
        return agents if agents is not None else getattr(problem, "agents", None)
    if scheme == "pursuit":
        if problem is not None:
            return getattr(problem, "samples", None)
        return None if is_reference(options.problem) else options.samples
    return getattr(options, "max_evals", None)


def estimate(scheme: str, units: int) -> int:
    """The peak bytes of a job of ``scheme`` of ``units`` (see :func:`size`)."""
    base, per_unit, _ = MODEL[scheme]
    return base + per_unit * units


def check(scheme: str, options: Any, problem: Any, limit: int | None) -> None:
    """Nothing if the job's estimate is within ``limit`` bytes (or either is unknown); a
    ValueError of one line naming the estimate and the limit otherwise."""
    units = size(scheme, options, problem)
    if limit is None or units is None:
        return
    need = estimate(scheme, units)
    if need > limit:
        raise ValueError(f"memory: a {scheme} job of {units:,} {MODEL[scheme][2]} needs about "
                         f"{gigabytes(need)} at its peak, above this server's limit of "
                         f"{gigabytes(limit)} per job (ocpar serve --max-job-memory)")


def gigabytes(count: int) -> str:
    """``count`` bytes in GB (10⁹), to 2 significant figures at least."""
    return f"{count / 1e9:.3g} GB"
