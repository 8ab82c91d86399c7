"""Dask backend: one chunk of tasks per worker per superstep, pinned to that worker.

With no scheduler address an embedded ``LocalCluster`` of single-threaded worker processes is
started; with ``scheduler="tcp://HOST:PORT"`` an existing cluster is used. Chunk w always goes
to the same worker, so each worker's solver cache stays warm.

Two ways to hand a chunk to its worker (``dispatch``):

* ``direct`` (default): ``Client.run`` sends the chunk to the worker, which runs it in its own
  task thread (so still one solve at a time per process, queued with any Dask tasks). About
  5 ms per superstep on this machine's LocalCluster, against ~15–20 ms for tasks; the chunks
  do not appear as tasks on the dashboard.
* ``tasks``: one Dask task per chunk, with a key that names the run, superstep and chunk
  (visible in the dashboard's task stream), through the scheduler.
"""

from __future__ import annotations

import asyncio
import os
import uuid
from typing import Any

from ocpar.bsp.backend import Backend, BackendError
from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.kernel import ChunkResult, run_packed_chunk
from ocpar.bsp.malloc import keep_solver_workspaces_on_heap

#: Environment of worker processes spawned by the embedded cluster: one BLAS/OpenMP thread.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: Modules the embedded cluster's workers import at start-up.
WORKER_PRELOAD = ("ocpar.ocp",)

#: Worker settings for CPU-bound ~ms kernels: no statistical profiler sampling the solves.
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}


def run_chunk_in_worker(name: str, tasks: Columns | list[Any]) -> ChunkResult:
    """:func:`~ocpar.bsp.kernel.run_packed_chunk` on a Dask worker, with malloc tuned for
    IPOPT first (see :mod:`ocpar.bsp.malloc`: Dask's ``MALLOC_TRIM_THRESHOLD_`` costs ~30% per
    small solve)."""
    keep_solver_workspaces_on_heap()
    return run_packed_chunk(name, tasks)


async def run_chunk_in_worker_thread(name: str, tasks: Columns | list[Any],
                                     dask_worker: Any) -> ChunkResult:
    """For ``Client.run``: :func:`run_chunk_in_worker` in the worker's task thread pool (not in
    its event loop, which keeps serving the scheduler meanwhile)."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(dask_worker.executors["default"], run_chunk_in_worker,
                                      name, tasks)


DISPATCH = ("direct", "tasks")


class DaskBackend(Backend):
    """Workers of a Dask cluster (embedded ``LocalCluster`` or an existing scheduler)."""

    name = "dask"

    def __init__(
        self,
        workers: int | None = None,
        scheduler: str | None = None,
        timeout_s: float = 10.0,
        balance: str = "blocks",
        dispatch: str = "direct",
    ) -> None:
        import dask
        from distributed import Client, LocalCluster

        if dispatch not in DISPATCH:
            raise BackendError(
                f"unknown dispatch {dispatch!r}; choose one of {', '.join(DISPATCH)}")
        self.dispatch = dispatch

        self._cluster = None
        # task keys must be unique on a shared cluster: identical keys from two coordinators
        # would be deduplicated by the scheduler, and one would get the other's results
        self._run_id = uuid.uuid4().hex[:12]
        with dask.config.set(WORKER_CONFIG):
            if scheduler is None:
                n = workers or os.cpu_count() or 1
                self._cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=":0",
                    env=WORKER_ENV,
                    # import the transcriptions (CasADi, SciPy: ~0.3 s) when a worker starts,
                    # as MPI ranks do, not in the first superstep
                    preload=list(WORKER_PRELOAD),
                )
                self.client = Client(self._cluster)
            else:
                try:
                    self.client = Client(scheduler, timeout=f"{timeout_s}s")
                except (OSError, TimeoutError, ValueError) as exc:
                    raise BackendError(f"cannot reach Dask scheduler {scheduler}: {exc}") from exc
        if workers is not None:
            try:
                self.client.wait_for_workers(workers, timeout=timeout_s)
            except TimeoutError as exc:
                self.close()
                raise BackendError(
                    f"Dask cluster has {len(self._worker_addresses())} workers, {workers} asked"
                ) from exc
        addresses = self._worker_addresses()
        if not addresses:
            self.close()
            raise BackendError("Dask cluster has no workers")
        self.addresses = addresses[: workers or len(addresses)]
        super().__init__(workers=len(self.addresses), balance=balance)

    @property
    def dashboard_link(self) -> str | None:
        """Address of the cluster's Dask dashboard (None if it has none)."""
        return self.client.dashboard_link if self.client is not None else None

    def _worker_addresses(self) -> list[str]:
        return sorted(self.client.scheduler_info(n_workers=-1)["workers"])

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        packed = [to_columns(chunk) for chunk in chunks]
        if self.dispatch == "direct":
            replies = self.client.sync(self._run_direct, name, packed)
        else:
            step = len(self.traces)
            futures = [
                self.client.submit(
                    run_chunk_in_worker,
                    name,
                    chunk,
                    key=f"ocpar-{self._run_id}-superstep-{step}-chunk-{w}",
                    workers=[address],
                    allow_other_workers=False,
                    pure=False,
                )
                for w, (address, chunk) in enumerate(zip(self.addresses, packed, strict=True))
            ]
            replies = self.client.gather(futures)
        return replies

    async def _run_direct(self, name: str, chunks: list[Columns | list[Any]]
                          ) -> list[ChunkResult]:
        replies = await asyncio.gather(*(
            self.client.run(run_chunk_in_worker_thread, name, chunk, workers=[address],
                            asynchronous=True)
            for address, chunk in zip(self.addresses, chunks, strict=True)))
        return [reply[address] for reply, address in zip(replies, self.addresses, strict=True)]

    def close(self) -> None:
        client, self.client = getattr(self, "client", None), None
        if client is not None:
            client.close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
