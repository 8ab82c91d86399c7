#!/usr/bin/env python
"""PBMS benchmark: wall time versus workers on case 1, and peak memory versus N.

    python scripts/pursuit_bench.py --output runs/pursuit-bench            # both parts
    python scripts/pursuit_bench.py --part time --workers 1 2 --output DIR
    python scripts/pursuit_bench.py --part memory --samples 501 1001 2001 --output DIR

``time``: case 1, N = 301, N_Δ = 60, N_δ = 32, ε = 1e-5 kg (the paper's Table II setting),
one ``mpirun -n P python -m ocpar.pursuit`` per worker count (and the Dask backend if asked):
solve wall time, agents, final mass, supersteps.

``memory``: case 2 with N_Δ = 100, N_δ = 81 (the paper's N = 2001 setting) for each N: PBMS on
2 MPI ranks (peak resident memory of the largest worker, agents, final mass, wall time) and
full-horizon MS on one rank (its peak memory grows with N; PBMS's must not).

Writes ``pursuit_bench.json`` and ``pursuit_bench.png``. Times exclude process start-up.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

MPIRUN = str(Path(sys.executable).parent / "mpirun")


def run(args: list[str], out: Path, backend: str, workers: int) -> dict:
    """One ``python -m ocpar.pursuit`` run; returns its result.json (without bulky fields)."""
    cmd = [sys.executable, "-m", "ocpar.pursuit", *args, "--quiet", "--no-reference",
           "--output", str(out)]
    if backend == "mpi":
        cmd = [MPIRUN, "-n", str(workers), *cmd]
    else:
        cmd += ["--backend", "dask", "--workers", str(workers)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"failed: {' '.join(cmd)}\n{proc.stderr[-2000:]}")
    data = json.loads((out / "result.json").read_text())
    keep = ("mode", "problem", "samples", "window", "update", "epsilon", "backend", "workers",
            "status", "message", "final_mass_kg", "agents", "subproblem_solves",
            "failed_solves", "supersteps", "max_agents_in_flight", "wall_time_s",
            "peak_rss_mb_per_worker", "rk_final_altitude_error_m")
    row = {k: data[k] for k in keep}
    print(json.dumps(row), flush=True)
    return row


def time_part(workers: list[int], backends: list[str], output: Path) -> list[dict]:
    args = ["--case", "1", "--samples", "301", "--window", "60", "--update", "32",
            "--epsilon", "1e-5"]
    return [run(args, output / f"time-{b}-{p}", b, p) for b in backends for p in workers]


def memory_part(samples: list[int], epsilon: float, output: Path) -> list[dict]:
    rows = []
    for n in samples:
        args = ["--case", "2", "--samples", str(n), "--window", "100", "--update", "81"]
        rows.append(run([*args, "--epsilon", str(epsilon)], output / f"memory-pbms-{n}", "mpi", 2))
        rows.append(run([*args, "--mode", "ms"], output / f"memory-ms-{n}", "mpi", 1))
    return rows


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(11, 4.5))
    for backend in sorted({r["backend"] for r in report["time"]}):
        rows = sorted((r for r in report["time"] if r["backend"] == backend),
                      key=lambda r: r["workers"])
        ax_t.plot([r["workers"] for r in rows], [r["wall_time_s"] for r in rows], "o-",
                  label=backend)
    ax_t.axhline(60, color="grey", ls=":", label="target 60 s")
    ax_t.set_xlabel("workers")
    ax_t.set_ylabel("wall time (s)")
    ax_t.set_title("case 1, N = 301, N_Δ = 60, N_δ = 32")
    ax_t.legend()
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
    parser.add_argument("--part", choices=("time", "memory", "all"), default="all")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--backend", nargs="+", choices=("mpi", "dask"), default=["mpi"])
    parser.add_argument("--samples", nargs="+", type=int, default=[501, 1001, 2001])
    parser.add_argument("--epsilon", type=float, default=1e-3,
                        help="stopping threshold of the memory part (kg), default 1e-3")
    parser.add_argument("--output", type=Path, default=Path("runs/pursuit-bench"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report: dict = {"time": [], "memory": []}
    if args.part in ("time", "all"):
        report["time"] = time_part(args.workers, args.backend, args.output)
    if args.part in ("memory", "all"):
        report["memory"] = memory_part(args.samples, args.epsilon, args.output)
    (args.output / "pursuit_bench.json").write_text(json.dumps(report, indent=1))
    plot(report, args.output / "pursuit_bench.png")
    print(f"wrote {args.output / 'pursuit_bench.json'} and {args.output / 'pursuit_bench.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
