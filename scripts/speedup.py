#!/usr/bin/env python
"""Speedup versus worker count of any scheme, per backend, with a BSP cost model's prediction.

    python scripts/speedup.py --scheme formation --agents 60 --backend mpi dask \
        --workers 1 2 --repeat 3 --output runs/speedup
    python scripts/speedup.py --scheme pursuit --samples 301 --backend mpi --workers 1 2
    python scripts/speedup.py --scheme macs --problem goddard --max-evals 2000 --backend mpi
    python scripts/speedup.py ... --predict-agents 1000     # formation: model at 1000 agents

Each (backend, workers, repetition) is one run of ``python -m ocpar.<scheme>`` in its own
process (``mpirun -n P`` for mpi, ``mpirun -n P+2`` for dask-mpi), writing its result.json;
the serial backend is always run too. Repetitions are outermost (every configuration once,
then again), so that a drift in the machine's speed affects all configurations alike.
The script gathers their superstep traces and writes

* ``speedup.json``: per backend and worker count the median solve wall time (process and
  cluster start-up excluded), speedup and efficiency against the fastest serial
  configuration of the run (the 1-worker configuration, serial backend or not, with the
  smallest median wall time: ``baseline``), the same against 1 worker of the same backend
  (``speedup_same_backend``, ``efficiency_same_backend``), median superstep time and its
  speedup against 1 worker of the same backend, median per-superstep overhead (wall −
  busiest worker) and load imbalance (max/mean worker busy time); the cost model's
  predictions (P = 1 … 64, both partitioning policies) from each backend's 1-worker runs,
  also rescaled to the fastest serial configuration, and its error at the measured 2-worker
  point;
* ``speedup.png``: measured and predicted speedup against the fastest serial configuration
  vs workers, the ideal line and the paper's table.

The cost model (``ocpar.bsp.cost_model``) schedules a run's measured per-task CPU times on P
workers and adds the per-superstep synchronisation cost fitted to the measured overheads, and
the coordinator's serial time. ``--predict-agents N`` (formation) also runs one N-agent
formation on 1 worker of the MPI backend (else the first backend) and predicts its speedup,
with a = that run's own per-superstep overhead (it grows with the task count) and b of the
fit above.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

from ocpar.bsp.cost_model import (
    POLICIES,
    Prediction,
    SyncCost,
    median_overhead,
    predict,
    serial_time,
    task_times,
)
from ocpar.result_files import load_trace, read_summary

#: Speedups the PUB implementation reported (hierarchical-formation paper, Tables I and II),
#: by formation problem.
PAPER_TABLES = {
    "point-mass-plane": ("paper Table I (PUB, 60 point masses)",
                         {2: 2.15, 4: 5.57, 8: 9.65, 16: 15.73, 32: 34.94, 64: 53.0}),
    "crtbp-rigid": ("paper Table II (PUB, 30 rigid spacecraft)",
                    {2: 2.11, 4: 3.77, 8: 6.75, 16: 10.49, 32: 18.89}),
}
PREDICT_WORKERS = (1, 2, 4, 8, 16, 32, 64)
BACKENDS = ("serial", "mpi", "dask", "dask-mpi")


def scheme_arguments(args: argparse.Namespace) -> list[str]:
    """The scheme's own command-line options for this benchmark."""
    if args.scheme == "formation":
        agents = [] if args.agents is None else ["--agents", str(args.agents)]
        return ["--problem", args.problem or "point-mass-plane", *agents, "--outer", args.outer]
    if args.scheme == "pursuit":
        return ["--case", str(args.case), "--samples", str(args.samples), "--no-reference"]
    return ["--problem", args.problem or "goddard", "--max-evals", str(args.max_evals), "--seed",
            "0"]


def command(scheme: str, backend: str, workers: int, extra: list[str], balance: str,
            out: Path) -> list[str]:
    """The command line of one run."""
    mpirun = str(Path(sys.executable).parent / "mpirun")
    cmd = [sys.executable, "-m", f"ocpar.{scheme}", *extra, "--balance", balance, "--quiet",
           "--output", str(out)]
    if backend == "mpi":
        return [mpirun, "-n", str(workers), *cmd]
    if backend == "dask-mpi":
        return [mpirun, "-n", str(workers + 2), *cmd, "--backend", "dask-mpi"]
    if backend == "dask":
        return [*cmd, "--backend", "dask", "--workers", str(workers)]
    return [*cmd, "--backend", "serial"]


