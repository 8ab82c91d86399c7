"""What runs inside a Dask worker process: the chunk runner, and the plugin that gives each
worker a :class:`~ocpar.bsp.channel.ChannelServer` the coordinator calls directly
(``dispatch="direct"``, see :mod:`ocpar.bsp.dask`).

:class:`ChunkChannel` is a worker plugin: registered once by a client, it is installed on every
worker of the cluster, present and future (a worker that replaces a lost one gets it when it
registers with the scheduler). It starts the worker's channel server on the worker's own host
(with the worker's TLS server context on a ``tls://`` cluster, so a peer needs a certificate
the cluster's CA signed, as for the worker's Dask port) and adds the comm handler
:data:`ADDRESS_OP`, through which a coordinator learns the channel's address. The channel adds
no reach to the worker: a worker already runs any function a peer that passed its TLS
handshake sends (its ``run`` handler).

Chunks run under :data:`~ocpar.bsp.channel.SOLVE_LOCK`, whichever way they arrive (the channel,
or a Dask task with ``dispatch="tasks"``), so a process makes one solver call at a time even
when several jobs share the cluster.
"""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from ocpar.bsp.channel import SOLVE_LOCK, ChannelServer
from ocpar.bsp.columns import Columns
from ocpar.bsp.kernel import ChunkResult, run_packed_chunk
from ocpar.bsp.malloc import keep_solver_workspaces_on_heap

#: Name of the comm handler (the message's ``op``) that answers the channel's address.
ADDRESS_OP = "ocpar_channel_address"


def run_chunk_in_worker(name: str, tasks: Columns | list[Any]) -> ChunkResult:
    """:func:`~ocpar.bsp.kernel.run_packed_chunk` on a Dask worker, with malloc tuned for
    IPOPT first (see :mod:`ocpar.bsp.malloc`: Dask's ``MALLOC_TRIM_THRESHOLD_`` costs ~30% per
    small solve)."""
    keep_solver_workspaces_on_heap()
    return run_packed_chunk(name, tasks)


def run_chunk_as_task(name: str, tasks: Columns | list[Any]) -> ChunkResult:
    """:func:`run_chunk_in_worker` as a Dask task (``dispatch="tasks"``), under
    :data:`~ocpar.bsp.channel.SOLVE_LOCK` (the channel's requests hold it already)."""
    with SOLVE_LOCK:
        return run_chunk_in_worker(name, tasks)


class ChunkChannel(WorkerPlugin):
    """Worker plugin starting the worker's channel server (module docstring). Idempotent: jobs
    sharing a cluster register it under one name, and the workers keep the first."""

    name = "ocpar-chunk-channel"
    idempotent = True

    def setup(self, worker: Any) -> None:
        protocol, _, location = worker.address.partition("://")
        host = location.rsplit(":", 1)[0].strip("[]")
        context = (worker.security.get_listen_args("worker").get("ssl_context")
                   if protocol == "tls" else None)
        self._server = ChannelServer(host, context)
        worker.handlers[ADDRESS_OP] = self.address
        keep_solver_workspaces_on_heap()  # malloc tuned now, not in the first superstep

    def teardown(self, worker: Any) -> None:
        worker.handlers.pop(ADDRESS_OP, None)
        self._server.close()

    def address(self) -> tuple[str, int]:
        """The handler: the channel's (host, port)."""
        return self._server.address
