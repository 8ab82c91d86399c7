#!/usr/bin/env python
"""PBMS benchmark: wall time versus workers on case 1, and peak memory versus N.

    python scripts/pursuit_bench.py --output runs/pursuit-bench            # both parts
    python scripts/pursuit_bench.py --part time --workers 1 2 --repeats 3 --output DIR
    python scripts/pursuit_bench.py --part memory --samples 501 1001 2001 --output DIR
    python scripts/pursuit_bench.py --part solvers --output DIR
    python scripts/pursuit_bench.py --part convergence --convergence-samples 501 --levels 1 3

``time``: case 1, N = 301, N_Δ = 60, N_δ = 32, the default ε (the paper's Table II setting),
``--repeats`` runs (default 3) of ``mpirun -n P python -m ocpar.pursuit`` and of the Dask
backend with P local workers, for each P, interleaved: solve wall time, agents, final mass,
supersteps and, from the trace, the time in the busiest worker's solves, the per-superstep
overhead and the coordinator's time between supersteps; the medians per configuration go to
``time_median``.

``solvers``: the subproblems of case 1's first ``--supersteps`` supersteps (N = 301, N_Δ = 60,
N_δ = 32), re-solved in this process from the leader's plan by each local solver and by IPOPT
alone, interleaved, ``--repeats`` times: median CPU time per solve (ms), iterations, failures,
largest difference from IPOPT's solution (w) and cost.

``memory``: case 2 with N_Δ = 100, N_δ = 81 (the paper's N = 2001 setting) for each N: PBMS on
2 MPI ranks, ``--memory-agents`` agents (peak resident memory of the largest worker, final mass,
wall time) and full-horizon MS on one rank (its peak memory grows with N; PBMS's must not).

``convergence``: the paper's settings (case 1, N = 301, N_Δ = 60, N_δ = 32; case 2, N = 501,
N_Δ = 60, N_δ = 32; case 2, N = 2001, N_Δ = 100, N_δ = 81), each N of ``--convergence-samples``:
PBMS on 2 MPI ranks with the default ε and at most 1.5 × the paper's agent count, and the
full-horizon MS of the same discretisation on one rank: agents, final mass and its distance to
MS, the first agent within 0.05 kg of MS, why the run stopped and the estimated improvement
still to come, wall time and peak memory per worker, for each of ``--levels`` (coarse-to-fine
levels; 1, the paper's scheme, by default); the plot shows each agent's distance to MS against
its index (the last level's agents), with the paper's agent counts.

Writes ``pursuit_bench.json`` and ``pursuit_bench.png``. Times exclude process start-up.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

import ocpar
from ocpar.result_files import load_trace, read_summary

MPIRUN = str(Path(sys.executable).parent / "mpirun")
#: The paper's PBMS runs by N: (case, N_Δ, N_δ, the paper's agents), §VI-B.1-3.
PAPER_RUNS = {301: (1, 60, 32, 3344), 501: (2, 60, 32, 2892), 2001: (2, 100, 81, 12402)}
#: How close to the full-horizon MS optimum the issue asks PBMS to come (kg).
CLOSE_KG = 0.05


def run(args: list[str], out: Path, backend: str, workers: int) -> dict:
    """One ``python -m ocpar.pursuit`` run; returns its result.json (without bulky fields)."""
    # --mode ms has no reference to skip; PBMS times the paper's train (--finish train)
    reference = [] if "ms" in args else ["--no-reference", "--finish", "train"]
    cmd = [sys.executable, "-m", "ocpar.pursuit", *args, "--quiet", *reference,
           "--output", str(out)]
    if backend == "mpi":
        cmd = [MPIRUN, "-n", str(workers), *cmd]
    else:
        cmd += ["--backend", "dask", "--workers", str(workers)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"failed: {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    data = read_summary(out)
    keep = ("mode", "problem", "samples", "window", "update", "epsilon", "backend", "workers",
            "status", "message", "final_mass_kg", "agents", "subproblem_solves",
            "failed_solves", "supersteps", "max_agents_in_flight", "wall_time_s",
            "peak_rss_mb_per_worker", "rk_final_altitude_error_m")
    # ms records no window, update or epsilon (it uses none)
    row = {k: data.get(k) for k in keep} | trace_summary(load_trace(out), data["wall_time_s"])
    if data["mode"] == "pbms":
        row |= {k: data[k] for k in ("stop_reason", "estimated_remaining_final_mass_kg",
                                     "result_source", "train_final_mass_kg")}
    print(json.dumps(row), flush=True)
    return row


def trace_summary(trace: list[dict], wall: float) -> dict:
    """Where a run's wall time went (s): the busiest worker's solves summed over supersteps,
    superstep wall minus that (communication and barrier), the rest (the coordinator); the
    median task time (ms) and tasks per superstep."""
    supersteps = sum(t["wall_s"] for t in trace)
    busiest = sum(max(t["worker_busy_s"]) for t in trace)
    tasks = [s for t in trace for s in t["task_wall_s"]]
    return {"busiest_worker_s": busiest, "superstep_overhead_s": supersteps - busiest,
            "coordinator_s": wall - supersteps, "median_task_ms": statistics.median(tasks) * 1e3,
            "tasks_per_superstep": len(tasks) / len(trace)}


def time_part(workers: list[int], backends: list[str], repeats: int,
              output: Path) -> tuple[list[dict], list[dict]]:
    """Every run, and the median of each (backend, workers) configuration's runs."""
    args = ["--case", "1", "--samples", "301", "--window", "60", "--update", "32"]
    rows = [run(args, output / f"time-{b}-{p}-{k}", b, p)
            for k in range(repeats) for b in backends for p in workers]
    medians = []
    for b in backends:
        for p in workers:
            runs = [r for r in rows if r["backend"] == b and r["workers"] == p]
            numbers = [k for k, v in runs[0].items() if isinstance(v, float)]
            medians.append({"backend": b, "workers": p, "runs": len(runs)}
                           | {k: statistics.median(r[k] for r in runs) for k in numbers}
                           | {"agents": sorted({r["agents"] for r in runs}),
                              "final_mass_kg": sorted({r["final_mass_kg"] for r in runs})})
    return rows, medians


