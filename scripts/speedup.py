#!/usr/bin/env python
"""Speedup of the formation scheme versus worker count, per backend.

    python scripts/speedup.py --agents 60 --backend mpi dask --workers 1 2 --repeat 3 \
        --output runs/speedup

Each (backend, workers, repetition) is one run of ``python -m ocpar.formation`` (under
``mpirun -n P`` for mpi) in its own process, writing its result.json. The script gathers
their superstep traces and writes ``speedup.json`` (per backend and worker count: median solve
wall time, median superstep time, speedup and efficiency against 1 worker of the same backend,
median superstep overhead, load imbalance = max/mean worker busy time, and the spread of total
costs across all runs) and ``speedup.png`` (speedup vs workers, ideal line, the paper's
Table I for reference). Times exclude process start-up and cluster start.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

PAPER_TABLE_I = {2: 2.15, 4: 5.57, 8: 9.65, 16: 15.73, 32: 34.94, 64: 53.0}


def run_once(backend: str, workers: int, agents: int, out: Path) -> dict:
    """One formation run in a fresh process; returns its result.json."""
    cmd = [sys.executable, "-m", "ocpar.formation", "--agents", str(agents), "--quiet",
           "--output", str(out)]
    if backend == "mpi":
        cmd = [str(Path(sys.executable).parent / "mpirun"), "-n", str(workers), *cmd]
    else:
        cmd += ["--backend", backend] + (["--workers", str(workers)] if backend == "dask" else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"run failed ({' '.join(cmd)}):\n{proc.stderr[-2000:]}")
    return json.loads((out / "result.json").read_text())


def summarise(runs: list[dict]) -> dict:
    """Medians over repetitions (and over supersteps within each run)."""
    steps = [t for r in runs for t in r["trace"]]
    busy = [t["worker_busy_s"] for t in steps]
    return {
        "runs": len(runs),
        "wall_time_s": statistics.median(r["wall_time_s"] for r in runs),
        "superstep_s": statistics.median(t["wall_s"] for t in steps),
        "overhead_s": statistics.median(t["overhead_s"] for t in steps),
        "imbalance": statistics.median(max(b) / (sum(b) / len(b)) for b in busy),
        "solve_ms": 1e3 * statistics.median(x for t in steps for x in t["task_wall_s"]),
        "total_cost": runs[0]["total_cost"],
    }


def plot(table: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    top = max([2, *(int(p) for rows in table.values() for p in rows)])
    ax.plot([1, top], [1, top], "k--", lw=0.8, label="ideal")
    for backend, rows in table.items():
        ps = sorted(int(p) for p in rows)
        ax.plot(ps, [rows[str(p)]["speedup"] for p in ps], "o-", label=backend)
    paper = {p: s for p, s in PAPER_TABLE_I.items() if p <= max(top, 2)}
    ax.plot(list(paper), list(paper.values()), "s:", color="grey",
            label="paper Table I (PUB, 60 point masses)")
    ax.set_xlabel("workers")
    ax.set_ylabel("speedup (superstep wall time vs 1 worker)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=60)
    parser.add_argument("--backend", nargs="+", choices=("serial", "mpi", "dask"),
                        default=["mpi", "dask"])
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--output", type=Path, default=Path("runs/speedup"))
    args = parser.parse_args()
    if 1 not in args.workers:
        parser.error("--workers must include 1 (the speedup baseline)")
    args.output.mkdir(parents=True, exist_ok=True)

    table: dict[str, dict[str, dict]] = {}
    costs = []
    for backend in args.backend:
        counts = [1] if backend == "serial" else sorted(set(args.workers))
        for p in counts:
            runs = []
            for rep in range(args.repeat):
                out = args.output / f"{backend}-{p}-{rep}"
                runs.append(run_once(backend, p, args.agents, out))
                print(f"{backend:6s} workers {p:2d} rep {rep}: "
                      f"{runs[-1]['wall_time_s']:.3f} s", flush=True)
            table.setdefault(backend, {})[str(p)] = summarise(runs)
            costs += [r["total_cost"] for r in runs]
        base = table[backend]["1"]["superstep_s"]
        for p, row in table[backend].items():
            row["speedup"] = base / row["superstep_s"]
            row["efficiency"] = row["speedup"] / int(p)

    spread = (max(costs) - min(costs)) / abs(min(costs))
    report = {"scheme": "formation", "agents": args.agents, "repeat": args.repeat,
              "total_cost_relative_spread": spread, "backends": table,
              "paper_table_I": PAPER_TABLE_I}
    (args.output / "speedup.json").write_text(json.dumps(report, indent=1))
    plot(table, args.output / "speedup.png")

    print(f"\n{'backend':8s}{'P':>3s}{'superstep ms':>14s}{'speedup':>9s}{'effic.':>8s}"
          f"{'overhead ms':>13s}{'imbalance':>11s}{'solve ms':>10s}")
    for backend, rows in table.items():
        for p in sorted(rows, key=int):
            r = rows[p]
            print(f"{backend:8s}{p:>3s}{r['superstep_s'] * 1e3:14.1f}{r['speedup']:9.2f}"
                  f"{r['efficiency']:8.2f}{r['overhead_s'] * 1e3:13.1f}{r['imbalance']:11.2f}"
                  f"{r['solve_ms']:10.3f}")
    print(f"total cost relative spread over all runs: {spread:.1e}")
    print(f"wrote {args.output / 'speedup.json'} and {args.output / 'speedup.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
