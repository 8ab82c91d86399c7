#!/usr/bin/env python
"""MACS benchmark: front quality over seeds, and wall time versus workers.

    python scripts/macs_bench.py --output runs/macs-bench
    python scripts/macs_bench.py --part quality --seeds 10 --archives 20 10 --output DIR
    python scripts/macs_bench.py --part time --workers 1 2 --repeats 3 --output DIR
    python scripts/macs_bench.py --part time --workers 2 --baseline OTHER/src --output DIR

``quality``: for each problem, archive size and seed, one ``--evaluations`` run (serial
backend, two runs at a time in separate processes): GD, IGD, HV of the re-simulated archive
against the reference front; mean and variance per problem and archive size (the paper's
Table III reports mean GD/IGD over 30 runs with a 10-member archive).
``time``: ``mpirun -n P python -m ocpar.macs --problem goddard`` (``--evaluations``) per
worker count, ``--repeats`` times: the median (and every run's) solve wall time, the CPU
seconds of all workers' tasks, the coordinator's share (wall minus the supersteps' walls) and
the imbalance (busiest worker's busy time over the mean worker's, summed over supersteps);
on a shared machine the CPU seconds are the steadier figure. With ``--baseline SRC`` (the
``src`` directory of another checkout, e.g. ``git archive main src | tar -x -C /tmp/base``)
every timed run is followed by the same run of that code, so before and after share the
machine's load: the medians per code and their ratio are reported.

Writes ``macs_bench.json`` and ``macs_bench.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from ocpar.macs.local_search import RESTORATIONS
from ocpar.result_files import load_trace, read_summary

PAPER_TABLE_III = {"goddard": {"gd": 2.833e-2, "igd": 2.9449e-2},
                   "orbit-raising": {"gd": 5.9444e-2, "igd": 4.387e-2}}


def quality_run(job: tuple[str, int, int, int, str]) -> dict:
    """One serial MACS run in this (worker) process."""
    from ocpar.macs import MacsSettings, make_problem, solve_macs

    problem, archive, seed, evaluations, restoration = job
    result = solve_macs(make_problem(problem),
                        MacsSettings(max_evaluations=evaluations, archive_size=archive, seed=seed,
                                     restoration=restoration))
    row = {"problem": problem, "archive": archive, "seed": seed, "restoration": restoration,
           "gd": result.gd,
           "igd": result.igd, "hv": result.hv, "evaluations": result.evaluations,
           "wall_time_s": result.wall_time_s}
    print(json.dumps(row), flush=True)
    return row


def time_run(workers: int, repeat: int, evaluations: int, output: Path, restoration: str,
             source: Path | None = None) -> dict:
    """One ``mpirun -n workers`` Goddard run: wall, task CPU and coordinator time; the
    ``ocpar`` package imported from ``source`` (a ``src`` directory, run with its default
    restoration) if given."""
    code = "this" if source is None else "baseline"
    out = output / f"time-goddard-mpi-{workers}-{code}-{repeat}"
    cmd = [str(Path(sys.executable).parent / "mpirun"), "-n", str(workers), sys.executable,
           "-m", "ocpar.macs", "--problem", "goddard", "--archive", "20", "--max-evals",
           str(evaluations), "--quiet", "--output", str(out),
           *(["--restoration", restoration] if source is None else [])]
    env = dict(os.environ)
    if source is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(source.resolve()),
                                             *filter(None, [env.get("PYTHONPATH")])])
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    data = read_summary(out)
    trace = load_trace(out)
    row = {"code": code, "workers": workers, "repeat": repeat,
           "wall_time_s": data["wall_time_s"],
           "task_cpu_s": sum(sum(step["worker_cpu_s"]) for step in trace),
           "coordinator_s": data["wall_time_s"] - sum(step["wall_s"] for step in trace),
           "imbalance": (sum(max(step["worker_busy_s"]) for step in trace)
                         / sum(np.mean(step["worker_busy_s"]) for step in trace)),
           "gd": data["gd"], "igd": data["igd"], "evaluations": data["evaluations"],
           "supersteps": data["supersteps"]}
    print(json.dumps(row), flush=True)
    return row


def time_medians(rows: list[dict]) -> list[dict]:
    """Per code and worker count: the median of each timing over the repeats (and, for this
    code, its ratio to the baseline's median where there is one)."""
    timings = ("wall_time_s", "task_cpu_s", "coordinator_s", "imbalance")
    medians = [{"code": c, "workers": p, "runs": len(g),
                **{f"median_{k}": float(np.median([r[k] for r in g])) for k in timings}}
               for c in ("this", "baseline") for p in sorted({r["workers"] for r in rows})
               for g in [[r for r in rows if r["workers"] == p and r["code"] == c]] if g]
    baseline = {m["workers"]: m for m in medians if m["code"] == "baseline"}
    for m in medians:
        if m["code"] == "this" and m["workers"] in baseline:
            m.update({f"ratio_{k}": m[f"median_{k}"] / baseline[m["workers"]][f"median_{k}"]
                      for k in timings})
    return medians


def summarise(rows: list[dict]) -> list[dict]:
    groups: dict[tuple[str, int], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["problem"], row["archive"]), []).append(row)
    return [{"problem": p, "archive": a, "runs": len(g),
             **{f"mean_{k}": float(np.mean([r[k] for r in g])) for k in ("gd", "igd", "hv")},
             **{f"var_{k}": float(np.var([r[k] for r in g])) for k in ("gd", "igd")}}
            for (p, a), g in sorted(groups.items())]


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.5))
    labels, gds, igds = [], [], []
    for group in report["summary"]:
        rows = [r for r in report["quality"]
                if r["problem"] == group["problem"] and r["archive"] == group["archive"]]
        labels.append(f"{group['problem']}\narchive {group['archive']}")
        gds.append([r["gd"] for r in rows])
        igds.append([r["igd"] for r in rows])
    for ax, data, name, target in ((axes[0], gds, "GD", 5e-3), (axes[1], igds, "IGD", 0.025)):
        if data:
            ax.boxplot(data, tick_labels=labels)
        ax.axhline(target, color="tab:red", ls=":", label=f"target {target:g}")
        ax.set_yscale("log")
        ax.set_title(f"{name} over seeds ({report['evaluations']:,} evaluations)")
        ax.legend()
    rows = report["time_medians"]
    x = np.arange(len(rows))
    axes[2].bar(x - 0.2, [r["median_wall_time_s"] for r in rows], 0.4, label="wall")
    axes[2].bar(x + 0.2, [r["median_task_cpu_s"] for r in rows], 0.4, label="task CPU")
    axes[2].set_xticks(x, [f"{r['workers']}" + ("" if r["code"] == "this" else "\nbaseline")
                           for r in rows])
    position = {(r["code"], r["workers"]): i for i, r in enumerate(rows)}
    for r in report["time"]:
        axes[2].plot(position[r["code"], r["workers"]] - 0.2, r["wall_time_s"], "k.")
    axes[2].axhline(15, color="tab:red", ls=":", label="target 15 s on 2 workers")
    axes[2].set_xlabel("MPI ranks")
    axes[2].set_ylabel("seconds (median; dots: each run)")
    axes[2].set_title(f"Goddard, {report['evaluations']:,} evaluations")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("quality", "time", "all"), default="all")
    parser.add_argument("--problems", nargs="+", default=["goddard", "orbit-raising"])
    parser.add_argument("--archives", nargs="+", type=int, default=[20, 10])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--evaluations", type=int, default=10_000)
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per worker count")
    parser.add_argument("--restoration", choices=RESTORATIONS, default="centred",
                        help="MacsSettings.restoration of this code's runs")
    parser.add_argument("--baseline", type=Path, default=None,
                        help="a src directory of other code to time alternately with this one")
    parser.add_argument("--processes", type=int, default=2,
                        help="quality runs in parallel (one serial run per process)")
    parser.add_argument("--output", type=Path, default=Path("runs/macs-bench"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report: dict = {"evaluations": args.evaluations, "restoration": args.restoration,
                    "quality": [], "summary": [], "time": [],
                    "time_medians": [],
                    "paper_table_III": PAPER_TABLE_III}
    if args.part in ("time", "all"):
        sources = [None] if args.baseline is None else [None, args.baseline]
        report["time"] = [time_run(p, i, args.evaluations, args.output, args.restoration,
                                   source)
                          for i in range(args.repeats) for p in args.workers
                          for source in sources]
        report["time_medians"] = time_medians(report["time"])
        for row in report["time_medians"]:
            print(json.dumps(row))
    if args.part in ("quality", "all"):
        jobs = [(p, a, s, args.evaluations, args.restoration) for p in args.problems
                for a in args.archives for s in range(args.seeds)]
        with ProcessPoolExecutor(args.processes) as pool:
            report["quality"] = list(pool.map(quality_run, jobs))
        report["summary"] = summarise(report["quality"])
        for group in report["summary"]:
            print(json.dumps(group))
    (args.output / "macs_bench.json").write_text(json.dumps(report, indent=1))
    plot(report, args.output / "macs_bench.png")
    print(f"wrote {args.output / 'macs_bench.json'} and {args.output / 'macs_bench.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
