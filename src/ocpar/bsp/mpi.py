"""MPI backend (SPMD under ``mpirun -n P``): rank 0 coordinates, every rank solves a chunk.

Each superstep rank 0 sends (kernel name, chunk) to every other rank, solves its own chunk,
and receives the chunk results; tasks and results travel as columns
(:mod:`ocpar.bsp.columns`). Ranks > 0 run :meth:`MpiBackend.serve` until rank 0 closes.

A superstep given cost estimates (of a kernel that is not batched) is a shared queue instead:
every rank gets all the tasks, sorted longest first, and takes the next one whenever it is
free by an atomic fetch-and-add on a counter in rank 0's memory (MPI one-sided, in a passive
epoch open from the first queued superstep until :meth:`MpiBackend.close`, so rank 0 need not
break off its own solve to hand out work). On MACS's 10 searches of unequal length per
superstep the busier of 2 ranks is ~5 % above the mean instead of ~12 % with blocks
(docs/schemes/macs.md).

A superstep has a deadline (``timeout_s``): if a rank's results have not arrived by then (a
rank hung, or lost where the launcher did not end the job), rank 0 says which ranks are
missing on stderr and aborts the job (``MPI_Abort``) instead of waiting forever. A rank that
dies is normally caught sooner by ``mpirun``, which ends the whole job; either way a
checkpoint (:mod:`ocpar.bsp.journal`) holds every superstep completed before.
"""

from __future__ import annotations

import os
import pickle
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

from ocpar.bsp.backend import Backend
from ocpar.bsp.columns import Columns, from_columns, to_columns
from ocpar.bsp.kernel import ChunkResult, resolve_kernel, run_packed_chunk

_MPI_ENV_SIZE = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMIX_SIZE")
TASKS, RESULTS = 11, 12
#: After its own chunk, rank 0 polls for the other ranks' results without pausing for this
#: long (s), then with 0.1 ms pauses: a pause costs a small superstep ~0.35 ms (median of
#: 2000 trivial supersteps on 2 ranks: 0.48 ms polling with pauses, 0.12 ms without), and the
#: rank's core has nothing else to do meanwhile (as in MPI's own blocking receive).
SPIN_S = 0.01
#: Default superstep deadline (s).
SUPERSTEP_TIMEOUT_S = 3600.0
#: Exit status of a job aborted on a superstep deadline.
ABORT_STATUS = 3
#: Pause (s) between printing the abort message and ``MPI_Abort``: the launcher forwards a
#: rank's stderr asynchronously, and an abort that overtakes it loses the message.
ABORT_GRACE_S = 0.5


def launched_by_mpirun() -> bool:
    """True when this process was started by an MPI launcher (checked without importing MPI)."""
    return any(key in os.environ for key in _MPI_ENV_SIZE)


