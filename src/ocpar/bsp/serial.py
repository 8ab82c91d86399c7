"""Serial backend: every chunk runs in the coordinator's own process."""

from __future__ import annotations

from typing import Any

from ocpar.bsp.backend import Backend
from ocpar.bsp.columns import Columns
from ocpar.bsp.kernel import ChunkResult, run_chunk


class SerialBackend(Backend):
    """One worker: the calling process."""

    name = "serial"

    def __init__(self, balance: str = "blocks") -> None:
        super().__init__(workers=1, balance=balance)

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        return [run_chunk(name, chunk) for chunk in chunks]
