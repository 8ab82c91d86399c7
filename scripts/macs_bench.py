#!/usr/bin/env python
"""MACS benchmark: front quality over seeds, and wall time versus workers.

    python scripts/macs_bench.py --output runs/macs-bench
    python scripts/macs_bench.py --part quality --seeds 10 --archives 20 10 --output DIR
    python scripts/macs_bench.py --part time --workers 1 2 --output DIR

``quality``: for each problem, archive size and seed, one 10,000-evaluation run (serial
backend, two runs at a time in separate processes): GD, IGD, HV of the re-simulated archive
against the reference front; mean and variance per problem and archive size (the paper's
Table III reports mean GD/IGD over 30 runs with a 10-member archive).
``time``: ``mpirun -n P python -m ocpar.macs --problem goddard`` (10,000 evaluations) per
worker count: the solve's wall time.

Writes ``macs_bench.json`` and ``macs_bench.png``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

PAPER_TABLE_III = {"goddard": {"gd": 2.833e-2, "igd": 2.9449e-2},
                   "orbit-raising": {"gd": 5.9444e-2, "igd": 4.387e-2}}


def quality_run(job: tuple[str, int, int, int]) -> dict:
    """One serial MACS run in this (worker) process."""
    from ocpar.macs import MacsSettings, make_problem, solve_macs

    problem, archive, seed, evaluations = job
    result = solve_macs(make_problem(problem),
                        MacsSettings(max_evaluations=evaluations, archive_size=archive, seed=seed))
    row = {"problem": problem, "archive": archive, "seed": seed, "gd": result.gd,
           "igd": result.igd, "hv": result.hv, "evaluations": result.evaluations,
           "wall_time_s": result.wall_time_s}
    print(json.dumps(row), flush=True)
    return row


def time_run(workers: int, output: Path) -> dict:
    out = output / f"time-goddard-mpi-{workers}"
    cmd = [str(Path(sys.executable).parent / "mpirun"), "-n", str(workers), sys.executable,
           "-m", "ocpar.macs", "--problem", "goddard", "--archive", "20", "--quiet",
           "--output", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    data = json.loads((out / "result.json").read_text())
    row = {"workers": workers, "wall_time_s": data["wall_time_s"], "gd": data["gd"],
           "igd": data["igd"], "evaluations": data["evaluations"],
           "supersteps": data["supersteps"]}
    print(json.dumps(row), flush=True)
    return row


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
        ax.set_title(f"{name} over seeds (10,000 evaluations)")
        ax.legend()
    rows = sorted(report["time"], key=lambda r: r["workers"])
    axes[2].bar([str(r["workers"]) for r in rows], [r["wall_time_s"] for r in rows])
    axes[2].axhline(30, color="tab:red", ls=":", label="target 30 s on 2 workers")
    axes[2].set_xlabel("MPI ranks")
    axes[2].set_ylabel("wall time (s)")
    axes[2].set_title("Goddard, 10,000 evaluations")
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
    parser.add_argument("--processes", type=int, default=2,
                        help="quality runs in parallel (one serial run per process)")
    parser.add_argument("--output", type=Path, default=Path("runs/macs-bench"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report: dict = {"quality": [], "summary": [], "time": [], "paper_table_III": PAPER_TABLE_III}
    if args.part in ("time", "all"):
        report["time"] = [time_run(p, args.output) for p in args.workers]
    if args.part in ("quality", "all"):
        jobs = [(p, a, s, args.evaluations) for p in args.problems for a in args.archives
                for s in range(args.seeds)]
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
