#!/usr/bin/env python
"""The scaling table: the whole process and the solve on 1 … P workers, per backend and size,
each run a fresh process started as a user starts it.

    python scripts/scaling.py --agents 10000 100000 --backend mpi dask --workers 1 2 4 8 16 \
        --repeat 5 --output runs/scaling
    python scripts/scaling.py --agents 1000000 --backend mpi dask --workers 1 2 4 8 16 \
        --repeat 3 --output runs/scaling-1m
    python scripts/scaling.py --scheme pursuit --backend mpi dask --workers 1 2 4 8 16 \
        --repeat 3 --output runs/scaling-pursuit          # case 1, N = 301, the paper's train
    python scripts/scaling.py --scheme macs --backend mpi dask --workers 1 2 4 8 16 \
        --repeat 3 --output runs/scaling-macs             # Goddard, 10,000 evaluations
    python scripts/scaling.py --agents 10000 100000 --backend mpi dask --repeat 5 \
        --compare-with /work/wt-e1ba789 --output runs/scaling-ab   # before/after, alternating

Configurations: the serial backend (always: a 1-worker baseline), and for each backend of
``--backend`` (``mpi``: ``mpirun -n P python -m ocpar.SCHEME``; ``dask``: ``python -m
ocpar.SCHEME --backend dask --workers P``, its embedded cluster) each P of ``--workers``
(1 always included; P above ``os.cpu_count()`` dropped unless ``--oversubscribe``, and for
the formation P above the number of agents). Sizes: the formation's ``--agents`` (default
10,000 and 100,000); pursuit at the paper's size (``--case 1 --samples 301``, the paper's
train: ``--no-reference --finish train``); MACS at the paper's (``--problem goddard
--max-evals 10000 --archive 20 --seed 0``). ``--extra="ARGS"`` adds scheme options to every
run (after the script's own, so they win). Repetitions are outermost, then sizes, then
configurations: a drift of the machine hits all alike.

Per run (each from ``python -m ocpar.SCHEME ... --quiet --output DIR`` in a fresh process):

* ``process_s``: the whole process measured from outside, from just before the launch to the
  exit (``mpirun`` and an embedded cluster's start included);
* ``solve_s``: the result's ``wall_time_s``; ``timings``: every entry of result.json's
  ``timings`` (``ocpar.timing``; absent in code older than it);
* from the trace, over all the run's supersteps: ``supersteps``, ``busiest_worker_s`` (the
  busiest worker's busy time summed over supersteps), ``overhead_s`` (Σ wall − busiest
  worker; ``overhead_median_s`` per superstep), ``trace_wall_s`` (Σ wall),
  ``worker_peak_rss_mb`` (per worker, the largest over supersteps). The trace also holds
  supersteps outside the solve where a scheme verifies on the workers (the formation's
  closest approach: its last superstep), and it does not mark them: these sums are the
  run's, not the solve's;
* ``process_peak_rss_mb``: the largest process of the run (``wait4``: the launched process and
  the descendants it waited for);
* the headline figure (total cost, final mass, hypervolume), its bits (``float.hex``);
* ``load_1min``: the load average when the run started.

A run that exits with a non-zero status, leaves no result.json or runs past ``--time-limit``
stops the benchmark with its stderr shown (``scaling.json`` then holds the samples so far,
``incomplete`` says why).

``--compare-with DIR`` runs every configuration also with another checkout of ocpar (DIR holds
``src/ocpar``, e.g. ``git worktree add /work/wt-e1ba789 e1ba789``), right before or after this
checkout's run (the order alternates with the repetition); each checkout's runs get
``PYTHONPATH=CHECKOUT/src`` ahead of the environment's, and before the runs the script checks
that each checkout's code is what a process, ``mpirun``'s ranks and a Dask worker import, and
runs the 60-agent formation once with it (whether its result.json has ``timings``).

Summaries per size, checkout and configuration: medians over the repetitions (peak memory: the
largest). Speedups: solve and whole process, each against the *fastest* 1-worker
configuration of that size (serial, MPI × 1 or Dask × 1, of any checkout measured, by median
``solve_s`` resp. ``process_s``: ``baseline``), efficiency = speedup / P. With
``--compare-with``: ``other_over_this``, the other checkout's medians over this one's (> 1:
this checkout is faster). The headline's spread per size and checkout: its distinct bits and
relative spread (it must not depend on the backend or P).

Writes in ``--output`` (default ``runs/scaling``): ``scaling.json`` (the machine, the
checkouts and their commits, the load average at start and end, every sample, the summaries),
``scaling.png`` (per size: solve and whole-process speedup against P, per backend, with the
ideal line; log2 axes) and ``scaling.md``, the printed Markdown tables (solve; whole process;
with ``--compare-with`` the ratios; where the whole process's time goes at each backend's
largest P). Each run's own files stay in ``--output/SIZE/CONFIGURATION[@other]/`` (the last
repetition's).

The benchmark process keeps its own memory small (it reads each run's result in a short-lived
child process): Linux counts the pages a child had before its ``exec``, so every launched
process's peak RSS is at least the benchmark's own (``benchmark_peak_rss_mb`` in the JSON).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from formation_bench import MPIRUN, launch
from speedup import command, headline_key

from ocpar.timing import PHASES, WORDS

BACKENDS = ("serial", "mpi", "dask")
#: Figures of a run summarised by their median over the repetitions.
MEDIANS = ("process_s", "solve_s", "busiest_worker_s", "overhead_s", "overhead_median_s",
           "trace_wall_s", "supersteps", "inner_solves")
THIS, OTHER = "this", "other"


@dataclass(frozen=True)
class Configuration:
    """``backend`` serial | mpi | dask on ``workers`` workers."""

    backend: str
    workers: int

    @property
    def name(self) -> str:
        return "serial" if self.backend == "serial" else f"{self.backend}x{self.workers}"


@dataclass(frozen=True)
class Checkout:
    """A checkout of ocpar whose ``src`` the runs put ahead on ``PYTHONPATH``; ``key`` this |
    other; ``label`` its short commit (``+`` when it has uncommitted changes) or its name."""

    key: str
    root: Path
    label: str
    commit: str | None
    dirty: bool | None

    @property
    def src(self) -> Path:
        return self.root / "src"

    def pythonpath(self) -> str:
        rest = os.environ.get("PYTHONPATH")
        return str(self.src) + (os.pathsep + rest if rest else "")


@dataclass(frozen=True)
class Size:
    """One problem size: ``key`` (directory and JSON key), ``label`` (tables), ``options``
    (the scheme's command-line options), ``agents`` (formation: caps the worker count)."""

    key: str
    label: str
    options: tuple[str, ...]
    agents: int | None = None


def checkout(key: str, root: Path) -> Checkout:
    """The checkout at ``root``, with its commit where git says it."""
    def git(*words: str) -> str | None:
        try:
            proc = subprocess.run(["git", "-C", str(root), *words], capture_output=True,
                                  text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return proc.stdout.strip() if proc.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    dirty = None if status is None else bool(status)
    label = root.name if commit is None else commit[:7] + ("+" if dirty else "")
    return Checkout(key, root.resolve(), label, commit, dirty)


def sizes(args: argparse.Namespace) -> list[Size]:
    """The sizes of the scheme, with their options (module docstring)."""
    extra = tuple(shlex.split(args.extra))
    if args.scheme == "formation":
        problem = args.problem or "point-mass-plane"
        return [Size(str(n), f"{n:,}", ("--problem", problem, "--agents", str(n), *extra), n)
                for n in args.agents]
    if args.scheme == "pursuit":
        return [Size(f"case{args.case}-N{args.samples}", f"case {args.case}, N = {args.samples}",
                     ("--case", str(args.case), "--samples", str(args.samples),
                      "--no-reference", "--finish", "train", *extra))]
    problem = args.problem or "goddard"
    return [Size(f"{problem}-{args.max_evals}", f"{problem}, {args.max_evals:,} evaluations",
                 ("--problem", problem, "--max-evals", str(args.max_evals), "--archive",
                  str(args.archive), "--seed", "0", *extra))]


def configurations(backends: list[str], workers: list[int]) -> list[Configuration]:
    """The serial backend, then each other backend on each worker count."""
    return [Configuration("serial", 1), *(Configuration(b, p) for b in backends
                                          if b != "serial" for p in workers)]


def own_peak_rss_mb() -> float:
    """This process's peak resident memory (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_figures(out: str) -> dict:
    """The figures of the run in ``out`` (module docstring), read from its result.json and
    trace. Called in a child process: a large run's trace would raise this process's peak
    memory, which Linux then counts in every later run's."""
    from ocpar.result_files import load_trace, read_summary

    result = read_summary(out)
    trace = load_trace(out)
    solve = result["wall_time_s"]
    workers = max((len(t["worker_busy_s"]) for t in trace), default=0)
    key = headline_key(result)
    return {
        "status": result.get("status"),
        "message": str(result.get("message", ""))[:300],
        "solve_s": solve,
        "timings": result.get("timings"),
        "supersteps": len(trace),
        "inner_solves": result.get("inner_solves"),
        "busiest_worker_s": sum(max(t["worker_busy_s"]) for t in trace),
        "overhead_s": sum(t["overhead_s"] for t in trace),
        "overhead_median_s": statistics.median(t["overhead_s"] for t in trace) if trace
        else None,
        "trace_wall_s": sum(t["wall_s"] for t in trace),
        "worker_peak_rss_mb": [max(t["worker_peak_rss_mb"][w] for t in trace
                                   if w < len(t.get("worker_peak_rss_mb", [])))
                               if any(w < len(t.get("worker_peak_rss_mb", [])) for t in trace)
                               else None for w in range(workers)],
        "headline_key": key,
        "headline": float(result[key]),
        "headline_hex": float(result[key]).hex(),
    }


def read_run(out: Path) -> dict:
    """:func:`run_figures` of ``out`` in a fresh child process."""
    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        return pool.submit(run_figures, str(out)).result()


class RunFailed(Exception):
    """A run exited with a non-zero status, left no result.json or ran out of time."""


def measure(cmd: list[str], out: Path, where: Checkout, limit_s: float) -> dict:
    """One run of ``cmd`` with ``where``'s code: its process figures and :func:`run_figures`;
    :class:`RunFailed`, with its stderr, if it failed."""
    load = os.getloadavg()[0]
    process = launch(cmd, out, limit_s, source=where.pythonpath())
    if "status" in process or process["exit_code"] != 0:
        stderr = (out / "stderr.txt").read_text(errors="replace")[-4000:]
        why = process.get("message", f"exit {process['exit_code']}")
        raise RunFailed(f"run failed ({why}): {shlex.join(cmd)}\n  with PYTHONPATH="
                        f"{where.pythonpath()}\n--- its stderr (end) ---\n{stderr}")
    return {"load_1min": load, **process, **read_run(out)}


def check_checkout(where: Checkout, backends: list[str], out: Path, limit_s: float) -> dict:
    """That ``where``'s code is what runs: the ``ocpar`` a process, ``mpirun``'s ranks and a
    Dask worker import with its PYTHONPATH; and one 60-agent formation with it (whether its
    result.json has ``timings``). SystemExit if another ocpar is imported."""
    env = os.environ | {"PYTHONPATH": where.pythonpath()}
    probe = "import ocpar; print(ocpar.__file__)"
    probes = {"process": [sys.executable, "-c", probe]}
    if "mpi" in backends:
        probes["mpirun -n 2"] = [MPIRUN, "-n", "2", sys.executable, "-c", probe]
    if "dask" in backends:
        probes["dask worker"] = [sys.executable, "-c", (
            "from dask.distributed import Client, LocalCluster\n"
            "with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,"
            " dashboard_address=None) as c, Client(c) as client:\n"
            "    print(*client.run(lambda: __import__('ocpar').__file__).values())")]
    found = {}
    for name, cmd in probes.items():
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
        files = proc.stdout.split()
        found[name] = files
        if proc.returncode != 0 or not files or not all(
                Path(f).resolve().is_relative_to(where.src) for f in files):
            raise SystemExit(f"{where.key} checkout {where.root}: {name} imports "
                             f"{files or 'nothing'} instead of {where.src}/ocpar\n"
                             f"{proc.stderr[-2000:]}")
    run = out / f"check-{where.key}"
    cmd = [sys.executable, "-m", "ocpar.formation", "--agents", "60", "--quiet", "--output",
           str(run)]
    process = launch(cmd, run, limit_s, source=where.pythonpath())
    if "status" in process or process["exit_code"] != 0:
        raise SystemExit(f"{where.key} checkout: the 60-agent formation failed:\n"
                         f"{(run / 'stderr.txt').read_text(errors='replace')[-3000:]}")
    has_timings = "timings" in json.loads((run / "result.json").read_text())
    return {"imports": found, "formation_60_has_timings": has_timings}


def median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def summarise(samples: list[dict]) -> dict:
    """Medians over a configuration's repetitions (peak memory: the largest)."""
    row: dict = {"runs": len(samples)}
    for key in MEDIANS:
        row[key] = median([s.get(key) for s in samples])
    names = [k for s in samples for k in (s.get("timings") or {})]
    names = sorted(set(names), key=lambda k: (list(WORDS).index(k) if k in WORDS
                                              else len(WORDS), k))
    row["timings"] = {k: median([(s.get("timings") or {}).get(k) for s in samples])
                      for k in names} or None
    row["outside_s"] = median([s["process_s"] - s["timings"]["total_s"] for s in samples
                               if (s.get("timings") or {}).get("total_s") is not None])
    row["process_peak_rss_mb"] = max(s["process_peak_rss_mb"] for s in samples)
    peaks = [s.get("worker_peak_rss_mb") or [] for s in samples]
    row["worker_peak_rss_mb"] = [
        max((p[w] for p in peaks if w < len(p) and p[w] is not None), default=None)
        for w in range(max(map(len, peaks), default=0))]
    row["load_1min"] = median([s.get("load_1min") for s in samples])
    return row


def add_speedups(rows: dict[str, dict[str, dict]], workers: dict[str, int]) -> dict:
    """Against the fastest 1-worker configuration of any checkout (``rows[checkout][name]``,
    ``workers[name]``), by median solve and by median whole process: each row's
    ``solve_speedup``, ``solve_efficiency``, ``process_speedup``, ``process_efficiency``.
    Returns the baselines."""
    baselines = {}
    for tag in ("solve", "process"):
        metric = f"{tag}_s"
        ones = [(row[metric], key, name) for key, by_name in rows.items()
                for name, row in by_name.items()
                if workers[name] == 1 and row.get(metric) is not None]
        if not ones:
            continue
        best, key, name = min(ones)
        baselines[tag] = {"checkout": key, "configuration": name, "s": best}
        for by_name in rows.values():
            for name, row in by_name.items():
                if row.get(metric):
                    row[f"{tag}_speedup"] = best / row[metric]
                    row[f"{tag}_efficiency"] = row[f"{tag}_speedup"] / workers[name]
    return baselines


def ratios(this: dict, other: dict) -> dict:
    """The other checkout's medians over this one's, per figure (> 1: this is faster)."""
    def ratio(a, b):
        return a / b if a is not None and b else None

    out = {k: ratio(other.get(k), this.get(k)) for k in ("process_s", "solve_s",
                                                          "busiest_worker_s", "overhead_s")}
    mine, theirs = this.get("timings") or {}, other.get("timings") or {}
    out["timings"] = {k: ratio(theirs.get(k), mine[k]) for k in mine if k in theirs}
    return out


def headline_spread(samples: list[dict]) -> dict:
    """The headline figure over ``samples``: its distinct bits (and how many runs gave each)
    and relative spread."""
    values = [s["headline"] for s in samples]
    counts: dict[str, int] = {}
    for s in samples:
        counts[s["headline_hex"]] = counts.get(s["headline_hex"], 0) + 1
    low, high = min(values), max(values)
    return {"key": samples[0]["headline_key"], "runs": len(samples), "values": counts,
            "identical_bits": len(counts) == 1,
            "relative_spread": (high - low) / max(abs(low), 1e-300)}


def summaries(samples: list[dict], size_list: list[Size],
              configs: dict[str, list[Configuration]], checkouts: list[Checkout]) -> dict:
    """Per size: the summaries per checkout and configuration, the baselines and speedups,
    the headline's spread and, with two checkouts, their ratios."""
    report = {}
    for size in size_list:
        at = [s for s in samples if s["size"] == size.key]
        workers = {c.name: c.workers for c in configs[size.key]}
        rows: dict[str, dict[str, dict]] = {}
        for where in checkouts:
            for c in configs[size.key]:
                mine = [s for s in at if s["checkout"] == where.key
                        and s["configuration"] == c.name]
                if mine:
                    rows.setdefault(where.key, {})[c.name] = summarise(mine)
        entry: dict = {"label": size.label, "options": list(size.options),
                       "configurations": rows, "baseline": add_speedups(rows, workers)}
        entry["headline"] = {key: headline_spread([s for s in at if s["checkout"] == key])
                             for key in rows}
        if len(entry["headline"]) > 1:
            entry["headline_same_across_checkouts"] = len(
                {h for spread in entry["headline"].values() for h in spread["values"]}) == 1
        if OTHER in rows and THIS in rows:
            entry["other_over_this"] = {name: ratios(rows[THIS][name], rows[OTHER][name])
                                        for name in rows[THIS] if name in rows[OTHER]}
        report[size.key] = entry
    return report


def seconds(t: float | None) -> str:
    if t is None:
        return "–"
    return f"{t:.0f} s" if t >= 100 else f"{t:.3g} s"


def markdown(report: dict) -> str:
    """The tables of the report (module docstring), in Markdown."""
    labels = {k: c["label"] for k, c in report["checkouts"].items()}
    compare = len(labels) > 1
    head = "agents" if report["scheme"] == "formation" else "size"
    ps = sorted({c["workers"] for cs in report["configurations"].values() for c in cs})
    lines = []

    def name_of(backend: str, p: int) -> str:
        return Configuration(backend, p).name

    def rows_of(size: dict):
        """(backend label, checkout key, backend) per table row."""
        present = {c["backend"] for c in report["configurations"][size["key"]]}
        for backend in (b for b in BACKENDS if b in present):
            for key in size["configurations"]:
                yield backend + (f" @{labels[key]}" if compare else ""), key, backend

    for tag, title in (("solve", "Solve"), ("process", "Whole process")):
        lines += ["", f"{title} (median {'solve_s' if tag == 'solve' else 'process_s'}; "
                  f"speedup against the fastest 1-worker configuration of the size):", "",
                  f"| {head} | backend | " + " | ".join(
                      (f"P = {p}" if p == ps[0] else str(p)) for p in ps) + " |",
                  "|---|---|" + "---|" * len(ps)]
        for size in report["sizes"].values():
            for label, key, backend in rows_of(size):
                cells = []
                for p in ps:
                    row = (None if backend == "serial" and p != 1
                           else size["configurations"][key].get(name_of(backend, p)))
                    cells.append("" if row is None or row.get(f"{tag}_s") is None else
                                 f"{seconds(row[f'{tag}_s'])} "
                                 f"({row.get(f'{tag}_speedup', float('nan')):.2f}×)")
                lines.append(f"| {size['label']} | {label} | " + " | ".join(cells) + " |")
        lines.append("")
        for size in report["sizes"].values():
            base = size["baseline"].get(tag)
            if base:
                lines.append(f"- {size['label']}: baseline {base['configuration']}"
                             + (f" @{labels[base['checkout']]}" if compare else "")
                             + f", {seconds(base['s'])}")
    if compare:
        lines += ["", f"@{labels[OTHER]} over @{labels[THIS]}, medians (> 1: "
                  f"@{labels[THIS]} is faster), solve / whole process:", "",
                  f"| {head} | backend | " + " | ".join(
                      (f"P = {p}" if p == ps[0] else str(p)) for p in ps) + " |",
                  "|---|---|" + "---|" * len(ps)]
        for size in report["sizes"].values():
            ratio = size.get("other_over_this", {})
            for backend in BACKENDS:
                cells = []
                for p in ps:
                    r = None if backend == "serial" and p != 1 else ratio.get(name_of(backend, p))
                    cells.append("" if r is None else " / ".join(
                        "–" if r[k] is None else f"{r[k]:.2f}×" for k in ("solve_s",
                                                                           "process_s")))
                if any(cells):
                    lines.append(f"| {size['label']} | {backend} | " + " | ".join(cells)
                                 + " |")
    phases = [k for k in (*PHASES, "reference_s") if k == "solve_s" or any(
        k in (row.get("timings") or {}) for size in report["sizes"].values()
        for rows in size["configurations"].values() for row in rows.values())]
    lines += ["", "Where the whole process goes at each backend's largest P (medians; "
              "'outside': the whole process minus the process's own total_s, i.e. the "
              "launcher, the interpreter's start before it and the exit):", "",
              f"| {head} | backend | P | whole process | "
              + " | ".join(WORDS[k] for k in phases)
              + " | total_s | outside | peak RSS: largest worker / largest process |",
              "|---|---|---|---|" + "---|" * len(phases) + "---|---|---|"]
    for size in report["sizes"].values():
        for label, key, backend in rows_of(size):
            rows = size["configurations"][key]
            p = max(c["workers"] for c in report["configurations"][size["key"]]
                    if c["backend"] == backend and Configuration(backend, c["workers"]).name
                    in rows)
            row = rows[name_of(backend, p)]
            # code without timings still has the solve: the result's wall_time_s
            timings = {"solve_s": row["solve_s"]} | (row.get("timings") or {})
            workers = [m for m in row["worker_peak_rss_mb"] if m is not None]
            lines.append(
                f"| {size['label']} | {label} | {p} | {seconds(row['process_s'])} | "
                + " | ".join(seconds(timings.get(k)) for k in phases)
                + f" | {seconds(timings.get('total_s'))} | {seconds(row['outside_s'])} | "
                + (f"{max(workers):.0f}" if workers else "–")
                + f" / {row['process_peak_rss_mb']:.0f} MiB |")
    lines.append("")
    for size in report["sizes"].values():
        for key, spread in size["headline"].items():
            where = f" @{labels[key]}" if compare else ""
            lines.append(f"- {size['label']}{where}: headline {spread['key']} "
                         + ("the same bits in all" if spread["identical_bits"] else
                            f"{len(spread['values'])} distinct values (relative spread "
                            f"{spread['relative_spread']:.1e}) over")
                         + f" {spread['runs']} runs")
        if "headline_same_across_checkouts" in size:
            lines.append(f"- {size['label']}: the checkouts' headlines are "
                         + ("the same bits" if size["headline_same_across_checkouts"]
                            else "not the same bits"))
    return "\n".join(lines) + "\n"


def plot(report: dict, path: Path) -> None:
    """Per size: solve and whole-process speedup against P, per backend and checkout."""
    from ocpar.plotting import pyplot, save

    plt = pyplot()
    from matplotlib.ticker import FuncFormatter

    labels = {k: c["label"] for k, c in report["checkouts"].items()}
    sizes_ = list(report["sizes"].values())
    fig, axes = plt.subplots(len(sizes_), 2, figsize=(10, 3.8 * len(sizes_)), squeeze=False)
    for size, row_axes in zip(sizes_, axes, strict=True):
        configs = report["configurations"][size["key"]]
        ps = sorted({c["workers"] for c in configs})
        for tag, title, ax in (("solve", "solve", row_axes[0]),
                               ("process", "whole process", row_axes[1])):
            ax.plot([1, max(ps)], [1, max(ps)], "k--", lw=0.8, label="ideal")
            for key, rows in size["configurations"].items():
                for colour, backend in enumerate(BACKENDS):
                    points = sorted((c["workers"], rows[n][f"{tag}_speedup"]) for c in configs
                                    if c["backend"] == backend
                                    and (n := Configuration(backend, c["workers"]).name) in rows
                                    and f"{tag}_speedup" in rows[n])
                    if not points:
                        continue
                    ax.plot(*zip(*points, strict=True), marker="s" if backend == "serial"
                            else "o", ls="-" if key == THIS else ":", color=f"C{colour}",
                            label=backend + (f" @{labels[key]}" if len(labels) > 1 else ""))
            base = size["baseline"].get(tag)
            ax.set_xscale("log", base=2)
            ax.set_yscale("log", base=2)
            ax.set_xticks(ps, [str(p) for p in ps])
            ax.minorticks_off()
            ax.yaxis.set_major_formatter(FuncFormatter(lambda y, _: f"{y:g}"))
            ax.set_xlabel("workers P")
            ax.set_ylabel("speedup")
            ax.set_title(f"{size['label']}: {title}"
                         + (f" (vs {base['configuration']}, {seconds(base['s'])})"
                            if base else ""), fontsize=9)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    save(fig, path)


def machine() -> dict:
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "machine": platform.machine(), "processor": platform.processor(),
            "python": sys.version.split()[0], "executable": sys.executable}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scheme", choices=("formation", "pursuit", "macs"),
                        default="formation")
    parser.add_argument("--agents", type=int, nargs="+", default=[10_000, 100_000],
                        help="formation: the sizes (default 10000 100000)")
    parser.add_argument("--problem", default=None,
                        help="formation: point-mass-plane (default) | crtbp-rigid; "
                             "macs: goddard (default) | orbit-raising")
    parser.add_argument("--case", type=int, default=1, help="pursuit: case (default 1)")
    parser.add_argument("--samples", type=int, default=301, help="pursuit: N (default 301)")
    parser.add_argument("--max-evals", type=int, default=10_000,
                        help="macs: evaluations (default 10000)")
    parser.add_argument("--archive", type=int, default=20, help="macs: archive (default 20)")
    parser.add_argument("--extra", default="",
                        help="more options for every run of the scheme, e.g. "
                             "--extra='--finish full_horizon'")
    parser.add_argument("--backend", nargs="+", choices=BACKENDS, default=["mpi", "dask"],
                        help="backends (the serial backend always runs: a 1-worker baseline)")
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2],
                        help="worker counts (1 always included; default 1 2)")
    parser.add_argument("--oversubscribe", action="store_true",
                        help="keep worker counts above os.cpu_count()")
    parser.add_argument("--balance", choices=("blocks", "lpt"), default="blocks")
    parser.add_argument("--repeat", type=int, default=3, help="repetitions (default 3)")
    parser.add_argument("--time-limit", type=float, default=3600.0,
                        help="seconds before a run is killed (and the benchmark stops)")
    parser.add_argument("--compare-with", type=Path, default=None, metavar="DIR",
                        help="another checkout of ocpar (DIR/src/ocpar), run alternating")
    parser.add_argument("--output", type=Path, default=Path("runs/scaling"))
    args = parser.parse_args()
    if min(args.workers) < 1 or args.repeat < 1:
        parser.error("--workers and --repeat must be positive")
    if args.compare_with is not None and not (args.compare_with / "src" / "ocpar").is_dir():
        parser.error(f"--compare-with {args.compare_with}: no src/ocpar there")
    started = time.perf_counter()
    load_start = os.getloadavg()
    rss_start = own_peak_rss_mb()
    cores = os.cpu_count() or 1
    workers = sorted({1, *args.workers})
    dropped = [] if args.oversubscribe else [p for p in workers if p > cores]
    workers = [p for p in workers if p not in dropped]
    if dropped:
        print(f"note: {dropped} workers dropped: more than this machine's {cores} cores "
              "(--oversubscribe keeps them)", flush=True)
    backends = ["serial", *(b for b in args.backend if b != "serial")]
    size_list = sizes(args)
    configs = {s.key: [c for c in configurations(backends, workers)
                       if s.agents is None or c.workers <= s.agents] for s in size_list}
    checkouts = [checkout(THIS, Path(__file__).resolve().parents[1])]
    if args.compare_with is not None:
        checkouts.append(checkout(OTHER, args.compare_with))
    args.output.mkdir(parents=True, exist_ok=True)
    checks = {}
    for where in checkouts:
        checks[where.key] = check_checkout(where, backends, args.output, args.time_limit)
        print(f"{where.key} checkout {where.root} ({where.label}): ocpar from {where.src}; its "
              f"60-agent result.json has timings: "
              f"{'yes' if checks[where.key]['formation_60_has_timings'] else 'no'}",
              flush=True)

    samples: list[dict] = []
    incomplete = None
    try:
        for rep in range(args.repeat):
            for size in size_list:
                for c in configs[size.key]:
                    # the checkouts alternate which goes first
                    order = checkouts if rep % 2 == 0 else checkouts[::-1]
                    for where in order:
                        out = (args.output / size.key
                               / (c.name + ("" if where.key == THIS else f"@{OTHER}")))
                        cmd = command(args.scheme, c.backend, c.workers, list(size.options),
                                      args.balance, out)
                        sample = measure(cmd, out, where, args.time_limit)
                        samples.append({"rep": rep, "size": size.key, "configuration": c.name,
                                        "backend": c.backend, "workers": c.workers,
                                        "checkout": where.key, "command": shlex.join(cmd),
                                        **sample})
                        if sample["status"] != "converged":
                            print(f"note: status {sample['status']!r}: {sample['message']}")
                        print(f"rep {rep + 1}/{args.repeat} {size.label:>12s} {c.name:8s} "
                              f"{where.label:>8s}: solve {sample['solve_s']:.3f} s, whole "
                              f"{sample['process_s']:.2f} s, {sample['headline_key']} "
                              f"{sample['headline']!r} (load {sample['load_1min']:.1f})",
                              flush=True)
    except RunFailed as failure:
        incomplete = str(failure)
        print(incomplete, file=sys.stderr)

    report = {
        "scheme": args.scheme, "argv": sys.argv[1:], "repeat": args.repeat,
        "backends": backends, "workers": workers, "workers_dropped": dropped,
        "balance": args.balance, "machine": machine(),
        "checkouts": {w.key: {"root": str(w.root), "label": w.label, "commit": w.commit,
                              "dirty": w.dirty, "check": checks[w.key]} for w in checkouts},
        "load_average": {"start": load_start, "end": os.getloadavg()},
        "benchmark_peak_rss_mb": {"start": rss_start, "end": own_peak_rss_mb()},
        "benchmark_wall_s": time.perf_counter() - started,
        "configurations": {s.key: [{"backend": c.backend, "workers": c.workers}
                                   for c in configs[s.key]] for s in size_list},
    }
    if incomplete is not None:
        report |= {"incomplete": incomplete, "samples": samples}
        (args.output / "scaling.json").write_text(json.dumps(report, indent=1))
        print(f"wrote {args.output / 'scaling.json'} (incomplete)", file=sys.stderr)
        return 1
    report["sizes"] = summaries(samples, size_list, configs, checkouts)
    for s in size_list:
        report["sizes"][s.key]["key"] = s.key
    report["samples"] = samples
    floor = report["benchmark_peak_rss_mb"]["end"]
    if any(s["process_peak_rss_mb"] <= floor + 1 for s in samples):
        print(f"note: some runs' process_peak_rss_mb is at the benchmark's own peak "
              f"({floor:.0f} MiB), which Linux counts in every child: read it as '≤'")
    (args.output / "scaling.json").write_text(json.dumps(report, indent=1))
    tables = markdown(report)
    (args.output / "scaling.md").write_text(tables)
    plot(report, args.output / "scaling.png")
    print(tables)
    print(f"load average {load_start[0]:.2f} at the start, {report['load_average']['end'][0]:.2f}"
          f" at the end; benchmark {report['benchmark_wall_s']:.0f} s")
    print(f"wrote {args.output / 'scaling.json'}, scaling.md and scaling.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
