"""Dask backend: one chunk of tasks per worker per superstep, pinned to that worker.

With no scheduler address an embedded ``LocalCluster`` of single-threaded worker processes is
started; with ``scheduler="tcp://HOST:PORT"`` an existing cluster is used. Chunk w always goes
to the same worker, so each worker's solver cache stays warm.

TLS (``security``, a :class:`distributed.Security`): the client presents its certificate to a
``tls://HOST:PORT`` scheduler, which refuses clients whose certificate its CA did not sign (and
clients without one); an embedded cluster then listens on ``tls://`` only, its scheduler and
workers using the client's certificate unless the ``Security`` names their own. See
``workers/tls.md``.

Two ways to hand a chunk to its worker (``dispatch``):

* ``direct`` (default): the coordinator's own thread writes each chunk to a socket of its
  worker (:mod:`ocpar.bsp.channel`: pickled, NumPy buffers out of band, plain TCP or TLS with
  the cluster's certificates), kept open for the run, and reads the reply; no scheduler, no
  event loop in between. Every chunk is encoded before the first is sent, so that the workers
  start together, and the replies are read as they arrive (the first ones unpickled while the
  last worker still works); a chunk of one task is sent as it is, not as columns. The worker
  end is a channel server that the worker plugin :class:`~ocpar.bsp.dask_worker.ChunkChannel`
  starts on every worker, present and future, when the backend registers it; the
  coordinator learns its address from the worker over Dask's comm. Chunks run one at a time
  per process, under the lock that the ``tasks`` path takes too. A chunk whose worker is lost
  runs again on a live one (:data:`MAX_CHUNK_RETRIES`). The workers must be reachable from
  the coordinator (the channel listens on an ephemeral port of the worker's host); the chunks
  do not appear on the dashboard.
* ``tasks``: one Dask task per chunk, with a key that names the run, superstep and chunk
  (visible in the dashboard's task stream), through the scheduler, which reruns a lost
  worker's chunk elsewhere.

Why this ``direct``: ``scripts/dask_overhead.py`` measures the superstep overhead (wall −
busiest worker) of each way side by side on fresh 2-worker LocalClusters; see
``docs/performance.md``. A Dask comm round trip crosses four threads (the coordinator's, the
client's event loop, the worker's event loop and its task thread); the channel crosses two.
On a 2-core machine the previous ``direct`` (a comm handler over the client's pooled
connections) measured 6–12× the channel's overhead per trivial superstep (0.5 ms for the
channel), ``Client.run`` 15–20×, and a Dask actor (own thread, reached directly) and
``tasks`` (the scheduler's bookkeeping on top of two hops) more still.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import copy
import gc
import itertools
import logging
import os
import select
import signal
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from typing import Any

from ocpar.bsp.backend import Backend, BackendError
from ocpar.bsp.channel import Channel
from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.dask_worker import (
    ADDRESS_OP,
    ChunkChannel,
    run_chunk_as_task,
    run_chunk_in_worker,
)
from ocpar.bsp.kernel import ChunkResult
from ocpar.bsp.mpi import SUPERSTEP_TIMEOUT_S

#: Environment of worker processes spawned by the embedded cluster: one BLAS/OpenMP thread.
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

#: Modules the embedded cluster's workers import at start-up: the transcriptions, and the
#: formation's worker side (its resident kernel and finish, which import the formation
#: package: ~0.3 s that would otherwise fall in the first superstep).
WORKER_PRELOAD = ("ocpar.ocp", "ocpar.formation.outer_step")

#: Settings of the clusters ocpar starts (embedded, ``ocpar serve``'s, dask-mpi): no
#: statistical profiler sampling the workers' ~ms solves; no work stealing: a chunk waits
#: for its own worker (which holds its resident agents' states and warm solvers) instead of
#: moving to an idle one, where a resident set would have to replay its history; and, on
#: Linux, worker processes forked from the process that starts them, with its imports,
#: instead of spawned afresh (2 workers: started in ~0.9 s instead of ~4 s and closed in
#: ~0.05 s instead of ~1 s, this 2-core machine, loaded; Python reinitialises its own locks
#: in the child, and no thread of ocpar's holds a lock while a cluster starts; the logging
#: handlers are held across each fork, :func:`_hold_log_handlers`).
CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False,
                  "distributed.scheduler.work-stealing": False,
                  **({"distributed.worker.multiprocessing-method": "fork"}
                     if sys.platform == "linux" else {})}

#: The logging handlers held by this process's thread that is forking (:func:`_hold_log_handlers`).
_held_handlers: list[logging.Handler] = []


def _hold_log_handlers() -> None:
    """Before a fork: take every logging handler's lock, so that no other thread is inside
    a handler's emit then. Python gives the child fresh handler locks, but not the lock of
    the stream a handler writes to: a worker forked while Dask's event-loop thread wrote a
    log line found its stream locked for ever at its first log line (its start hung)."""
    loggers = [logging.getLogger(), *(logger for logger in
                                      list(logging.Logger.manager.loggerDict.values())
                                      if isinstance(logger, logging.Logger))]
    handlers = {id(h): h for logger in loggers for h in logger.handlers}
    for handler in handlers.values():
        handler.acquire()
        _held_handlers.append(handler)


def _release_log_handlers() -> None:
    """After a fork, in the parent: release what :func:`_hold_log_handlers` took."""
    while _held_handlers:
        _held_handlers.pop().release()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_hold_log_handlers, after_in_parent=_release_log_handlers,
                        after_in_child=_held_handlers.clear)  # the child's locks are new


DISPATCH = ("direct", "tasks")

#: How long (s) a worker may take to start its channel once it has joined.
CHANNEL_WAIT_S = 10.0

#: How often one superstep may re-run a chunk whose worker was lost.
MAX_CHUNK_RETRIES = 3

#: The roles of a cluster's processes that hold a TLS certificate of their own.
TLS_ROLES = ("scheduler", "worker")


def tls_security(ca_file: str, cert: str, key: str) -> Any:
    """A :class:`distributed.Security` for a client that presents ``cert`` (with its private
    ``key``) and trusts the schedulers and workers whose certificates ``ca_file`` signed;
    encryption required. Raises :class:`BackendError` if the files do not load."""
    from distributed import Security

    security = Security(tls_ca_file=ca_file, tls_client_cert=cert, tls_client_key=key,
                        require_encryption=True)
    try:
        security.get_connection_args("client")  # loads the CA, certificate and key now
    except (OSError, ValueError) as exc:  # ssl.SSLError is an OSError
        raise BackendError(f"cannot load the TLS CA file {ca_file}, certificate {cert} and "
                           f"key {key}: {' '.join(str(exc).split())}") from exc
    return security


def embedded_cluster_security(security: Any) -> Any:
    """``security`` for an embedded cluster: encryption required, and the scheduler and workers
    present the client's certificate and key where ``security`` names none of theirs."""
    cluster = copy.copy(security)
    cluster.require_encryption = True
    for role in TLS_ROLES:
        for part in ("cert", "key"):
            if not getattr(cluster, f"tls_{role}_{part}"):
                setattr(cluster, f"tls_{role}_{part}", getattr(security, f"tls_client_{part}"))
    if not (cluster.tls_ca_file and all(getattr(cluster, f"tls_{role}_cert")
                                        for role in ("client", *TLS_ROLES))):
        raise BackendError("a TLS-secured embedded Dask cluster needs a CA file and a client "
                           "certificate and key")
    return cluster


