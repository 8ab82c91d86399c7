"""The superstep engine: a coordinator hands independent tasks to workers, one superstep at a
time, and gets the results back in task order.

>>> from ocpar.bsp import open_backend
>>> with open_backend("serial") as backend:
...     backend.superstep("math:sqrt", [4.0, 9.0])
[2.0, 3.0]

Backends: ``serial`` (in process), ``mpi`` (SPMD under ``mpirun``), ``dask`` (embedded
``LocalCluster`` or an existing scheduler), ``dask-mpi`` (a Dask cluster made of the ranks of
an MPI allocation). Every superstep is timed (:class:`SuperstepTrace`). Agents whose state
carries over from one superstep to the next keep it on the workers (:class:`ResidentSet`,
:meth:`Backend.resident`; see :mod:`ocpar.bsp.resident`).
"""

from __future__ import annotations

from ocpar.bsp.backend import (
    BALANCE_POLICIES,
    Backend,
    BackendError,
    RunCancelled,
    UnreadableRequest,
    check_balance,
)
from ocpar.bsp.kernel import ChunkResult, kernel_name, run_chunk
from ocpar.bsp.mpi import SUPERSTEP_TIMEOUT_S, launched_by_mpirun
from ocpar.bsp.partition import contiguous_blocks
from ocpar.bsp.resident import ResidentSet
from ocpar.bsp.trace import SuperstepTrace

BACKENDS = ("serial", "mpi", "dask", "dask-mpi")


def open_backend(
    name: str, workers: int | None = None, scheduler: str | None = None,
    balance: str = "blocks", security: object = None,
    superstep_timeout_s: float = SUPERSTEP_TIMEOUT_S, dispatch: str = "direct",
    run_name: str | None = None,
) -> Backend:
    """Start the backend ``name`` with ``workers`` workers and the ``balance`` policy
    (``blocks`` or ``lpt``, see :data:`BALANCE_POLICIES`).

    ``serial`` ignores ``workers``; ``mpi`` takes its size from the MPI launcher (``workers``,
    if given, must match); ``dask`` starts ``workers`` local worker processes (default 1), or
    connects to ``scheduler`` and uses ``workers`` of its workers (default all); ``dask-mpi``
    (under ``mpirun -n P``, P ≥ 3) makes rank 0 a Dask scheduler, ranks 2… workers and returns
    in rank 1 only, as the coordinator (see :mod:`ocpar.bsp.dask_mpi`).

    ``superstep_timeout_s`` (``mpi``, ``dask``): a superstep whose results have not all arrived
    by then ends the run with a message instead of waiting forever. ``dispatch`` and
    ``run_name`` (``dask``): how chunks reach workers (``direct`` or ``tasks``, see
    :mod:`ocpar.bsp.dask`) and the name the tasks' keys start with. ``security`` (``dask``
    only): a :class:`distributed.Security` with the TLS certificates
    for a ``tls://`` scheduler, or for an embedded cluster that then uses TLS (see
    ``workers/tls.md`` and :func:`ocpar.bsp.dask.tls_security`).
    """
    check_balance(balance)  # before dask-mpi turns ranks into a scheduler and workers
    if security is not None and name != "dask":
        raise BackendError(f"TLS certificates only apply to the dask backend, not {name}")
    if name == "serial":
        from ocpar.bsp.serial import SerialBackend

        return SerialBackend(balance=balance)
    if name == "mpi":
        from ocpar.bsp.mpi import MpiBackend

        backend = MpiBackend(balance=balance, timeout_s=superstep_timeout_s)
        if workers is not None and workers != backend.workers:
            raise BackendError(f"--workers {workers} but mpirun started {backend.workers} ranks")
        return backend
    if name == "dask":
        from ocpar.bsp.dask import DaskBackend

        return DaskBackend(workers=workers, scheduler=scheduler, balance=balance,
                           security=security, superstep_timeout_s=superstep_timeout_s,
                           dispatch=dispatch, run_name=run_name)
    if name == "dask-mpi":
        from ocpar.bsp.dask_mpi import open_dask_mpi

        return open_dask_mpi(workers=workers, balance=balance)
    raise BackendError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")


__all__ = [
    "BACKENDS",
    "BALANCE_POLICIES",
    "Backend",
    "BackendError",
    "ChunkResult",
    "ResidentSet",
    "RunCancelled",
    "SuperstepTrace",
    "UnreadableRequest",
    "contiguous_blocks",
    "kernel_name",
    "launched_by_mpirun",
    "open_backend",
    "run_chunk",
]