def run_once(cmd: list[str], out: Path) -> dict:
    """One run in a fresh process; returns its result.json. A run that ends with a status
    other than success (e.g. a failed inner solve) still has a trace to time: it is used and
    its status is reported; a run without result.json stops the benchmark."""
    proc = subprocess.run(cmd, capture_output=True, text=True)
    path = out / "result.json"
    if proc.returncode != 0 and not path.exists():
        raise SystemExit(f"run failed ({' '.join(cmd)}):\n{proc.stderr[-2000:]}")
    result = read_summary(out) | {"trace": load_trace(out)}
    if proc.returncode != 0:
        print(f"note: {' '.join(cmd[-8:])} ended with status {result.get('status')!r}: "
              f"{result.get('message', '')}", flush=True)
    return result


def summarise(runs: list[dict]) -> dict:
    """Medians over repetitions (and over supersteps within each run)."""
    steps = [t for r in runs for t in r["trace"]]
    return {
        "runs": len(runs),
        "wall_time_s": statistics.median(r["wall_time_s"] for r in runs),
        "superstep_s": statistics.median(t["wall_s"] for t in steps),
        "supersteps": statistics.median(len(r["trace"]) for r in runs),
        "overhead_s": median_overhead(steps),
        "imbalance": statistics.median(t["imbalance"] for t in steps),
        "task_ms": 1e3 * statistics.median(x for t in steps for x in t["task_wall_s"]),
    }