def connection_failure(scheduler: str, security: Any, exc: BaseException) -> BackendError:
    """A one-line :class:`BackendError` for a client that could not connect to ``scheduler``."""
    reason = " ".join(str(exc).split()) or type(exc).__name__
    if (scheduler.startswith("tls://") and "ssl_context" in reason
            and (security is None or not security.tls_client_cert)):
        # distributed's own words ("TLS expects a `ssl_context` argument...") name no option
        reason = ("the scheduler requires TLS and no client certificate was given "
                  "(--tls-ca-file, --tls-cert and --tls-key; security= in the API)")
    elif security is not None and any(word in reason for word in ("SSL", "TLS certificate")):
        reason += (" (refused in the TLS handshake: the scheduler's CA must have signed this "
                   "client's certificate, and the CA file must be the one that signed the "
                   "scheduler's)")
    return BackendError(f"cannot reach Dask scheduler {scheduler}: {reason}")


def connect_client(scheduler: str, security: Any = None, timeout_s: float = 10.0) -> Any:
    """A :class:`distributed.Client` of the scheduler at ``scheduler`` (``security``: a
    :class:`distributed.Security` for a ``tls://`` one); a one-line :class:`BackendError` if it
    cannot connect (unreachable, or refused in the TLS handshake)."""
    from distributed import Client

    error = None
    try:
        return Client(scheduler, timeout=f"{timeout_s}s", security=security)
    # TypeError: a tls:// address with no TLS context; RuntimeError: encryption required but
    # refused by the other end
    except (OSError, TimeoutError, ValueError, TypeError, RuntimeError) as exc:
        error = connection_failure(scheduler, security, exc)
    # the half-started Client is garbage now (``exc`` and its frames are gone): collect it
    # here, so its __del__ stops its IO loop now, and not when the garbage collector happens to
    # run inside the start of a later Client, which then deadlocks on distributed's LoopRunner
    # lock
    gc.collect()
    raise error



