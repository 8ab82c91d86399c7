"""Timing records of supersteps (all times in seconds)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np


@dataclass
class SuperstepTrace:
    """Measurements of one superstep.

    ``task_wall_s``/``task_cpu_s``/``task_worker`` (the worker that ran it) are per task in
    task order (arrays: a million tasks cost 8 MB each, not a list of Python objects);
    ``worker_busy_s``/``worker_cpu_s``
    and ``worker_peak_rss_mb`` (peak resident memory of the worker process so far, MiB)
    per worker; ``overhead_s`` = ``wall_s`` - max(``worker_busy_s``): communication, barrier
    and scheduling cost. ``worker_sent_bytes``/``worker_received_bytes``: per worker, the
    bytes of the coordinator's messages to it and of its replies (0 for a chunk run in the
    coordinator's own process, as worker 0 under MPI and the serial backend's, or where the
    transport does not count: Dask's ``tasks`` dispatch); :attr:`sent_bytes` and
    :attr:`received_bytes` their sums (the h of the cost model's g·h).
    """

    index: int
    tasks: int
    wall_s: float
    worker_busy_s: list[float]
    worker_cpu_s: list[float]
    worker_tasks: list[int]
    worker_peak_rss_mb: list[float]
    task_wall_s: np.ndarray
    task_cpu_s: np.ndarray
    task_worker: np.ndarray
    worker_sent_bytes: list[int] = field(default_factory=list)
    worker_received_bytes: list[int] = field(default_factory=list)

    @property
    def sent_bytes(self) -> int:
        """Bytes the coordinator sent this superstep."""
        return sum(self.worker_sent_bytes)

    @property
    def received_bytes(self) -> int:
        """Bytes the coordinator received this superstep."""
        return sum(self.worker_received_bytes)

    @property
    def workers(self) -> int:
        return len(self.worker_busy_s)

    @property
    def overhead_s(self) -> float:
        return self.wall_s - max(self.worker_busy_s, default=0.0)

    @property
    def imbalance(self) -> float:
        """max/mean worker busy time (1 = perfectly balanced)."""
        busy = self.worker_busy_s
        mean = sum(busy) / len(busy) if busy else 0.0
        return max(busy) / mean if mean > 0 else 1.0

    def to_dict(self, lists: bool = True) -> dict:
        """The fields (lists copied, not deep-copied item by item as ``dataclasses.asdict`` does:
        ~1 s per run at 10,000 agents; the per-task arrays as lists, or as they are with
        ``lists`` False), with ``overhead_s`` and ``imbalance``."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out = {k: list(v) if isinstance(v, list) else v.tolist()
               if lists and isinstance(v, np.ndarray) else v for k, v in out.items()}
        return out | {"overhead_s": self.overhead_s, "imbalance": self.imbalance,
                      "sent_bytes": self.sent_bytes, "received_bytes": self.received_bytes}