def model_of(runs: list[dict], sync: SyncCost, workers: list[int],
             baseline_s: float | None = None) -> dict:
    """Predictions from the median-wall-time run of ``runs`` (1 worker) for each policy;
    with ``baseline_s`` (s, the fastest serial configuration's median wall time) each also
    gets ``speedup_vs_baseline``: the model's speedup rescaled by baseline_s / that run's
    median wall time."""
    run = sorted(runs, key=lambda r: r["wall_time_s"])[len(runs) // 2]
    tasks = task_times(run["trace"], use="cpu")
    serial = serial_time(run["wall_time_s"], run["trace"])
    scale = {} if baseline_s is None else {"factor": baseline_s / run["wall_time_s"]}

    def row(p: Prediction) -> dict:
        return vars(p) | ({"speedup_vs_baseline": p.speedup * scale["factor"]} if scale
                          else {})

    return {"sync": {"a_s": sync.a_s, "b_s": sync.b_s}, "serial_s": serial,
            "tasks_per_superstep": statistics.median(len(t) for t in tasks),
            "policies": {policy: [row(p) for p in predict(tasks, workers, policy, sync, serial)]
                         for policy in POLICIES}}


def headline_key(result: dict) -> str:
    """The name of the scheme's headline figure in ``result`` (a result.json)."""
    for key in ("total_cost", "final_mass_kg", "hv"):
        if key in result:
            return key
    raise KeyError("result.json has no headline figure")


def headline(result: dict) -> float:
    """The scheme's headline figure, compared across all runs (must not depend on P)."""
    return float(result[headline_key(result)])


def plot(table: dict, models: dict, paper: tuple[str, dict] | None, baseline: str,
         path: Path) -> None:
    from ocpar.plotting import pyplot, save

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    top = max([2, *(int(p) for rows in table.values() for p in rows)])
    top_model = max([top, *(p["workers"] for m in models.values()
                            for p in m["policies"]["blocks"])])
    ax.plot([1, top_model], [1, top_model], "k--", lw=0.8, label="ideal")
    for backend, rows in table.items():
        ps = sorted(int(p) for p in rows)
        (line,) = ax.plot(ps, [rows[str(p)]["speedup"] for p in ps], "o-",
                          label=f"{backend}, measured")
        if backend in models:
            predicted = models[backend]["policies"]["blocks"]
            ax.plot([p["workers"] for p in predicted],
                    [p["speedup_vs_baseline"] for p in predicted], ":",
                    color=line.get_color(), label=f"{backend}, cost model (blocks)")
    if paper is not None:
        label, speedups = paper
        ax.plot(list(speedups), list(speedups.values()), "s:", color="grey", label=label)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log", base=2)
    ax.set_xlabel("workers")
    ax.set_ylabel(f"speedup (solve wall time vs {baseline})")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    save(fig, path)


def print_table(table: dict, models: dict, baseline: str) -> None:
    print(f"\nspeedup and efficiency against the fastest serial configuration ({baseline}); "
          "'same': against 1 worker of the same backend; model: cost model, same backend")
    print(f"{'backend':9s}{'P':>3s}{'wall s':>9s}{'speedup':>9s}{'effic.':>8s}{'same':>7s}"
          f"{'step ms':>9s}{'step speedup':>14s}{'overhead ms':>13s}{'imbalance':>11s}"
          f"{'model':>8s}")
    for backend, rows in table.items():
        predicted = {p["workers"]: p for p in models.get(backend, {}).get(
            "policies", {}).get("blocks", [])}
        for p in sorted(rows, key=int):
            r = rows[p]
            model = predicted.get(int(p))
            print(f"{backend:9s}{p:>3s}{r['wall_time_s']:9.3f}{r['speedup']:9.2f}"
                  f"{r['efficiency']:8.2f}{r['speedup_same_backend']:7.2f}"
                  f"{r['superstep_s'] * 1e3:9.1f}"
                  f"{r['superstep_speedup']:14.2f}{r['overhead_s'] * 1e3:13.1f}"
                  f"{r['imbalance']:11.2f}{model['speedup'] if model else float('nan'):8.2f}")


def print_predictions(title: str, model: dict) -> None:
    print(f"\ncost model, {title}: serial part {model['serial_s']:.3f} s, sync "
          f"{model['sync']['a_s'] * 1e3:.2f} ms + {model['sync']['b_s'] * 1e3:.2f} ms·log2 P "
          f"per superstep")
    print(f"{'P':>4s}" + "".join(f"{policy + ' wall s':>14s}{'speedup':>9s}{'effic.':>8s}"
                                 for policy in POLICIES))
    rows = zip(*(model["policies"][policy] for policy in POLICIES), strict=True)
    for row in rows:
        print(f"{row[0]['workers']:4d}" + "".join(
            f"{p['wall_s']:14.3f}{p['speedup']:9.2f}{p['efficiency']:8.2f}" for p in row))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scheme", choices=("formation", "pursuit", "macs"),
                        default="formation")
    parser.add_argument("--agents", type=int, default=None,
                        help="formation: agents (default: the problem's)")
    parser.add_argument("--outer", choices=("newton", "sqp", "offset"), default="newton",
                        help="formation: outer solver")
    parser.add_argument("--case", type=int, default=1, help="pursuit: case 1 or 2")
    parser.add_argument("--samples", type=int, default=301, help="pursuit: samples N")
    parser.add_argument("--problem", default=None,
                        help="formation: point-mass-plane (default) | crtbp-rigid; "
                             "macs: goddard (default) | orbit-raising")
    parser.add_argument("--max-evals", type=int, default=2000, help="macs: evaluations")
    parser.add_argument("--backend", nargs="+", choices=BACKENDS, default=["mpi", "dask"],
                        help="backends to measure (the serial backend is always run too: "
                             "the baseline)")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--balance", choices=("blocks", "lpt"), default="blocks")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--predict-workers", nargs="+", type=int, default=list(PREDICT_WORKERS))
    parser.add_argument("--predict-agents", type=int, default=None,
                        help="formation: also predict a run with this many agents")
    parser.add_argument("--output", type=Path, default=Path("runs/speedup"))
    args = parser.parse_args()
    if 1 not in args.workers or min(args.workers) < 1:
        parser.error("--workers must be positive and include 1 (the speedup baseline)")
    if args.predict_agents is not None and args.scheme != "formation":
        parser.error("--predict-agents applies to --scheme formation")
    args.output.mkdir(parents=True, exist_ok=True)
    extra = scheme_arguments(args)
    paper = (PAPER_TABLES.get(args.problem or "point-mass-plane")
             if args.scheme == "formation" else None)

    table: dict[str, dict[str, dict]] = {}
    models: dict[str, dict] = {}
    raw: dict[str, dict[int, list[dict]]] = {}
    figures = []
    # repetitions outermost: a drift in the machine's speed hits every configuration alike
    backends = ["serial", *(b for b in args.backend if b != "serial")]
    configurations = [(backend, p) for backend in backends
                      for p in ([1] if backend == "serial" else sorted(set(args.workers)))]
    for rep in range(args.repeat):
        for backend, p in configurations:
            out = args.output / f"{args.scheme}-{backend}-{p}-{rep}"
            result = run_once(command(args.scheme, backend, p, extra, args.balance, out), out)
            raw.setdefault(backend, {}).setdefault(p, []).append(result)
            figures.append(headline(result))
            print(f"{backend:8s} workers {p:2d} rep {rep}: {result['wall_time_s']:.3f} s",
                  flush=True)
    for backend, p in configurations:
        table.setdefault(backend, {})[str(p)] = summarise(raw[backend][p])
    # the baseline: the fastest serial (1-worker) configuration measured in this run
    baseline = min(table, key=lambda b: table[b]["1"]["wall_time_s"])
    baseline_s = table[baseline]["1"]["wall_time_s"]
    for backend in backends:
        base = table[backend]["1"]
        for p, row in table[backend].items():
            row["speedup"] = baseline_s / row["wall_time_s"]
            row["efficiency"] = row["speedup"] / int(p)
            row["speedup_same_backend"] = base["wall_time_s"] / row["wall_time_s"]
            row["efficiency_same_backend"] = row["speedup_same_backend"] / int(p)
            row["superstep_speedup"] = base["superstep_s"] / row["superstep_s"]
    for backend in args.backend:
        sync = SyncCost.fit({p: table[backend][str(p)]["overhead_s"] for p in raw[backend]})
        models[backend] = model_of(raw[backend][1], sync, sorted(set(args.predict_workers)
                                                                | set(raw[backend])),
                                   baseline_s)
        if "2" in table[backend]:
            predicted = next(p for p in models[backend]["policies"][args.balance]
                             if p["workers"] == 2)
            measured = table[backend]["2"]["speedup_same_backend"]
            models[backend]["check_2_workers"] = {
                "measured_speedup": measured, "predicted_speedup": predicted["speedup"],
                "relative_error": predicted["speedup"] / measured - 1}

    report = {"scheme": args.scheme, "arguments": extra, "balance": args.balance,
              "repeat": args.repeat, "baseline": {"backend": baseline, "workers": 1,
                                                  "wall_time_s": baseline_s},
              "backends": table, "models": models,
              "headline_relative_spread": (max(figures) - min(figures))
              / max(abs(min(figures)), 1e-300),
              "paper": paper[1] if paper else {}}
    if args.predict_agents is not None:
        # the large run on 1 worker of the backend whose synchronisation cost is used: its
        # overheads include the per-task packing and unpacking at that task count, which a
        # fit at the small size cannot see (conservative: at P workers the workers' part of
        # it is shared among them)
        sync_backend = "mpi" if "mpi" in models else next(iter(models))
        big = args.output / f"formation-{sync_backend}-1-{args.predict_agents}-agents"
        result = run_once(command("formation", sync_backend, 1,
                                  ["--problem", args.problem or "point-mass-plane",
                                   "--agents", str(args.predict_agents), "--outer", args.outer],
                                  args.balance, big), big)
        sync = SyncCost(a_s=median_overhead(result["trace"]),
                        b_s=models[sync_backend]["sync"]["b_s"])
        report["prediction_large"] = {"agents": args.predict_agents, "sync_from": sync_backend,
                                      "status": result.get("status"),
                                      "wall_time_s": result["wall_time_s"],
                                      **model_of([result], sync, sorted(set(
                                          args.predict_workers)))}
    (args.output / "speedup.json").write_text(json.dumps(report, indent=1))
    plot(table, models, paper, f"fastest serial: {baseline}", args.output / "speedup.png")

    print_table(table, models, baseline)
    for backend, model in models.items():
        print_predictions(f"{backend}, from its 1-worker runs", model)
        if check := model.get("check_2_workers"):
            print(f"  2 workers: measured speedup {check['measured_speedup']:.2f}, predicted "
                  f"{check['predicted_speedup']:.2f} ({check['relative_error']:+.1%})")
    if "prediction_large" in report:
        large = report["prediction_large"]
        print_predictions(f"{large['agents']} agents (1-worker {large['sync_from']} run: its "
                          f"overhead, b of the fit above)", large)
    print(f"headline figure's relative spread over all runs: "
          f"{report['headline_relative_spread']:.1e}")
    print(f"wrote {args.output / 'speedup.json'} and {args.output / 'speedup.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
