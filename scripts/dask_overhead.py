#!/usr/bin/env python
"""Per-superstep overhead of the Dask backend, for each way of handing chunks to workers.

    python scripts/dask_overhead.py --output runs/dask-overhead
    python scripts/dask_overhead.py --steps 200 --reps 3 --workers 2 --output DIR

Overhead = superstep wall − busiest worker's busy time (``SuperstepTrace.overhead_s``): what
the coordinator waits beyond the work itself. For each repetition and each dispatch, a fresh
embedded ``LocalCluster`` of ``--workers`` single-threaded workers runs ``--steps`` supersteps
of the 60 point-mass formation's DMOC solves (``ocpar.ocp:solve_tasks``, batched and columnar, the
formation's own path; the first of them is the run's first superstep) and then ``--steps``
of a trivial kernel (``math:sqrt`` of 60 numbers). Dispatches:

* ``direct``: the default, each worker's channel (``ocpar.bsp.channel``, started by the
  ``ocpar.bsp.dask_worker.ChunkChannel`` plugin) reached over a blocking socket from the
  coordinator's thread;
* ``comm``: the previous ``direct``, a comm handler of the worker reached over the client's
  pooled Dask connections, running the chunk in the worker's task thread (kept here only as a
  baseline);
* ``run``: the ``direct`` before that, ``Client.run`` through the scheduler (a baseline);
* ``tasks``: one named Dask task per chunk through the scheduler;
* ``actor``: a Dask actor per worker, its method called directly by the client.

Writes ``dask_overhead.json`` (every superstep's overhead, medians, p90s, first-superstep
overheads) and ``dask_overhead.png``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from distributed.diagnostics.plugin import WorkerPlugin
from distributed.protocol import ToPickle

from ocpar.bsp.dask import DaskBackend
from ocpar.bsp.dask_worker import run_chunk_in_worker
from ocpar.bsp.kernel import ChunkResult
from ocpar.bsp.malloc import keep_solver_workspaces_on_heap
from ocpar.examples.formation_point_masses import make as point_masses

DISPATCHES = ("direct", "comm", "run", "tasks", "actor")
AGENTS = 60
COMM_OP = "ocpar_run_chunk_baseline"


async def run_in_task_thread(name: str, tasks: Any, dask_worker: Any) -> ChunkResult:
    """The chunk in the worker's task thread, from its event loop."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(dask_worker.executors["default"], run_chunk_in_worker,
                                      name, tasks)


class AsyncCallBackend(DaskBackend):
    """A baseline: each chunk through ``_call`` on the client's event loop, all at once (no
    lost-worker recovery)."""

    def _prepare_direct(self) -> None:
        pass

    def _run_direct(self, name: str, chunks: list[Any]) -> list[ChunkResult]:
        async def run_all() -> list[ChunkResult]:
            return await asyncio.gather(*(self._call(a, name, c)
                                          for a, c in zip(self.addresses, chunks, strict=True)))
        return self.client.sync(run_all)

    async def _call(self, address: str, name: str, chunk: Any) -> ChunkResult:
        raise NotImplementedError


class ClientRunBackend(AsyncCallBackend):
    """``Client.run`` through the scheduler, no plugin, no warm-up."""

    async def _call(self, address: str, name: str, chunk: Any) -> ChunkResult:
        out = await self.client.run(run_in_task_thread, name, chunk, workers=[address],
                                    asynchronous=True)
        return out[address]


class CommHandler(WorkerPlugin):
    """A comm handler running the chunk in the worker's task thread, warmed at set-up."""

    name = "ocpar-baseline-comm-handler"

    async def setup(self, worker: Any) -> None:
        self._worker = worker
        worker.handlers[COMM_OP] = self.run_chunk
        await asyncio.get_running_loop().run_in_executor(
            worker.executors["default"], keep_solver_workspaces_on_heap)

    async def run_chunk(self, name: str, tasks: Any) -> ToPickle:
        return ToPickle(await run_in_task_thread(name, tasks, self._worker))


class CommBackend(AsyncCallBackend):
    """:class:`CommHandler` over the client's pooled connections, opened before the run."""

    def _prepare_direct(self) -> None:
        self.client.register_plugin(CommHandler())

        async def connect() -> None:
            await asyncio.gather(*(self.client.rpc(a).identity() for a in self.addresses))
        self.client.sync(connect)

    async def _call(self, address: str, name: str, chunk: Any) -> ChunkResult:
        return await getattr(self.client.rpc(address), COMM_OP)(name=name,
                                                                  tasks=ToPickle(chunk))


class ChunkActor:
    """A Dask actor running chunks (in the worker's actor thread)."""

    def run(self, name: str, tasks: Any) -> ChunkResult:
        return run_chunk_in_worker(name, tasks)


class ActorBackend(AsyncCallBackend):
    """One :class:`ChunkActor` per worker, called directly by the client."""

    def _prepare_direct(self) -> None:
        futures = [self.client.submit(ChunkActor, actor=True, workers=[a], pure=False)
                   for a in self.addresses]
        self._actors = dict(zip(self.addresses, self.client.gather(futures), strict=True))

    async def _call(self, address: str, name: str, chunk: Any) -> ChunkResult:
        return await self._actors[address].run(name, chunk)


BASELINES = {"run": ClientRunBackend, "comm": CommBackend, "actor": ActorBackend}


