"""MPI backend (SPMD under ``mpirun -n P``): rank 0 coordinates, every rank solves a chunk.

Each superstep rank 0 scatters (kernel name, chunk) to all ranks, solves its own chunk, and
gathers the chunk results; tasks and results travel as columns (:mod:`ocpar.bsp.columns`).
Ranks > 0 run :meth:`MpiBackend.serve` until rank 0 closes.
"""

from __future__ import annotations

import os
from typing import Any

from ocpar.bsp.backend import Backend
from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.kernel import ChunkResult, run_packed_chunk

_MPI_ENV_SIZE = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMIX_SIZE")


def launched_by_mpirun() -> bool:
    """True when this process was started by an MPI launcher (checked without importing MPI)."""
    return any(key in os.environ for key in _MPI_ENV_SIZE)


class MpiBackend(Backend):
    """All ranks of ``comm`` (default ``MPI.COMM_WORLD``) are workers; rank 0 coordinates."""

    name = "mpi"

    def __init__(self, comm: Any = None, balance: str = "blocks") -> None:
        from mpi4py import MPI

        self.comm = comm if comm is not None else MPI.COMM_WORLD
        self.rank = self.comm.Get_rank()
        self._closed = False
        super().__init__(workers=self.comm.Get_size(), balance=balance)

    @property
    def is_coordinator(self) -> bool:
        return self.rank == 0

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        mine = self.comm.scatter([(name, to_columns(chunk)) for chunk in chunks], root=0)
        return self.comm.gather(run_packed_chunk(*mine), root=0)

    def serve(self) -> None:
        """On ranks > 0: solve the chunks rank 0 scatters until it closes the backend."""
        while (message := self.comm.scatter(None, root=0)) is not None:
            self.comm.gather(run_packed_chunk(*message), root=0)

    def close(self) -> None:
        if self.is_coordinator and not self._closed:
            self._closed = True
            self.comm.scatter([None] * self.workers, root=0)
