"""The Dask backend on an MPI allocation (``mpirun -n P python -m ocpar.<scheme> --backend
dask-mpi``), through dask-mpi: rank 0 runs the scheduler, rank 1 the coordinator (the
scheme's outer loop, a Dask client) and ranks 2 … P−1 one single-threaded worker each, so
P ranks give P − 2 workers. Scheduler and worker ranks never return: they exit when the
coordinator's client closes.
"""

from __future__ import annotations

from ocpar.bsp.backend import BackendError
from ocpar.bsp.dask import CLUSTER_CONFIG, DaskBackend


def open_dask_mpi(workers: int | None = None, balance: str = "blocks") -> DaskBackend:
    """Turn this MPI job into a Dask cluster and return the coordinator's backend (rank 1).
    ``workers``, if given, must equal the number of worker ranks (P − 2)."""
    import logging

    import dask
    from dask_mpi import initialize
    from mpi4py import MPI

    size = MPI.COMM_WORLD.Get_size()
    if size < 3:
        raise BackendError(f"--backend dask-mpi needs mpirun -n P with P >= 3 (scheduler, "
                           f"coordinator, workers), got {size} ranks")
    if workers is not None and workers != size - 2:
        raise BackendError(f"--workers {workers} but mpirun -n {size} gives {size - 2} "
                           "dask-mpi workers (P - 2)")
    # the scheduler and worker ranks share the job's stderr and never return from initialize:
    # silence their logs (their connections closing at shutdown are expected); the
    # coordinator rank gets its level back
    logger = logging.getLogger("distributed")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    with dask.config.set(CLUSTER_CONFIG):
        initialize(nthreads=1, dashboard_address=":0", memory_limit=0)
    logger.setLevel(level)
    return DaskBackend(workers=size - 2, scheduler=dask.config.get("scheduler_address"),
                       balance=balance)
