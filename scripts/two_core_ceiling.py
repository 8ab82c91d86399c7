#!/usr/bin/env python
"""This machine's ceiling for the formation on 2 workers, beside the measured runs, in one
sitting: how fast two processes go when they never communicate at all.

    python scripts/two_core_ceiling.py --agents 10000 --repeat 5 --output runs/two-core-ceiling

Each repetition (repetitions outermost, so that a drift of the machine hits every figure alike):

1. **Inner solves alone.** One process solves the n-agent formation on the serial backend
   (after a warm-up solve that builds its solvers), ``--rounds`` times. Its per-agent time per
   superstep is τ1 = Σ supersteps' busy time / Σ supersteps' tasks.
2. **Inner solves side by side.** Two processes each solve the n/2-agent formation at the
   same moment (a barrier starts every round), τ2 likewise (each round the slower process's).
   Nothing passes between them: ``c = 2·τ1/τ2`` is the most that splitting the inner solves
   over this machine's 2 cores can give (2 on an ideal machine; less where the cores share
   a cache, memory bandwidth or a busy host).
3. **The measured runs**, each ``python -m ocpar.formation --agents n`` in a fresh process:
   ``mpirun -n 1`` (the fastest serial configuration, ``scripts/formation_bench.py``),
   ``mpirun -n 2`` and Dask with 2 workers. From MPI × 1: T1, its solve wall time, W1 its
   supersteps' worker busy time, and S1 = T1 − W1, the coordinator's serial part.

The run's ceiling on 2 workers is ``T1 / (S1 + W1/c)`` (Amdahl's law with the machine's c and
no communication cost); a measured speedup is T1 over that run's solve wall time.
Point-mass agents cost the same per solve whatever their boundary values (one KKT solve), so
the n/2-agent formation's τ is that of half the n-agent one.

Writes ``two_core_ceiling.json`` (every sample and the medians) and ``two_core_ceiling.png``
(speedups against MPI × 1: the ceilings and the measured runs) in ``--output``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import sys
from pathlib import Path

from formation_bench import MPIRUN, run_once

FORMATION = [sys.executable, "-m", "ocpar.formation", "--quiet"]
#: The measured configurations: name, command prefix before FORMATION's options.
RUNS = {"MPI × 1": [MPIRUN, "-n", "1"], "MPI × 2": [MPIRUN, "-n", "2"],
        "Dask × 2": ["--backend", "dask", "--workers", "2"]}
TARGET = 1.8


def _solve_rounds(agents: int, rounds: int, barrier) -> list[float]:
    """In a fresh process: the n-agent formation solved serially ``rounds`` times after a
    warm-up, each round started by ``barrier``; per round the per-agent time per superstep
    (s)."""
    from ocpar.bsp import open_backend
    from ocpar.examples.formation_point_masses import make
    from ocpar.formation import solve_formation

    problem = make(agents=agents)
    times = []
    with open_backend("serial") as backend:
        solve_formation(problem, backend)
        for _ in range(rounds):
            barrier.wait()
            trace = solve_formation(problem, backend).trace
            times.append(sum(t.wall_s for t in trace) / sum(t.tasks for t in trace))
    return times


def inner_solves(agents: int, processes: int, rounds: int) -> list[float]:
    """Per round, the slowest of ``processes`` processes' per-agent time per superstep (s),
    each solving ``agents`` agents at the same moment."""
    context = mp.get_context("spawn")
    with context.Manager() as manager, context.Pool(processes) as pool:
        barrier = manager.Barrier(processes)
        per_process = pool.starmap(_solve_rounds, [(agents, rounds, barrier)] * processes)
    return [max(round_times) for round_times in zip(*per_process, strict=True)]


def measured_run(name: str, agents: int, output: Path, limit_s: float) -> dict:
    """One run of the formation by configuration ``name`` (:data:`RUNS`): its solve wall
    time, worker busy time summed over its supersteps (the busiest worker's) and status."""
    prefix = RUNS[name]
    launcher, options = (prefix, []) if prefix[0] == MPIRUN else ([], prefix)
    out = output / name.replace(" × ", "x").lower()
    result = run_once(launcher + FORMATION + ["--agents", str(agents), "--output", str(out)]
                      + options, out, limit_s)
    if result.get("status") != "converged":
        raise RuntimeError(f"{name}: {result.get('status')}: {result.get('message')}")
    return {"wall_s": result["wall_time_s"], "total_cost": result["total_cost"],
            "busy_s": sum(max(t["worker_busy_s"]) for t in result["trace"])}


def plot(report: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars = {"inner solves split,\nno communication (c)": report["parallel_part_ceiling"],
            "the run's ceiling\nT1 / (S1 + W1/c)": report["run_ceiling"]}
    bars |= {f"{name}\nmeasured": s for name, s in report["speedups"].items()}
    fig, ax = plt.subplots(figsize=(7.5, 4))
    ax.bar(list(bars), list(bars.values()), color=["0.6", "0.4"] + ["C0"] * (len(bars) - 2))
    for k, value in enumerate(bars.values()):
        ax.text(k, value / 2, f"{value:.2f}×", ha="center", color="w")
    ax.axhline(2.0, color="k", lw=0.8, label="2 cores, ideal")
    ax.axhline(TARGET, color="C3", ls="--", lw=0.8, label=f"target {TARGET}×")
    ax.set_ylim(0, 2.5)
    ax.set_ylabel("speedup against MPI × 1")
    ax.set_title(f"{report['agents']:,} point masses on this machine's 2 cores "
                 f"(medians of {report['repeat']})")
    ax.legend(loc="upper right", ncols=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=10_000, help="n (default 10,000; even)")
    parser.add_argument("--repeat", type=int, default=5, help="repetitions (default 5)")
    parser.add_argument("--rounds", type=int, default=5,
                        help="solves per process and repetition (default 5)")
    parser.add_argument("--time-limit", type=float, default=600.0,
                        help="seconds before a measured run is killed (default 600)")
    parser.add_argument("--output", type=Path, default=Path("runs/two-core-ceiling"))
    args = parser.parse_args()
    if args.agents < 2 or args.agents % 2:
        parser.error(f"--agents must be an even number ≥ 2, got {args.agents}")
    os.environ["OMP_NUM_THREADS"] = "1"
    args.output.mkdir(parents=True, exist_ok=True)
    samples: dict[str, list] = {"alone_s": [], "side_by_side_s": []} | {n: [] for n in RUNS}
    for rep in range(args.repeat):
        samples["alone_s"] += inner_solves(args.agents, 1, args.rounds)
        samples["side_by_side_s"] += inner_solves(args.agents // 2, 2, args.rounds)
        for name in RUNS:
            samples[name].append(measured_run(name, args.agents, args.output, args.time_limit))
        print(f"repetition {rep + 1}/{args.repeat}: τ1 {1e6 * samples['alone_s'][-1]:.2f} µs, "
              f"τ2 {1e6 * samples['side_by_side_s'][-1]:.2f} µs, "
              + ", ".join(f"{n} {samples[n][-1]['wall_s']:.3f} s" for n in RUNS), flush=True)
    tau1 = statistics.median(samples["alone_s"])
    tau2 = statistics.median(samples["side_by_side_s"])
    walls = {n: statistics.median(r["wall_s"] for r in samples[n]) for n in RUNS}
    t1 = walls["MPI × 1"]
    w1 = statistics.median(r["busy_s"] for r in samples["MPI × 1"])
    c = 2 * tau1 / tau2
    report = {
        "agents": args.agents, "repeat": args.repeat, "rounds": args.rounds,
        "inner_solve_alone_us": 1e6 * tau1, "inner_solve_side_by_side_us": 1e6 * tau2,
        "parallel_part_ceiling": c,
        "serial_T1_s": t1, "serial_busy_W1_s": w1, "serial_part_S1_s": t1 - w1,
        "run_ceiling": t1 / (t1 - w1 + w1 / c),
        "wall_s": walls,
        "speedups": {n: t1 / walls[n] for n in RUNS if n != "MPI × 1"},
        "samples": samples,
    }
    (args.output / "two_core_ceiling.json").write_text(json.dumps(report, indent=1))
    plot(report, args.output / "two_core_ceiling.png")
    print(f"per-agent inner solve: alone {1e6 * tau1:.2f} µs, side by side {1e6 * tau2:.2f} µs"
          f" → the inner solves' ceiling on 2 cores c = {c:.2f}×")
    print(f"MPI × 1: T1 {t1:.3f} s = W1 {w1:.3f} s busy + S1 {t1 - w1:.3f} s serial → the "
          f"run's ceiling {report['run_ceiling']:.2f}×")
    for name, speedup in report["speedups"].items():
        print(f"{name}: {walls[name]:.3f} s, {speedup:.2f}× "
              f"({speedup / report['run_ceiling']:.0%} of the ceiling)")
    print(f"wrote {args.output / 'two_core_ceiling.json'} and two_core_ceiling.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
