"""A BSP cost model: predict wall time and speedup at any worker count from one measured run.

A run is a serial coordinator part plus a sequence of supersteps, each a set of independent
tasks followed by a barrier. With P workers the model predicts (all times in seconds)

    T(P) = serial + Σ_supersteps [makespan_P(task times, policy) + σ(P, h)],
    σ(P, h) = L(P) + g·h(P),  L(P) = a + b·log2(P)     (:class:`SyncCost`),

where ``makespan_P`` schedules the superstep's measured per-task times onto P workers with the
partitioning policy the engine would use (``"blocks"``: ``partition.contiguous_blocks``;
``"lpt"``: ``partition.longest_first`` with the measured times as the cost estimates), and
``serial`` (the coordinator's time outside supersteps: outer optimiser, I/O, ...) does not
shrink with P. L(P) is the latency of a superstep (barrier, scatter and gather along a tree
of P workers), g the coordinator's time per byte it sends or receives (pickling, copying,
the wire), h(P) the bytes of a superstep that cross between the coordinator and its workers:
all of the superstep's bytes h, or (P−1)/P of them where the coordinator runs one of the P
chunks itself (MPI's rank 0). A superstep's h does not shrink with P: every agent's task and
result goes through the coordinator. Speedup is T(1)/T(P) of the model itself.

Assumptions worth remembering when reading the numbers: a task's time does not depend on P
(no memory-bandwidth contention, no oversubscription), ``"lpt"`` sees the exact times (the
engine only sees estimates, usually the previous superstep's), and the barrier cost grows
like a tree (log2 P), not linearly.

>>> sync = SyncCost(a_s=0.0, b_s=0.0)
>>> [p.wall_s for p in predict([[1.0] * 8], [1, 2, 4], "blocks", sync)]
[8.0, 4.0, 2.0]
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from statistics import median
from typing import Any

import numpy as np

from ocpar.bsp.partition import contiguous_blocks, longest_first
from ocpar.bsp.trace import SuperstepTrace

POLICIES = ("blocks", "lpt")
"""Partitioning policies the model knows: contiguous blocks, longest-processing-time-first."""

TraceLike = SuperstepTrace | Mapping[str, Any]
"""A :class:`SuperstepTrace` or its ``to_dict()`` (as saved in result.json's ``"trace"``)."""


def _check_workers(workers: int) -> int:
    if isinstance(workers, bool) or not isinstance(workers, int | np.integer):
        raise ValueError(f"worker count must be an integer, got {workers!r}")
    if workers < 1:
        raise ValueError(f"worker count must be at least 1, got {workers}")
    return int(workers)


def _check_policy(policy: str) -> None:
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; choose one of {', '.join(POLICIES)}")


def _check_times(times: Iterable[float], what: str) -> list[float]:
    out = []
    for k, t in enumerate(times):
        try:
            value = float(t)
        except (TypeError, ValueError):
            raise ValueError(f"{what}[{k}] is not a number: {t!r}") from None
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"{what}[{k}] must be a finite time ≥ 0 s, got {t!r}")
        out.append(value)
    return out


def makespan(times: Sequence[float], workers: int, policy: str) -> float:
    """Time (s) until the last of ``workers`` workers finishes when the tasks with the given
    times (s, one per task in task order) are partitioned by ``policy`` (``"blocks"`` or
    ``"lpt"``). No tasks → 0."""
    _check_policy(policy)
    return _makespan(_check_times(times, "times"), _check_workers(workers), policy)


def _makespan(times: list[float], workers: int, policy: str) -> float:
    if policy == "blocks":
        blocks = contiguous_blocks(len(times), workers)
        return max((sum(times[b.start:b.stop]) for b in blocks), default=0.0)
    return max((sum(times[i] for i in group) for group in longest_first(times, workers)),
               default=0.0)


