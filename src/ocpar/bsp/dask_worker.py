"""What runs inside a Dask worker process: the chunk runner and the plugin that lets the
coordinator call it directly over Dask's comm layer (``dispatch="direct"``, see
:mod:`ocpar.bsp.dask`).

:class:`ChunkHandler` is a worker plugin: registered once by a client, it is installed on every
worker of the cluster, present and future (a worker that replaces a lost one gets it when it
registers with the scheduler). It adds the comm handler :data:`CHUNK_OP` to the worker, which
runs a chunk in the worker's task thread (never in its event loop, which keeps serving the
scheduler meanwhile; one thread, so still one solve at a time per process, queued with any
Dask tasks), and it warms that thread and the malloc settings when the worker joins, so that
the first superstep costs what the others do. The handler adds no reach to the worker: a
worker already runs any function a peer that passed its TLS handshake sends (its ``run``
handler).
"""

from __future__ import annotations

import asyncio
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin
from distributed.protocol import ToPickle

from ocpar.bsp.columns import Columns
from ocpar.bsp.kernel import ChunkResult, run_packed_chunk
from ocpar.bsp.malloc import keep_solver_workspaces_on_heap

#: Name of the comm handler (the message's ``op``) that runs a chunk.
CHUNK_OP = "ocpar_run_chunk"


def run_chunk_in_worker(name: str, tasks: Columns | list[Any]) -> ChunkResult:
    """:func:`~ocpar.bsp.kernel.run_packed_chunk` on a Dask worker, with malloc tuned for
    IPOPT first (see :mod:`ocpar.bsp.malloc`: Dask's ``MALLOC_TRIM_THRESHOLD_`` costs ~30% per
    small solve)."""
    keep_solver_workspaces_on_heap()
    return run_packed_chunk(name, tasks)


class ChunkHandler(WorkerPlugin):
    """Worker plugin adding the :data:`CHUNK_OP` handler (module docstring). Idempotent: jobs
    sharing a cluster register it under one name, and the workers keep the first."""

    name = "ocpar-chunk-handler"
    idempotent = True

    async def setup(self, worker: Any) -> None:
        self._worker = worker
        worker.handlers[CHUNK_OP] = self.run_chunk
        # start the task thread and tune malloc now, not in the first superstep
        await asyncio.get_running_loop().run_in_executor(
            worker.executors["default"], keep_solver_workspaces_on_heap)

    def teardown(self, worker: Any) -> None:
        worker.handlers.pop(CHUNK_OP, None)

    async def run_chunk(self, name: str, tasks: Columns | list[Any]) -> ToPickle:
        """The handler: :func:`run_chunk_in_worker` in the worker's task thread; the
        :class:`~ocpar.bsp.kernel.ChunkResult` goes back pickled (out-of-band buffers)."""
        result = await asyncio.get_running_loop().run_in_executor(
            self._worker.executors["default"], run_chunk_in_worker, name, tasks)
        return ToPickle(result)