@contextlib.contextmanager
def sigint_left_to_this_process() -> Iterator[None]:
    """Within (on the main thread): SIGINT ignored, so that the embedded cluster's worker
    processes started here inherit that and Ctrl-C, which a terminal sends to the whole
    process group, is this process's alone (one line, the cluster closed in order) instead
    of a traceback from every worker. This process's handler is restored on exit."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


#: Clients of existing schedulers that this process keeps open between runs, by address
#: (:func:`keep_clients`).
_KEPT: dict[str, Any] = {}
_keeping: list[bool] = []


def keep_clients() -> None:
    """Keep this process's clients of existing schedulers (no TLS) open when their runs end,
    and give them to later runs on the same scheduler: a process that runs many jobs one
    after another (a warm runner of ``ocpar serve``) connects once, not once per job. A
    client found closed is replaced."""
    _keeping[:] = [True]


def shared_client(scheduler: str, security: Any, timeout_s: float) -> Any:
    """A client of ``scheduler``: the kept one (:func:`keep_clients`) if it still runs, else a
    new connection (:func:`connect_client`), kept if this process keeps clients."""
    if not _keeping or security is not None:
        return connect_client(scheduler, security, timeout_s)
    client = _KEPT.get(scheduler)
    if client is not None and client.status == "running":
        return client
    if client is not None:
        _KEPT.pop(scheduler)
        with contextlib.suppress(Exception):
            client.close()
    _KEPT[scheduler] = client = connect_client(scheduler, security, timeout_s)
    return client


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
        security: Any = None,
        superstep_timeout_s: float = SUPERSTEP_TIMEOUT_S,
        run_name: str | None = None,
    ) -> None:
        import dask
        from distributed import Client, LocalCluster, Security

        if security is not None and not isinstance(security, Security):
            raise TypeError(f"security must be a distributed.Security, got {security!r}")
        if dispatch not in DISPATCH:
            raise BackendError(
                f"unknown dispatch {dispatch!r}; choose one of {', '.join(DISPATCH)}")
        self.dispatch = dispatch
        if not superstep_timeout_s > 0:
            raise BackendError(f"the superstep timeout must be > 0 s, got {superstep_timeout_s}")
        self.superstep_timeout_s = superstep_timeout_s
        #: Chunks run again because their worker was lost (over the backend's life).
        self.lost_chunks = 0
        #: Rounds of chunks sent so far (``tasks`` dispatch: a superstep may send several,
        #: e.g. a resident set's replay round, and each needs keys of its own).
        self._rounds = itertools.count()

        self._cluster = None
        self._channels: dict[str, Channel] = {}
        # task keys must be unique on a shared cluster: identical keys from two coordinators
        # would be deduplicated by the scheduler, and one would get the other's results
        self._run_id = (f"{run_name}-{uuid.uuid4().hex[:6]}" if run_name
                        else uuid.uuid4().hex[:12])
        with dask.config.set(CLUSTER_CONFIG):
            if scheduler is None:
                n = workers or os.cpu_count() or 1
                tls = {}
                if security is not None:
                    security = embedded_cluster_security(security)
                    tls = {"security": security, "protocol": "tls://"}
                try:
                    with sigint_left_to_this_process():
                        self._cluster = LocalCluster(
                            n_workers=n,
                            threads_per_worker=1,
                            processes=True,
                            dashboard_address=":0",
                            env=WORKER_ENV,
                            # import the transcriptions (CasADi, SciPy: ~0.3 s) when a worker
                            # starts, as MPI ranks do, not in the first superstep
                            preload=list(WORKER_PRELOAD),
                            **tls,
                        )
                except OSError as exc:  # e.g. ssl.SSLError: a certificate that does not load
                    if not tls:
                        raise
                    raise BackendError(f"cannot start a TLS-secured Dask cluster: "
                                       f"{' '.join(str(exc).split())}") from exc
                self.client = Client(self._cluster, security=security)
            else:
                if (security is not None and security.require_encryption
                        and not scheduler.startswith("tls://")):
                    raise BackendError(f"TLS certificates need a tls:// scheduler address, "
                                       f"not {scheduler}")
                self.client = shared_client(scheduler, security, timeout_s)
        if workers is not None:
            try:
                self.client.wait_for_workers(workers, timeout=timeout_s)
            except TimeoutError as exc:
                have = len(self._worker_addresses())  # before close() drops the client
                self.close()
                raise BackendError(f"Dask cluster has {have} workers, {workers} asked") from exc
        addresses = self._worker_addresses()
        if not addresses:
            self.close()
            raise BackendError("Dask cluster has no workers")
        self.addresses = addresses[: workers or len(addresses)]
        super().__init__(workers=len(self.addresses), balance=balance)
        if dispatch == "direct":
            self._prepare_direct()

    def _prepare_direct(self) -> None:
        """Install :class:`~ocpar.bsp.dask_worker.ChunkChannel` on the cluster's workers and
        connect to each worker's channel (a TLS handshake, for instance) now, not in the first
        superstep."""
        self.client.register_plugin(ChunkChannel())
        try:
            for address in self.addresses:
                self._channel(address)
        except (OSError, TimeoutError) as exc:
            self.close()
            raise BackendError(f"cannot reach the Dask workers {', '.join(self.addresses)} "
                               f"directly ({' '.join(str(exc).split())}): dispatch 'direct' "
                               "needs them reachable from here; 'tasks' goes through the "
                               "scheduler") from exc

    def _channel(self, address: str) -> Channel:
        """The open channel to the worker at (Dask) ``address``, connected on first use: its
        address from the worker's :data:`~ocpar.bsp.dask_worker.ADDRESS_OP` handler (None
        from a worker that has just joined until its plugin is set up: asked again)."""
        if address not in self._channels:
            async def channel_address() -> tuple[str, int]:
                rpc = self.client.rpc(address)
                end = asyncio.get_running_loop().time() + CHANNEL_WAIT_S
                while (reply := await getattr(rpc, ADDRESS_OP)()) is None:
                    if asyncio.get_running_loop().time() > end:
                        raise TimeoutError(f"worker {address} started no ocpar channel within "
                                           f"{CHANNEL_WAIT_S:g} s")
                    await asyncio.sleep(0.05)
                return tuple(reply)

            context = (self.client.security.get_connection_args("client").get("ssl_context")
                       if address.startswith("tls://") else None)
            self._channels[address] = Channel(self.client.sync(channel_address), context)
        return self._channels[address]

    @property
    def shares_files(self) -> bool:
        """True where every worker is on this host (an embedded cluster, or workers on
        127.0.0.1 or on one of this host's own addresses); a remote worker may not see the
        coordinator's files."""
        import socket

        local = {"127.0.0.1", "localhost", "::1", socket.gethostname()}
        with contextlib.suppress(OSError):
            local |= {info[4][0] for info in socket.getaddrinfo(socket.gethostname(), None)}
        hosts = {address.partition("://")[2].rsplit(":", 1)[0].strip("[]")
                 for address in self.addresses}
        return hosts <= local

    @property
    def dashboard_link(self) -> str | None:
        """Address of the cluster's Dask dashboard (None if it has none)."""
        return self.client.dashboard_link if self.client is not None else None

    def _worker_addresses(self) -> list[str]:
        return sorted(self.client.scheduler_info(n_workers=-1)["workers"])

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        # a chunk of one task (a resident set's, a pursuit train's) travels as it is: packing
        # it into columns and back costs more than it saves
        packed = [chunk if isinstance(chunk, list) and len(chunk) == 1 else to_columns(chunk)
                  for chunk in chunks]
        if self.dispatch == "direct":
            return self._run_direct(name, packed)
        from distributed import wait

        # a key names one computation: a superstep's second round of chunks (a resident set's
        # replay, or a set's drop before the next superstep) must not reuse the first's keys,
        # or the scheduler hands back the first round's results
        step, round_ = len(self.traces), next(self._rounds)
        futures = [
            self.client.submit(
                run_chunk_as_task,
                name,
                chunk,
                key=f"ocpar-{self._run_id}-superstep-{step}-round-{round_}-chunk-{w}",
                # its worker first; if that worker is lost the scheduler runs it elsewhere
                workers=[address],
                allow_other_workers=True,
                pure=False,
            )
            for w, (address, chunk) in enumerate(zip(self.addresses, packed, strict=True))
        ]
        if wait(futures, timeout=self.superstep_timeout_s).not_done:
            self._timed_out()
        return self.client.gather(futures)

    def _run_direct(self, name: str, chunks: list[Columns | list[Any]]) -> list[ChunkResult]:
        """Chunk w on worker w over its channel: every chunk encoded, then sent (back to back,
        so that the workers start together), then every reply received as it arrives (the
        first ones unpickled while the last worker still works). A chunk whose worker is lost
        meanwhile runs again on a live worker (at most :data:`MAX_CHUNK_RETRIES` times), all
        within the superstep deadline."""
        deadline = time.monotonic() + self.superstep_timeout_s
        targets = list(self.addresses)
        replies: list[ChunkResult | None] = [None] * len(chunks)
        pending = list(range(len(chunks)))
        for _ in range(MAX_CHUNK_RETRIES + 1):
            failed: dict[int, BaseException] = {}
            requests = {w: Channel.request(run_chunk_in_worker, name, chunks[w])
                        for w in pending}
            waiting: dict[Channel, collections.deque[int]] = {}  # in the order sent
            for w in pending:
                try:
                    channel = self._channel(targets[w])
                    channel.send_request(requests[w])
                except OSError as exc:
                    failed[w] = exc
                else:
                    waiting.setdefault(channel, collections.deque()).append(w)
            kernel_error: Exception | None = None
            for channel, w in _as_they_come(waiting, deadline):
                try:
                    reply = channel.receive(max(deadline - time.monotonic(), 0.0))
                    reply.sent_bytes = requests[w].size
                    reply.received_bytes = channel.received_bytes
                    replies[w] = reply
                except TimeoutError:
                    for address in list(self._channels):  # replies may still come: out of step
                        self._drop_channel(address)
                    self._timed_out()
                except (OSError, EOFError) as exc:  # the worker is lost (or, rarely, the
                    failed[w] = exc                  # kernel raised OSError: checked below)
                except Exception as exc:  # the kernel failed; the other replies still read
                    kernel_error = kernel_error or exc
            if kernel_error is not None:
                raise kernel_error
            if not failed:
                return replies  # type: ignore[return-value]
            for w in failed:
                self._drop_channel(targets[w])
            live = self.client.sync(self._live_workers, {targets[w] for w in failed})
            for w, exc in failed.items():
                if targets[w] in live:  # the worker is fine: the kernel itself failed
                    raise exc
            self.lost_chunks += len(failed)
            if not live:
                raise BackendError(f"superstep {len(self.traces)}: every Dask worker is lost")
            # later supersteps: the live workers (fewer, if the lost ones are not replaced)
            self.addresses = live[: len(self.addresses)]
            self.workers = len(self.addresses)
            pending = sorted(failed)
            for k, w in enumerate(pending):
                targets[w] = live[k % len(live)]
        raise BackendError(f"superstep {len(self.traces)}: chunks lost their worker "
                           f"{MAX_CHUNK_RETRIES + 1} times")

    def _drop_channel(self, address: str) -> None:
        channel = self._channels.pop(address, None)
        if channel is not None:
            channel.close()

    async def _live_workers(self, lost: set[str], wait_s: float = 10.0) -> list[str]:
        """The scheduler's workers once it has noticed that ``lost`` are gone (or after
        ``wait_s``), sorted."""
        loop = asyncio.get_running_loop()
        end = loop.time() + wait_s
        while True:
            info = await self.client.scheduler.identity(n_workers=-1)
            live = sorted(info["workers"])
            if not lost & set(live) or loop.time() > end:
                return live
            await asyncio.sleep(0.05)

    def _timed_out(self) -> None:
        raise BackendError(f"superstep {len(self.traces)}: not all Dask workers answered within "
                           f"{self.superstep_timeout_s:g} s (lost or hung)")

    def close(self) -> None:
        if getattr(self, "client", None) is not None and getattr(self, "_resident_sets", None):
            # workers gone take their states with them
            with contextlib.suppress(OSError, EOFError, BackendError):
                self._close_resident_sets()
        for address in list(getattr(self, "_channels", {})):
            self._drop_channel(address)
        client, self.client = getattr(self, "client", None), None
        if client is not None and all(client is not kept for kept in _KEPT.values()):
            client.close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


def _as_they_come(waiting: dict[Channel, collections.deque[int]], deadline: float
                  ) -> Iterator[tuple[Channel, int]]:
    """(channel, chunk) for each chunk in ``waiting`` (per channel, its chunks in the order
    sent), as the channels' replies arrive; the caller reads each reply. After ``deadline``
    (``time.monotonic()``) the chunks still waiting come as they are (the caller's read then
    times out). Waits with ``poll`` (one system call; a ``selectors`` selector costs seven
    per superstep), ``select`` where there is none."""
    by_fd = {channel.fileno(): channel for channel in waiting}
    while waiting:
        if len(waiting) == 1:  # nothing to wait for in another order
            ready = list(waiting)
        else:
            ready = [c for c in waiting if c.buffered()] or _readable(
                [c.fileno() for c in waiting], max(deadline - time.monotonic(), 0.0), by_fd)
        for channel in ready or list(waiting):
            chunks = waiting[channel]
            w = chunks.popleft()
            if not chunks:
                del waiting[channel]
            yield channel, w


def _readable(fds: list[int], timeout_s: float, by_fd: dict[int, Channel]) -> list[Channel]:
    """The channels of ``fds`` that have bytes to read, within ``timeout_s`` (none after)."""
    if hasattr(select, "poll"):
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        return [by_fd[fd] for fd, _ in poller.poll(timeout_s * 1e3)]
    return [by_fd[fd] for fd in select.select(fds, [], [], timeout_s)[0]]