@dataclass(frozen=True)
class SyncCost:
    """Per-superstep synchronisation cost σ(P, h) = ``a_s`` + ``b_s``·log2(P) +
    ``g_s_per_byte``·h(P), in seconds: the latency of the barrier, scatter of tasks and gather
    of results along a tree of P workers, and the coordinator's time per byte of the
    superstep's h bytes. ``local_chunk``: the coordinator runs one of the P chunks itself
    (MPI's rank 0), so only (P−1)/P of the bytes cross (module docstring)."""

    a_s: float
    b_s: float
    g_s_per_byte: float = 0.0
    local_chunk: bool = False

    def __post_init__(self) -> None:
        for name in ("a_s", "b_s", "g_s_per_byte"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"SyncCost.{name} must be finite and ≥ 0, got {value!r}")

    def at(self, workers: int, superstep_bytes: float = 0.0) -> float:
        """σ(P, h) in seconds for ``workers`` = P ≥ 1 and a superstep of ``superstep_bytes``
        = h bytes (its tasks and results, all of them)."""
        p = _check_workers(workers)
        return (self.a_s + self.b_s * math.log2(p)
                + self.g_s_per_byte * superstep_bytes * self.crossing(p))

    def crossing(self, workers: int) -> float:
        """The share of a superstep's bytes that crosses between the coordinator and
        ``workers`` workers: (P−1)/P with :attr:`local_chunk`, else 1."""
        return (workers - 1) / workers if self.local_chunk else 1.0

    @classmethod
    def fit_supersteps(cls, samples: Iterable[tuple[int, float, float]],
                       local_chunk: bool) -> SyncCost:
        """Non-negative least-squares fit of a, b, g to measured supersteps: ``samples`` of
        (P, bytes that crossed, overhead s) per superstep (a trace's ``workers``,
        ``sent_bytes`` + ``received_bytes`` and ``overhead_s``), from runs on at least two
        worker counts or with bytes that vary (else the terms cannot be told apart: the
        coefficient NNLS sets to 0 is then folded into the others)."""
        from scipy.optimize import nnls
        rows = [(float(_check_workers(p)), float(h), float(y)) for p, h, y in samples]
        if not rows:
            raise ValueError("SyncCost.fit_supersteps needs at least one superstep")
        if any(not (math.isfinite(h) and h >= 0 and math.isfinite(y)) for _, h, y in rows):
            raise ValueError("superstep bytes must be finite and ≥ 0, overheads finite")
        p, h, y = (np.array(column) for column in zip(*rows, strict=True))
        design = np.column_stack([np.ones(len(p)), np.log2(p), h])
        scale = np.maximum(np.abs(design).max(axis=0), 1e-300)  # bytes ~1e6, the rest ~1
        coefficients, _ = nnls(design / scale, y)
        a, b, g = (float(c) for c in coefficients / scale)
        return cls(a_s=a, b_s=b, g_s_per_byte=g, local_chunk=local_chunk)

    @classmethod
    def fit(cls, overheads: Mapping[int, float]) -> SyncCost:
        """Least-squares fit of a, b ≥ 0 to measured per-superstep overheads: ``overheads``
        maps a worker count P to the median ``overhead_s`` (s) of the supersteps of a run with
        P workers (see :func:`median_overhead`). One point gives b = 0 and a = that overhead.
        The fit is non-negative least squares, so a coefficient that would come out negative
        is 0 and the other one is refitted (noise, e.g. overheads falling with P)."""
        from scipy.optimize import nnls
        if not overheads:
            raise ValueError("SyncCost.fit needs at least one (workers, overhead) point")
        ps = [_check_workers(p) for p in overheads]
        ys = []
        for p, y in overheads.items():
            if not math.isfinite(y):
                raise ValueError(f"overhead at P={p} must be finite, got {y!r}")
            ys.append(float(y))
        if len(ps) == 1:
            return cls(a_s=max(ys[0], 0.0), b_s=0.0)
        design = np.column_stack([np.ones(len(ps)), np.log2(np.asarray(ps, dtype=float))])
        (a, b), _ = nnls(design, np.asarray(ys))
        return cls(a_s=float(max(a, 0.0)), b_s=float(max(b, 0.0)))


@dataclass(frozen=True)
class Prediction:
    """Predicted run at ``workers`` = P workers (times in seconds).

    ``wall_s`` = ``serial_s`` + ``compute_s`` + ``sync_s``; ``compute_s`` is the sum over
    supersteps of the makespan, ``sync_s`` the number of supersteps × σ(P). ``speedup`` is the
    model's T(1)/T(P) (1 if both are 0); ``efficiency`` = ``speedup``/P;
    :attr:`coordinator_share` the part of ``wall_s`` that does not shrink with P.
    """

    workers: int
    wall_s: float
    compute_s: float
    sync_s: float
    serial_s: float
    speedup: float
    efficiency: float

    @property
    def coordinator_share(self) -> float:
        """``serial_s``/``wall_s``: the coordinator's serial share of the predicted wall time
        (0 if the wall time is 0)."""
        return self.serial_s / self.wall_s if self.wall_s > 0 else 0.0


def _check_supersteps(supersteps: Sequence[Sequence[float]]) -> list[list[float]]:
    if isinstance(supersteps, str | bytes) or not isinstance(supersteps, Sequence | np.ndarray):
        raise ValueError(f"supersteps must be a list of per-task time lists, got {supersteps!r}")
    out = []
    for s, times in enumerate(supersteps):
        if isinstance(times, str | bytes) or not isinstance(times, Sequence | np.ndarray):
            raise ValueError(
                f"supersteps[{s}] must be a list of per-task times (s), got {times!r}; "
                "pass one list per superstep, e.g. [[t0, t1, ...], ...]"
            )
        out.append(_check_times(times, f"supersteps[{s}]"))
    return out