def solvers_part(supersteps: int, repeats: int) -> list[dict]:
    """Each local solver and IPOPT on the same recorded pursuit subproblems."""
    import dataclasses
    import time

    import numpy as np

    from ocpar.examples.pursuit_orbit_transfer import make
    from ocpar.ocp import ms_problem, solve_task
    from ocpar.ocp.multiple_shooting import LOCAL_SOLVERS
    from ocpar.pursuit import PursuitSettings
    from ocpar.pursuit.slp import PursuitTrain

    train, tasks = PursuitTrain(make(case=1, samples=301), PursuitSettings()), []
    for _ in range(supersteps):
        work = train.ready()
        for agent, task in work:
            tasks.append(task)
            train.apply(agent, solve_task(task))
        train.retire_finished(solve_task)
    variants = {name: dataclasses.replace(tasks[0].shape, local_solver=name)
                for name in LOCAL_SOLVERS} | {"ipopt": dataclasses.replace(
                    tasks[0].shape, warm_start=False)}
    times: dict = {name: [] for name in variants}
    solutions: dict = {}
    for _ in range(repeats):
        for task in tasks:
            for name, base in variants.items():
                nlp = ms_problem(dataclasses.replace(base, intervals=task.shape.intervals))
                start = time.process_time()
                solutions[name, id(task)] = nlp.solve(task.params, task.warm_start,
                                                      task.multipliers)
                times[name].append(time.process_time() - start)
    rows = []
    for name in variants:
        sols = [solutions[name, id(t)] for t in tasks]
        ref = [solutions["ipopt", id(t)] for t in tasks]
        rows.append({
            "solver": name, "solves": len(tasks), "median_cpu_ms": statistics.median(
                times[name]) * 1e3, "median_iterations": statistics.median(
                s.iterations for s in sols), "failed": sum(not s.success for s in sols),
            "max_w_difference": max(float(np.max(np.abs(s.w - r.w))) for s, r in zip(
                sols, ref, strict=True)),
            "max_cost_difference": max(abs(s.cost - r.cost) for s, r in zip(
                sols, ref, strict=True))})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def memory_part(samples: list[int], agents: int, output: Path) -> list[dict]:
    rows = []
    for n in samples:
        args = ["--case", "2", "--samples", str(n), "--window", "100", "--update", "81"]
        rows.append(run([*args, "--max-agents", str(agents)], output / f"memory-pbms-{n}",
                        "mpi", 2))
        rows.append(run([*args, "--mode", "ms"], output / f"memory-ms-{n}", "mpi", 1))
    return rows


def convergence_part(samples: list[int], levels: list[int], output: Path) -> list[dict]:
    """PBMS with the paper's settings (and each number of coarse-to-fine ``levels``) against
    the full-horizon MS, for each N."""
    import numpy as np

    rows = []
    for n, level in ((n, level) for n in samples for level in levels):
        case, window, update, paper_agents = PAPER_RUNS[n]
        args = ["--case", str(case), "--samples", str(n), "--window", str(window),
                "--update", str(update)]
        ms = run([*args, "--mode", "ms"], output / f"convergence-ms-{n}", "mpi", 1)
        out = output / f"convergence-pbms-{n}-levels-{level}"
        row = run([*args, "--max-agents", str(int(1.5 * paper_agents)), "--levels", str(level)],
                  out, "mpi", 2)
        data = read_summary(out)
        headlines = ocpar.load(out).dataset["agent_headline"].values   # the last level's
        gap = ms["final_mass_kg"] - headlines
        close = np.flatnonzero(gap[1:] <= CLOSE_KG) + sum(data["agents_per_level"][:-1])
        row |= {"case": case, "levels": level, "paper_agents": paper_agents,
                "agents_per_level": data["agents_per_level"],
                "ms_final_mass_kg": ms["final_mass_kg"], "gap_to_ms_kg": float(gap[-1]),
                "first_agent_within_0_05_kg": int(close[0]) + 1 if len(close) else None,
                "gap_to_ms_kg_per_agent": gap.tolist()}
        print(json.dumps({k: v for k, v in row.items() if k != "gap_to_ms_kg_per_agent"}),
              flush=True)
        rows.append(row)
    return rows


