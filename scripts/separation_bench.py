#!/usr/bin/env python
"""Cost of the closest approach (``ocpar.formation.keep_out.separation``) against the number of
agents.

    python scripts/separation_bench.py --output runs/separation-bench

Two families of paths, N = 10 intervals: ``random`` (n agents spread over a square of side
2√n, each a random walk of unit steps) and ``paper`` (the paper's point-mass geometry with n
agents: straight lines from the start line [−30, 30] to the circle of radius 10 about (100,
100) at the initial angles, with the rest-to-rest profile 3t² − 2t³, a bundle that narrows
half-way). For each n, ``closest_approach`` is timed ``--repeat`` times (median); up to
``--brute-max`` agents the all-pairs exact minimum (``interval_closest`` on every pair) is
timed in turn with it and must give the same distance and pair. Writes
``separation_bench.json`` and ``separation_bench.png``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from ocpar.examples import formation_point_masses
from ocpar.formation.keep_out.separation import closest_approach, interval_closest
from ocpar.plotting import pyplot, save

INTERVALS = 10


def random_paths(n: int) -> np.ndarray:
    rng = np.random.default_rng(n)
    start = rng.uniform(0, 2 * np.sqrt(n), (n, 1, 2))
    return start + rng.normal(0, 1, (n, INTERVALS + 1, 2)).cumsum(axis=1)


def paper_paths(n: int) -> np.ndarray:
    problem = formation_point_masses.make(agents=n)
    end = problem.final_positions(problem.initial_phi())
    t = np.linspace(0, 1, INTERVALS + 1)
    profile = 3 * t**2 - 2 * t**3
    return problem.starts[:, None, :] + profile[None, :, None] * (end - problem.starts)[:, None]


FAMILIES = {"random": random_paths, "paper": paper_paths}


def brute_force(positions: np.ndarray) -> tuple[float, tuple[int, int]]:
    """The all-pairs exact minimum and its pair."""
    pairs = np.column_stack(np.triu_indices(len(positions), 1))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    best = int(np.argmin(minima))
    return float(minima[best]), (int(pairs[best, 0]), int(pairs[best, 1]))


def timed(function, *args) -> tuple[float, object]:
    start = time.perf_counter()
    value = function(*args)
    return time.perf_counter() - start, value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=3, help="timed calls per size (median)")
    parser.add_argument("--brute-max", type=int, default=1000,
                        help="largest n also solved by all pairs")
    parser.add_argument("--output", type=Path, default=Path("runs/separation-bench"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report = {"intervals": INTERVALS, "repeat": args.repeat, "families": {}}
    for family, make in FAMILIES.items():
        rows = []
        for n in args.agents:
            positions = make(n)
            times, brute_times = [], []
            for _ in range(args.repeat):
                elapsed, found = timed(closest_approach, positions, 1.0)
                times.append(elapsed)
                if n <= args.brute_max:
                    elapsed, (distance, pair) = timed(brute_force, positions)
                    brute_times.append(elapsed)
                    if (distance, pair) != (found.distance, found.agents):
                        raise SystemExit(f"{family} n={n}: all pairs give {distance} {pair}, "
                                         f"closest_approach {found}")
            row = {"agents": n, "seconds": statistics.median(times),
                   "min_separation": found.distance, "closest_pair": list(found.agents),
                   "closest_time": found.time}
            if brute_times:
                row["brute_force_seconds"] = statistics.median(brute_times)
            rows.append(row)
            print(family, row, flush=True)
        report["families"][family] = rows
    (args.output / "separation_bench.json").write_text(json.dumps(report, indent=1))

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for family, rows in report["families"].items():
        n = [r["agents"] for r in rows]
        line, = ax.loglog(n, [r["seconds"] for r in rows], "o-", label=f"{family}: tree of boxes")
        brute = [(r["agents"], r["brute_force_seconds"]) for r in rows
                 if "brute_force_seconds" in r]
        if brute:
            ax.loglog(*zip(*brute, strict=True), "s", color=line.get_color(), mfc="none",
                      label=f"{family}: all pairs")
    ax.set_xlabel("agents")
    ax.set_ylabel("closest approach (s, median)")
    ax.set_title(f"closest approach on piecewise-linear paths, N = {INTERVALS}")
    ax.legend(fontsize=8)
    save(fig, args.output / "separation_bench.png")
    print(f"wrote {args.output}/separation_bench.json, separation_bench.png")


if __name__ == "__main__":
    main()