class MpiBackend(Backend):
    """All ranks of ``comm`` (default ``MPI.COMM_WORLD``) are workers; rank 0 coordinates.
    ``timeout_s``: the superstep deadline (s)."""

    name = "mpi"

    def __init__(self, comm: Any = None, balance: str = "blocks",
                 timeout_s: float = SUPERSTEP_TIMEOUT_S) -> None:
        from mpi4py import MPI

        if not timeout_s > 0:
            raise ValueError(f"the superstep timeout must be > 0 s, got {timeout_s}")
        self.comm = comm if comm is not None else MPI.COMM_WORLD
        self.rank = self.comm.Get_rank()
        self.timeout_s = timeout_s
        self._closed = False
        super().__init__(workers=self.comm.Get_size(), balance=balance)
        self._window: Any = None  # the queue's counter, made by the first queued superstep
        self._fetched = 0  # the counter's value when the next queued superstep starts

    @property
    def is_coordinator(self) -> bool:
        return self.rank == 0

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        sends = [self._isend((name, to_columns(chunk)), rank, TASKS)
                 for rank, chunk in enumerate(chunks[1:], start=1)]
        deadline = time.monotonic() + self.timeout_s
        results, sizes = self._gather(run_packed_chunk(name, to_columns(chunks[0])), sends,
                                      deadline)
        return [_counted(result, size) for result, size in zip(results, sizes, strict=True)]

    def _queues(self, name: str) -> bool:
        return self.workers > 1 and not getattr(resolve_kernel(name), "batched", False)

    def _run_queue(self, name: str, tasks: list[Any] | Columns
                   ) -> tuple[list[list[int]], list[ChunkResult]]:
        packed = to_columns(tasks)
        base = self._fetched
        self._fetched += len(packed) + self.workers  # each rank's last fetch finds it empty
        sends = [self._isend((name, packed, base), rank, TASKS)
                 for rank in range(1, self.workers)]
        deadline = time.monotonic() + self.timeout_s
        gathered, sizes = self._gather(self._take(name, packed, base), sends, deadline)
        return ([taken for taken, _ in gathered],
                [_counted(chunk, size) for (_, chunk), size in zip(gathered, sizes, strict=True)])

    def _take(self, name: str, tasks: list[Any] | Columns, base: int
              ) -> tuple[list[int], ChunkResult]:
        """Run tasks from the shared queue until it is empty: the positions taken (in the
        order run) and their chunk result. The queue is a counter on rank 0 that every rank
        increments atomically (one-sided, rank 0 need not take part), started at ``base``."""
        from mpi4py import MPI

        items, taken = from_columns(tasks), []
        one, fetched = np.ones(1, dtype=np.int64), np.empty(1, dtype=np.int64)
        window = self._counter()

        def pull() -> Iterator[Any]:
            while True:
                window.Fetch_and_op(one, fetched, 0, 0, MPI.SUM)
                window.Flush(0)
                k = int(fetched[0]) - base
                if k >= len(items):
                    return
                taken.append(k)
                yield items[k]

        return taken, run_packed_chunk(name, pull())

    def _counter(self) -> Any:
        """The queue's counter, an MPI window of one int64 on rank 0, set to 0 and in a
        passive-target epoch open until :meth:`close`; made by all ranks together in the
        first queued superstep."""
        from mpi4py import MPI

        if self._window is None:
            self._window = MPI.Win.Allocate(8 if self.rank == 0 else 0, 8, comm=self.comm)
            self._window.Lock_all()
            if self.rank == 0:
                self._window.Accumulate(np.zeros(1, dtype=np.int64), 0, op=MPI.REPLACE)
                self._window.Flush(0)
            self.comm.Barrier()  # no rank counts before the counter is 0
        return self._window

    def _isend(self, message: Any, rank: int, tag: int) -> tuple[Any, int]:
        """Send ``message`` pickled (as mpi4py's ``isend`` does) to ``rank``, without waiting:
        the request and the message's length (bytes)."""
        from mpi4py import MPI

        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        return self.comm.Isend([data, MPI.BYTE], dest=rank, tag=tag), len(data)

    def _send(self, message: Any, rank: int, tag: int) -> None:
        """Send ``message`` pickled to ``rank`` and wait until it has left."""
        request, _ = self._isend(message, rank, tag)
        request.Wait()

    def _receive(self, rank: int, tag: int) -> tuple[Any, int]:
        """The next message from ``rank`` with ``tag``, unpickled, and its length (bytes)."""
        from mpi4py import MPI

        status = MPI.Status()
        self.comm.Probe(source=rank, tag=tag, status=status)
        data = bytearray(status.Get_count(MPI.BYTE))
        self.comm.Recv([data, MPI.BYTE], source=rank, tag=tag)
        return pickle.loads(data), len(data)

    def _gather(self, own: Any, sends: list[tuple[Any, int]], deadline: float
                ) -> tuple[list[Any], list[tuple[int, int]]]:
        """Rank 0's own result followed by every other rank's, received by ``deadline``
        (else abort), and per rank the bytes (sent, received): (0, 0) for rank 0."""
        results: list[Any] = [own] + [None] * (self.workers - 1)
        sizes = [(0, 0)] + [(sent, 0) for _, sent in sends]
        waiting = set(range(1, self.workers))
        finished = time.monotonic()  # rank 0's own chunk
        while waiting:
            for rank in sorted(waiting):
                if self.comm.Iprobe(source=rank, tag=RESULTS):
                    results[rank], received = self._receive(rank, RESULTS)
                    sizes[rank] = (sizes[rank][0], received)
                    waiting.discard(rank)
            if waiting:
                now = time.monotonic()
                if now > deadline:
                    self._abort(waiting)
                if now - finished > SPIN_S:
                    time.sleep(1e-4)
        for request, _ in sends:
            request.Wait()
        return results, sizes

    def _abort(self, missing: set[int]) -> None:
        ranks = ", ".join(str(r) for r in sorted(missing))
        print(f"ocpar: superstep {len(self.traces)}: no result from MPI rank(s) {ranks} within "
              f"{self.timeout_s:g} s (lost or hung); aborting the job. A checkpoint holds the "
              "supersteps completed before (--resume).", file=sys.stderr, flush=True)
        time.sleep(ABORT_GRACE_S)
        self.comm.Abort(ABORT_STATUS)

    def serve(self) -> None:
        """On ranks > 0: solve the chunks rank 0 sends until it closes the backend."""
        while (message := self._receive(0, TASKS)[0]) is not None:
            result = run_packed_chunk(*message) if len(message) == 2 else self._take(*message)
            self._send(result, 0, RESULTS)
        self._free_window()

    def close(self) -> None:
        if self.is_coordinator and not self._closed:
            self._close_resident_sets()
            self._closed = True
            for rank in range(1, self.workers):
                self._send(None, rank, TASKS)
            self._free_window()

    def _free_window(self) -> None:
        if self._window is not None:
            self._window.Unlock_all()
            self._window.Free()
            self._window = None


def _counted(result: ChunkResult, size: tuple[int, int]) -> ChunkResult:
    """``result`` with the bytes (sent, received) its chunk crossed."""
    result.sent_bytes, result.received_bytes = size
    return result
