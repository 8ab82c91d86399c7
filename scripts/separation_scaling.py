#!/usr/bin/env python
"""How a minimum separation scales with the fleet: the built-in point masses at D.

    python scripts/separation_scaling.py --output runs/separation-scaling        # 200, 1000
    python scripts/separation_scaling.py --agents 200 --distance 0.05 --output ...

For each size: the unconstrained solve, then the same with ``min_separation`` D (the
default ``separation exact``), serially. Reports the solve's wall time of both, the status,
the separation rounds, the agents each round re-solved (from the run's progress lines), the
pairs within D (1 + 1e-6) on the returned paths, whether the exact
separation ran (its largest cluster) and the cost's increase over the unconstrained optimum,
and per superstep the busiest worker's time against the unconstrained run's largest.
Writes ``separation_scaling.json`` and ``separation_scaling.png`` (the busiest worker's
time per superstep, both runs, each size).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

from ocpar.examples.formation_point_masses import make
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.keep_out.separation import close_pairs
from ocpar.plotting import pyplot, save


def busiest(result: object) -> list[float]:
    """The busiest worker's time (s) of each superstep of ``result``'s trace."""
    return [max(step.worker_busy_s) for step in result.trace]   # type: ignore[attr-defined]


def measure(agents: int, distance: float) -> dict:
    """One size: the unconstrained and the separated run's figures (module docstring)."""
    problem = make(agents=agents)
    start = time.perf_counter()
    free = solve_formation(problem)
    free_s = time.perf_counter() - start
    resolved: list[int] = []

    def progress(line: str) -> None:
        found = re.match(r"separation round +\d+ +spread +\d+ it +agents +(\d+)", line)
        if found:
            resolved.append(int(found.group(1)))

    start = time.perf_counter()
    kept = solve_formation(problem, options=FormationOptions(min_separation=distance),
                           progress=progress)
    kept_s = time.perf_counter() - start
    free_busiest, kept_busiest = busiest(free), busiest(kept)
    return {
        "agents": agents, "distance": distance, "status": kept.status,
        "message": kept.message, "unconstrained_solve_s": free.wall_time_s,
        "unconstrained_call_s": free_s, "solve_s": kept.wall_time_s, "call_s": kept_s,
        "rounds": kept.separation_rounds, "resolved_per_round": resolved,
        "binding_pairs": len(close_pairs(problem.positions(kept.trajectories),
                                             distance * (1 + 1e-6))),
        "min_separation": kept.separation.distance,
        "cost": kept.total_cost, "unconstrained_cost": free.total_cost,
        "increase": kept.total_cost / free.total_cost - 1,
        "exact_run": "exact separation not run" not in kept.message,
        "unconstrained_busiest_s": free_busiest, "busiest_s": kept_busiest,
        "busiest_ratio": max(kept_busiest) / max(free_busiest)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[200, 1000])
    parser.add_argument("--distance", type=float, default=0.05, help="D, length unit")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report = []
    fig, ax = pyplot().subplots(figsize=(7, 4))
    for colour, agents in enumerate(args.agents):
        row = measure(agents, args.distance)
        report.append(row)
        print(json.dumps({k: v for k, v in row.items()
                          if k not in ("busiest_s", "unconstrained_busiest_s")}), flush=True)
        ax.plot(row["unconstrained_busiest_s"], color=f"C{colour}", linestyle=":",
                marker=".", label=f"{agents}, unconstrained")
        ax.plot(row["busiest_s"], color=f"C{colour}", marker=".",
                label=f"{agents}, min separation {args.distance:g}")
    ax.set_yscale("log")
    ax.set_xlabel("superstep")
    ax.set_ylabel("busiest worker (s)")
    ax.set_title("point masses, serial")
    ax.legend(fontsize=8)
    (args.output / "separation_scaling.json").write_text(json.dumps(report, indent=1))
    save(fig, args.output / "separation_scaling.png")
    print(f"wrote {args.output / 'separation_scaling.json'}, "
          f"{args.output / 'separation_scaling.png'}")


if __name__ == "__main__":
    main()
