#!/usr/bin/env python
"""Dask's overhead per superstep in the formation itself, on a warm cluster.

    python scripts/dask_formation_overhead.py --agents 1000 --runs 30
    PYTHONPATH=OTHER_CHECKOUT/src python scripts/dask_formation_overhead.py ...   # before

One embedded ``LocalCluster`` of ``--workers`` workers solves the point-mass formation of
``--agents`` agents once (building the workers' solvers), then ``--runs`` times; printed: the
median, quartiles and count of the traced supersteps' overhead (wall − busiest worker,
``SuperstepTrace.overhead_s``) over those runs, and the total cost's bits (the same on every
backend and checkout). Run it alternating with the other checkout: the figures move with the
machine's load.
"""

from __future__ import annotations

import argparse

import numpy as np

from ocpar.bsp.dask import DaskBackend
from ocpar.examples.formation_point_masses import make
from ocpar.formation.solve import solve_formation


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--runs", type=int, default=30, help="solves after the first")
    args = parser.parse_args(argv)
    problem = make(agents=args.agents)
    with DaskBackend(workers=args.workers) as backend:
        solve_formation(problem, backend)
        backend.traces.clear()
        costs = {solve_formation(problem, backend).total_cost.hex() for _ in range(args.runs)}
        overhead_ms = np.array([t.overhead_s for t in backend.traces]) * 1e3
    q25, q50, q75 = np.percentile(overhead_ms, [25, 50, 75])
    print(f"{args.agents} agents, Dask x {args.workers}: {len(overhead_ms)} supersteps, "
          f"overhead median {q50:.3f} ms (quartiles {q25:.3f}, {q75:.3f}); "
          f"total cost {', '.join(sorted(costs))}")


if __name__ == "__main__":
    main()