def plot_convergence(rows: list[dict], path: Path) -> None:
    """Each agent's distance to the MS optimum against its index (log), one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for row in rows:
        gap, before = row["gap_to_ms_kg_per_agent"], sum(row["agents_per_level"][:-1])
        line, = ax.semilogy(range(before + 1, before + len(gap)), [max(g, 1e-6) for g in gap[1:]],
                            label=f"case {row['case']}, N = {row['samples']}, "
                                  f"N_Δ = {row['window']}, N_δ = {row['update']}, "
                                  f"levels {row['levels']} (last level)")
        ax.axvline(row["paper_agents"], color=line.get_color(), ls=":")
    ax.axhline(CLOSE_KG, color="grey", ls="--", label=f"{CLOSE_KG} kg")
    ax.set_xlabel("agent, counting earlier levels' (dotted: the paper's agent count)")
    ax.set_ylabel("MS final mass − agent's final mass (kg)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_s, ax_m) = plt.subplots(1, 3, figsize=(16, 4.5))
    medians = report["time_median"]
    labels = [f"{r['backend']} × {r['workers']}" for r in medians]
    bottom = [0.0] * len(medians)
    for key, name in (("busiest_worker_s", "busiest worker's solves"),
                      ("superstep_overhead_s", "superstep overhead"),
                      ("coordinator_s", "coordinator")):
        heights = [r[key] for r in medians]
        ax_t.bar(labels, heights, bottom=bottom, label=name)
        bottom = [b + h for b, h in zip(bottom, heights, strict=True)]
    ax_t.axhline(10, color="grey", ls=":", label="target 10 s (2 MPI ranks)")
    ax_t.set_ylabel("median wall time (s)")
    ax_t.set_title("case 1, N = 301, N_Δ = 60, N_δ = 32")
    ax_t.legend()
    ax_s.bar([r["solver"] for r in report["solvers"]],
             [r["median_cpu_ms"] for r in report["solvers"]])
    ax_s.set_ylabel("median CPU time per subproblem (ms)")
    ax_s.set_title("re-solve from the leader's plan")
    for mode, style in (("pbms", "o-"), ("ms", "s--")):
        rows = sorted((r for r in report["memory"] if r["mode"] == mode),
                      key=lambda r: r["samples"])
        ax_m.plot([r["samples"] for r in rows], [r["peak_rss_mb_per_worker"] for r in rows],
                  style, label=mode.upper())
    ax_m.set_xlabel("samples N")
    ax_m.set_ylabel("peak memory per worker (MiB)")
    ax_m.set_title("case 2, N_Δ = 100, N_δ = 81")
    ax_m.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("time", "memory", "solvers", "convergence", "all"),
                        default="all")
    parser.add_argument("--convergence-samples", nargs="+", type=int, choices=sorted(PAPER_RUNS),
                        default=[301, 501], help="the convergence part's runs, by N")
    parser.add_argument("--levels", nargs="+", type=int, default=[1],
                        help="the convergence part's coarse-to-fine levels (1: the paper's)")
    parser.add_argument("--supersteps", type=int, default=200,
                        help="supersteps recorded by the solvers part")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--backend", nargs="+", choices=("mpi", "dask"), default=["mpi", "dask"])
    parser.add_argument("--repeats", type=int, default=3, help="runs per configuration")
    parser.add_argument("--samples", nargs="+", type=int, default=[501, 1001, 2001])
    parser.add_argument("--memory-agents", type=int, default=2000,
                        help="agents per PBMS run of the memory part, default 2000")
    parser.add_argument("--output", type=Path, default=Path("runs/pursuit-bench"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report: dict = {"time": [], "time_median": [], "memory": [], "solvers": [],
                    "convergence": []}
    if args.part in ("time", "all"):
        report["time"], report["time_median"] = time_part(args.workers, args.backend,
                                                          args.repeats, args.output)
    if args.part in ("solvers", "all"):
        report["solvers"] = solvers_part(args.supersteps, args.repeats)
    if args.part in ("memory", "all"):
        report["memory"] = memory_part(args.samples, args.memory_agents, args.output)
    if args.part in ("convergence", "all"):
        report["convergence"] = convergence_part(args.convergence_samples, args.levels,
                                                 args.output)
        plot_convergence(report["convergence"], args.output / "pursuit_convergence.png")
    (args.output / "pursuit_bench.json").write_text(json.dumps(report, indent=1))
    if args.part != "convergence":
        plot(report, args.output / "pursuit_bench.png")
    print(f"wrote {args.output / 'pursuit_bench.json'} and the plots")
    return 0


if __name__ == "__main__":
    sys.exit(main())
