#!/usr/bin/env python
"""Bytes the coordinator sends and receives per superstep, and its own time per superstep, on
the formation's outer solve.

    python scripts/superstep_traffic.py --output runs/traffic            # 10,000 and 100,000
    python scripts/superstep_traffic.py --agents 1000 --workers 4 --repeat 3 --output DIR

For each ``--agents`` n: the point-mass example with n agents, solved as ``python -m
ocpar.formation`` solves it by default (projected Newton from the initial angles, then the
final solutions once more for the paths) without the report after the solve, on an
in-process backend of ``--workers`` simulated remote workers: each chunk is pickled as the
MPI backend sends it (``(kernel, to_columns(chunk))``, pickle protocol 5 in band, as
mpi4py), unpickled, run, and its :class:`~ocpar.bsp.kernel.ChunkResult` pickled and
unpickled again. Per superstep it records:

* ``sent_bytes`` / ``received_bytes``: the pickled chunks to and results from all workers
  (under MPI worker 0 is the coordinator's own rank and its chunk travels nowhere: its share
  is ``sent_bytes_rank0`` / ``received_bytes_rank0``);
* ``coordinator_s``: the coordinator's own time per superstep, everything except the
  workers' side (unpickling a chunk, running it, pickling its result): building tasks, the
  outer step, pickling chunks and unpickling results;
* ``workers_s``: the workers' side, summed over workers.

Medians over ``--repeat`` runs (one process, the repetitions outermost). Writes
``superstep_traffic.json`` in ``--output``; run it on two commits to compare designs.
"""

from __future__ import annotations

import argparse
import json
import pickle
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ocpar.bsp.backend import Backend
from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.kernel import ChunkResult, run_packed_chunk
from ocpar.formation.examples import make_example
from ocpar.formation.hierarchical import OuterObjective, solve_outer_newton

SIZES = (10_000, 100_000)


class PickledWorkers(Backend):
    """``workers`` simulated remote workers in this process: every chunk and every result
    crosses pickle as it would cross MPI; bytes and the workers' side timed per superstep."""

    name = "pickled"

    def __init__(self, workers: int) -> None:
        super().__init__(workers=workers)
        #: Per superstep: bytes to and from all workers, to and from worker 0, workers' time.
        self.messages: list[dict[str, float]] = []

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        sent = received = workers_s = 0.0
        sizes = []
        out = []
        for chunk in chunks:
            message = pickle.dumps((name, to_columns(chunk)), protocol=5)
            start = time.perf_counter()
            result = run_packed_chunk(*pickle.loads(message))
            reply = pickle.dumps(result, protocol=5)
            workers_s += time.perf_counter() - start
            out.append(pickle.loads(reply))
            sent += len(message)
            received += len(reply)
            sizes.append((len(message), len(reply)))
        self.messages.append({"sent_bytes": sent, "received_bytes": received,
                              "sent_bytes_rank0": sizes[0][0],
                              "received_bytes_rank0": sizes[0][1], "workers_s": workers_s})
        return out


def measure(agents: int, workers: int) -> dict[str, Any]:
    """One outer solve at ``agents`` agents on ``workers`` simulated workers: its supersteps'
    bytes and times, medians per superstep."""
    problem = make_example("point-mass-plane", agents)
    backend = PickledWorkers(workers)
    start = time.perf_counter()
    objective = OuterObjective(problem, backend)
    phi, iterations, success, _ = solve_outer_newton(objective, problem.initial_phi(), 1e-10,
                                                     50)
    solutions = objective.solutions(phi)
    total_cost = float(np.sum(solutions.column("cost")))
    paths_shape = np.asarray(solutions.column("q")).shape
    wall = time.perf_counter() - start
    steps = backend.messages
    workers_total = sum(s["workers_s"] for s in steps)

    def median(key: str) -> float:
        return statistics.median(s[key] for s in steps)

    return {"agents": agents, "workers": workers, "supersteps": len(steps),
            "outer_iterations": iterations, "converged": success, "total_cost": total_cost,
            "paths_shape": list(paths_shape), "wall_s": wall,
            "coordinator_s_per_superstep": (wall - workers_total) / len(steps),
            "workers_s_per_superstep": workers_total / len(steps),
            **{f"{key}_per_superstep": median(key) for key in
               ("sent_bytes", "received_bytes", "sent_bytes_rank0", "received_bytes_rank0")},
            "sent_bytes_total": sum(s["sent_bytes"] for s in steps),
            "received_bytes_total": sum(s["received_bytes"] for s in steps),
            "per_superstep": steps}


def medians(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The runs' figures, numbers as medians over the runs (the first run's lists)."""
    out = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            out[key] = statistics.median(r[key] for r in runs)
    return out


def commit() -> str:
    """The checked-out commit of the ocpar this script imported ('' outside git)."""
    import ocpar

    done = subprocess.run(["git", "-C", str(Path(ocpar.__file__).parent), "rev-parse",
                           "--short", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", nargs="+", type=int, default=list(SIZES))
    parser.add_argument("--workers", type=int, default=2, help="simulated workers (default 2)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--output", type=Path, default=Path("runs/superstep-traffic"))
    args = parser.parse_args()
    if min(args.agents) < 2 or args.workers < 1 or args.repeat < 1:
        parser.error("--agents ≥ 2, --workers ≥ 1, --repeat ≥ 1")
    runs: dict[int, list[dict[str, Any]]] = {n: [] for n in args.agents}
    for rep in range(args.repeat):
        for n in args.agents:
            row = measure(n, args.workers)
            runs[n].append(row)
            print(f"rep {rep} {n:7d} agents: {row['supersteps']} supersteps, "
                  f"sent {row['sent_bytes_per_superstep'] / 1e6:.3f} MB, received "
                  f"{row['received_bytes_per_superstep'] / 1e6:.3f} MB per superstep; "
                  f"coordinator {row['coordinator_s_per_superstep'] * 1e3:.1f} ms per "
                  f"superstep; cost {row['total_cost']:.12e}", flush=True)
    report = {"commit": commit(), "source": str(Path(sys.modules["ocpar"].__file__).parent),
              "workers": args.workers, "repeat": args.repeat,
              "sizes": {str(n): medians(rows) | {"runs": rows} for n, rows in runs.items()}}
    args.output.mkdir(parents=True, exist_ok=True)
    path = args.output / "superstep_traffic.json"
    path.write_text(json.dumps(report, indent=1))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
