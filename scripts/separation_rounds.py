#!/usr/bin/env python
"""What a required minimum separation costs, with the keep and the optimal ordering.

    python scripts/separation_rounds.py --output runs/separation          # 60 masses, D 0.5
    python scripts/separation_rounds.py --problem crtbp-rigid --distance 0.05 --output ...

For each ordering: the unconstrained solve (its cost, closest approach and the number of
pairs closer than D on the continuous paths), then the same with ``min_separation`` D (cost,
increase, separation rounds, closest approach, wall time), serially. Writes
``separation.json`` and ``separation.png``: the distance of the closest pair over time, all
pairs (exact on the piecewise-linear paths:
:func:`~ocpar.formation.keep_out.separation.interval_closest`
per interval), before and after, against D.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np

from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.examples import make_example
from ocpar.formation.keep_out.separation import close_pairs, interval_closest
from ocpar.plotting import pyplot, save


def closest_per_interval(positions: np.ndarray) -> np.ndarray:
    """The closest distance of any pair on each interval (N,), exactly, all pairs."""
    pairs = np.array(list(itertools.combinations(range(len(positions)), 2)))
    distance, _ = interval_closest(positions, pairs)
    return distance.min(axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="point-mass-plane")
    parser.add_argument("--agents", type=int, default=None)
    parser.add_argument("--distance", type=float, default=0.5, help="D, length unit")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    problem = make_example(args.problem, args.agents)
    report: dict = {"problem": problem.name, "agents": problem.agents,
                    "distance": args.distance, "orderings": {}}
    fig, ax = pyplot().subplots(figsize=(7, 4))
    grid = np.arange(problem.shape.intervals) + 0.5
    for ordering, colour in (("keep", "C0"), ("optimal", "C1")):
        start = time.perf_counter()
        free = solve_formation(problem, options=FormationOptions(ordering=ordering))
        free_wall = time.perf_counter() - start
        start = time.perf_counter()
        kept = solve_formation(problem, options=FormationOptions(
            ordering=ordering, min_separation=args.distance))
        wall = time.perf_counter() - start
        free_positions = problem.positions(free.trajectories)
        report["orderings"][ordering] = {
            "unconstrained_cost": free.total_cost,
            "unconstrained_min_separation": free.separation.distance,
            "conflicts": len(close_pairs(free_positions, args.distance * (1 - 1e-12))),
            "status": kept.status, "cost": kept.total_cost,
            "increase": kept.total_cost / free.total_cost - 1,
            "rounds": kept.separation_rounds, "min_separation": kept.separation.distance,
            "inner_solves": kept.inner_solves, "unconstrained_wall_s": free_wall,
            "wall_s": wall}
        print(ordering, json.dumps(report["orderings"][ordering]), flush=True)
        ax.step(grid, closest_per_interval(free_positions), where="mid", color=colour,
                linestyle=":", label=f"{ordering}, unconstrained")
        ax.step(grid, closest_per_interval(problem.positions(kept.trajectories)), where="mid",
                color=colour, label=f"{ordering}, min separation {args.distance:g}")
    ax.axhline(args.distance, color="k", linewidth=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("DMOC interval")
    ax.set_ylabel("closest pair on the interval")
    ax.set_title(f"{problem.name}, {problem.agents} agents")
    ax.legend(fontsize=8)
    (args.output / "separation.json").write_text(json.dumps(report, indent=1))
    save(fig, args.output / "separation.png")
    print(f"wrote {args.output / 'separation.json'}, {args.output / 'separation.png'}")


if __name__ == "__main__":
    main()
