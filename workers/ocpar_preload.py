"""Dask worker preload: import ocpar and build the default DMOC solver before the first task.

    dask worker tcp://SCHEDULER:8786 --nthreads 1 --preload /path/to/workers/ocpar_preload.py

Importing ocpar pins BLAS/OpenMP to one thread in this process (unless already set); malloc is
tuned for IPOPT's workspaces (see ``ocpar.bsp.malloc``). Building the 60-point-mass formation's
inner solver here takes it out of the first superstep's time.
"""

from __future__ import annotations

import logging

# importing ocpar sets one BLAS/OpenMP thread per process; the formation's worker side
# (its resident kernel) is imported now, not in the first superstep
import ocpar.formation.outer_step  # noqa: F401
from ocpar.bsp.malloc import keep_solver_workspaces_on_heap
from ocpar.examples.formation_point_masses import make as point_masses
from ocpar.ocp import dmoc_problem

logger = logging.getLogger("ocpar.preload")


def dask_setup(worker) -> None:
    """Called by ``dask worker --preload`` once the worker starts."""
    keep_solver_workspaces_on_heap()
    shape = point_masses(agents=2).shape
    dmoc_problem(shape).solver  # noqa: B018  (builds and caches the IPOPT solver)
    logger.info("ocpar preload: DMOC solver for %s built on %s", shape, worker.address)