def predict(
    supersteps: Sequence[Sequence[float]],
    workers: Sequence[int],
    policy: str,
    sync: SyncCost,
    serial_s: float = 0.0,
    superstep_bytes: Sequence[float] | None = None,
) -> list[Prediction]:
    """Predict the run at each worker count in ``workers``.

    ``supersteps``: one list per superstep of per-task times in seconds (task order, as from
    :func:`task_times`); ``policy``: ``"blocks"`` or ``"lpt"``; ``sync``: the per-superstep
    synchronisation cost; ``serial_s``: coordinator time outside supersteps (s, does not
    shrink with P); ``superstep_bytes``: per superstep the bytes of all its tasks and
    results, h (None: 0). Returns one :class:`Prediction` per entry of ``workers``, in that
    order.
    """
    _check_policy(policy)
    steps = _check_supersteps(supersteps)
    counts = [_check_workers(p) for p in workers]
    if not math.isfinite(serial_s) or serial_s < 0:
        raise ValueError(f"serial_s must be a finite time ≥ 0 s, got {serial_s!r}")
    volumes = _check_times(superstep_bytes if superstep_bytes is not None
                           else [0.0] * len(steps), "superstep_bytes")
    if len(volumes) != len(steps):
        raise ValueError(f"{len(volumes)} superstep byte counts for {len(steps)} supersteps")

    def parts(p: int) -> tuple[float, float]:
        compute = sum(_makespan(times, p, policy) for times in steps)
        return compute, sum(sync.at(p, h) for h in volumes)

    base = serial_s + sum(parts(1))
    out = []
    for p in counts:
        compute, sync_s = parts(p)
        wall = serial_s + compute + sync_s
        speedup = base / wall if wall > 0 else 1.0
        out.append(Prediction(workers=p, wall_s=wall, compute_s=compute, sync_s=sync_s,
                              serial_s=serial_s, speedup=speedup, efficiency=speedup / p))
    return out


def _field(trace: TraceLike, name: str, k: int) -> Any:
    if isinstance(trace, SuperstepTrace):
        return getattr(trace, name)
    if isinstance(trace, Mapping):
        if name not in trace:
            raise ValueError(f"trace[{k}] has no {name!r} (keys: {', '.join(sorted(trace))})")
        return trace[name]
    raise ValueError(f"trace[{k}] is neither a SuperstepTrace nor a dict: {trace!r}")


def task_times(traces: Iterable[TraceLike], use: str = "cpu") -> list[list[float]]:
    """Per-superstep lists of per-task times (s, task order) from a run's traces, for
    :func:`predict`. ``use="cpu"`` takes the tasks' CPU times (insensitive to other load on
    the machine, but they overcount multithreaded and undercount waiting tasks), ``"wall"``
    their wall-clock times."""
    if use not in ("cpu", "wall"):
        raise ValueError(f"use must be 'cpu' or 'wall', got {use!r}")
    name = f"task_{use}_s"
    return [_check_times(_field(t, name, k), f"trace[{k}].{name}") for k, t in enumerate(traces)]


def superstep_samples(traces: Iterable[TraceLike]) -> list[tuple[int, float, float]]:
    """(P, bytes that crossed, overhead s) of each superstep of a run's traces, for
    :meth:`SyncCost.fit_supersteps` (0 bytes from traces that did not count them)."""
    out = []
    for k, t in enumerate(traces):
        busy = _field(t, "worker_busy_s", k)
        wall = float(_field(t, "wall_s", k))
        if isinstance(t, SuperstepTrace):
            crossed = t.sent_bytes + t.received_bytes
        else:
            crossed = sum(t.get("worker_sent_bytes", [])) + sum(t.get("worker_received_bytes", []))
        out.append((len(busy), float(crossed), wall - max(busy, default=0.0)))
    return out


def median_overhead(traces: Iterable[TraceLike]) -> float:
    """Median per-superstep overhead (s: wall − max worker busy) of a run's traces, the
    measurement :meth:`SyncCost.fit` takes per worker count."""
    values = []
    for k, t in enumerate(traces):
        if isinstance(t, SuperstepTrace):
            values.append(t.overhead_s)
        elif isinstance(t, Mapping) and "overhead_s" in t:
            values.append(float(t["overhead_s"]))
        else:
            busy = _field(t, "worker_busy_s", k)
            values.append(float(_field(t, "wall_s", k)) - max(busy, default=0.0))
    if not values:
        raise ValueError("no supersteps in the traces")
    return median(values)


def serial_time(run_wall_s: float, traces: Iterable[TraceLike]) -> float:
    """The coordinator's serial time (s): the run's total wall time minus the wall time of its
    supersteps (clamped at 0)."""
    inside = sum(float(_field(t, "wall_s", k)) for k, t in enumerate(traces))
    return max(float(run_wall_s) - inside, 0.0)


def coordinator_share(run_wall_s: float, traces: Iterable[TraceLike]) -> float:
    """A measured run's coordinator share: :func:`serial_time` / ``run_wall_s`` (0 for a run
    of no wall time)."""
    if not math.isfinite(run_wall_s) or run_wall_s < 0:
        raise ValueError(f"run_wall_s must be a finite time ≥ 0 s, got {run_wall_s!r}")
    return serial_time(run_wall_s, traces) / run_wall_s if run_wall_s > 0 else 0.0


__all__ = [
    "POLICIES",
    "Prediction",
    "SyncCost",
    "coordinator_share",
    "makespan",
    "median_overhead",
    "predict",
    "serial_time",
    "superstep_samples",
    "task_times",
]