def open_dispatch(dispatch: str, workers: int) -> DaskBackend:
    if dispatch in BASELINES:
        return BASELINES[dispatch](workers=workers)
    return DaskBackend(workers=workers, dispatch=dispatch)


def measure(dispatch: str, workers: int, steps: int) -> dict:
    """One fresh cluster: ``steps`` DMOC supersteps then ``steps`` trivial ones; overheads
    in ms."""
    problem = point_masses(agents=AGENTS)
    tasks = problem.tasks(problem.initial_phi())
    numbers = [float(i) for i in range(AGENTS)]
    start = time.perf_counter()
    with open_dispatch(dispatch, workers) as backend:
        started_s = time.perf_counter() - start
        for _ in range(steps):
            backend.superstep_columns("ocpar.ocp:solve_tasks", tasks)
        for _ in range(steps):
            backend.superstep("math:sqrt", numbers)
        overhead = [t.overhead_s * 1e3 for t in backend.traces]
        busy = [max(t.worker_busy_s) * 1e3 for t in backend.traces]
    return {"start_s": started_s, "dmoc_ms": overhead[:steps], "trivial_ms": overhead[steps:],
            "dmoc_busy_ms": busy[:steps]}


def summary(runs: list[dict]) -> dict:
    """Medians over repetitions of each run's median and p90 (first superstep excluded), and
    the first superstep's overhead and its excess over the run's median."""
    out = {}
    for kernel in ("dmoc", "trivial"):
        rest = [np.asarray(r[f"{kernel}_ms"][1:]) for r in runs]
        out[kernel] = {
            "median_ms": float(np.median([np.median(x) for x in rest])),
            "p90_ms": float(np.median([np.percentile(x, 90) for x in rest])),
        }
    out["dmoc"]["busy_ms"] = float(np.median([np.median(r["dmoc_busy_ms"][1:]) for r in runs]))
    firsts = [r["dmoc_ms"][0] for r in runs]
    out["first_ms"] = float(np.median(firsts))
    out["first_excess_ms"] = float(np.median(
        [r["dmoc_ms"][0] - np.median(r["dmoc_ms"][1:]) for r in runs]))
    out["start_s"] = float(np.median([r["start_s"] for r in runs]))
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dispatches = list(result["summary"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    x = np.arange(len(dispatches))
    for k, kernel in enumerate(("dmoc", "trivial")):
        med = [result["summary"][d][kernel]["median_ms"] for d in dispatches]
        p90 = [result["summary"][d][kernel]["p90_ms"] for d in dispatches]
        bars = axes[0].bar(x + (k - 0.5) * 0.4, med, 0.4,
                           label=f"{kernel} (median; line: p90)")
        axes[0].errorbar(x + (k - 0.5) * 0.4, med,
                         yerr=[np.zeros(len(med)), np.subtract(p90, med)], fmt="none",
                         ecolor=bars.patches[0].get_facecolor(), capsize=3)
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--", label="1 ms target")
    axes[0].set_xticks(x, dispatches)
    axes[0].set_ylabel("overhead per superstep (ms)")
    axes[0].set_title(f"wall − busiest worker, {result['workers']} local workers")
    axes[0].legend(fontsize=8)
    axes[1].bar(x, [result["summary"][d]["first_excess_ms"] for d in dispatches], 0.5)
    axes[1].axhline(5.0, color="k", lw=0.8, ls="--", label="5 ms target")
    axes[1].set_xticks(x, dispatches)
    axes[1].set_ylabel("first superstep's overhead − median (ms)")
    axes[1].set_title("first superstep (60 DMOC solves)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--steps", type=int, default=200, help="supersteps per kernel")
    parser.add_argument("--reps", type=int, default=3, help="fresh clusters per dispatch")
    parser.add_argument("--dispatch", nargs="+", choices=DISPATCHES, default=list(DISPATCHES))
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    args.output.mkdir(parents=True, exist_ok=True)
    runs: dict[str, list[dict]] = {d: [] for d in args.dispatch}
    for rep in range(args.reps):  # interleaved, so that load changes hit every dispatch
        for dispatch in args.dispatch:
            runs[dispatch].append(measure(dispatch, args.workers, args.steps))
            s = summary(runs[dispatch][-1:])
            print(f"rep {rep} {dispatch:7s} dmoc median {s['dmoc']['median_ms']:.3f} ms "
                  f"p90 {s['dmoc']['p90_ms']:.3f} | trivial median "
                  f"{s['trivial']['median_ms']:.3f} ms | first {s['first_ms']:.2f} ms",
                  flush=True)
    result = {"workers": args.workers, "steps": args.steps, "reps": args.reps,
              "agents": AGENTS, "summary": {d: summary(r) for d, r in runs.items()},
              "runs": runs}
    (args.output / "dask_overhead.json").write_text(json.dumps(result, indent=1))
    plot(result, args.output / "dask_overhead.png")
    for d, s in result["summary"].items():
        print(f"{d:7s} overhead median/p90: DMOC {s['dmoc']['median_ms']:.3f}/"
              f"{s['dmoc']['p90_ms']:.3f} ms, trivial {s['trivial']['median_ms']:.3f}/"
              f"{s['trivial']['p90_ms']:.3f} ms; first superstep +{s['first_excess_ms']:.2f} ms")


if __name__ == "__main__":
    main()
