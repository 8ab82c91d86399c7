#!/usr/bin/env python
"""Side-by-side formation benchmark: serial, MPI, Dask and monolithic IPOPT at several sizes.

    python scripts/formation_bench.py --output runs/formation-bench          # 60, 1000, 10,000
    python scripts/formation_bench.py --quick --output runs/formation-quick  # 60, 200; 2 reps
    python scripts/formation_bench.py --agents 60 1000 --repeat 5 \
        --variant default="" --variant offset="--outer offset" --monolithic-limit 120

For each number of agents, each option set (``--variant NAME="ARGS"``, repeatable: ARGS are
``python -m ocpar.formation`` options added to every ocpar run of that variant; default
``default=""`` and ``offset="--outer offset"``) and each backend (``serial``; ``mpi`` and
``dask`` with each of ``--workers``, MPI through ``mpirun -n P``, Dask on an embedded local
cluster), one run of ``python -m ocpar.formation`` in a fresh process; plus one monolithic
CasADi/IPOPT run (``--mode monolithic``), killed after ``--monolithic-limit`` seconds and
recorded as ``timeout`` (every ocpar run likewise after ``--time-limit``); its address space
is capped at ``--monolithic-memory`` MiB, so that its dense coupling Jacobian cannot take the
machine's memory (a run that hits the cap ends as ``error``, or ``timeout`` if it hangs). A
configuration that timed out or ended without result.json (``error``) is not run again at
that size or larger ones, in any later repetition.
Repetitions are outermost, so a drift of the machine's speed hits every configuration alike.

Per configuration and size, medians over the repetitions of (each from the run's result.json
and its superstep trace): solve wall time (process and cluster start-up excluded),
supersteps, inner solves, per-solve time, per-superstep overhead (wall − busiest worker), the
first superstep's overhead, coordinator share (time outside supersteps / solve wall); peak
resident memory per worker and of the largest process of the run; the total cost, which
must agree across all runs of a size to ``--cost-rtol``; speedup and efficiency against the
fastest serial configuration of the same size (the 1-worker ocpar configuration, whatever its
backend and variant, with the smallest median solve wall time).

``--baseline-src DIR`` runs every ocpar configuration a second time with ``PYTHONPATH=DIR``
(another checkout's ``src``: the design before a change, in the same sitting), named
``…@baseline``; ``--baseline-traffic FILE`` is that design's ``superstep_traffic.json``
(``scripts/superstep_traffic.py``: its supersteps' bytes, which its traces may not count).

At the largest size the BSP cost model (:mod:`ocpar.bsp.cost_model`) predicts P = 1, 2, 4,
…, 1024 workers for ``--model-agents`` agents (default 10,000 and 100,000) from each design's
fastest serial run (its per-task CPU times and serial part, both scaled by the ratio of
agents: per-agent work and data do not depend on n) and its supersteps' bytes h (from the
MPI run with the most ranks, or the baseline's traffic file; scaled likewise), with each
parallel backend's constants σ(P, h) = a + b·log2 P + g·h fitted to the supersteps measured
on that backend (this design's runs: their traces count the bytes; per superstep the median
over the repetitions, each run's first superstep left out).

``--problem mixed-fleet-by-kind``: the mixed fleet whose first half is thrust-limited and
second half is not (``ocpar.examples.formation_mixed_fleet:make`` with ``unlimited`` = half the
agents; a limited agent's solve costs ~5× an unlimited one's): a cost skewed by agent order,
for the resident agents' blocks that follow the measured costs. Rebalancing on vs off::

    python scripts/formation_bench.py --problem mixed-fleet-by-kind --agents 2000 \
        --no-monolithic --variant measured="" --variant fixed="--resident-blocks fixed"

Per run the figures include ``imbalances`` (each superstep's max/mean worker busy) and
``moved_agents`` (agents whose worker changed between supersteps, from the traces' block
sizes).

Writes ``formation_bench.json`` and ``formation_bench.png`` (solve wall vs agents per
configuration; predicted efficiency vs P) in ``--output``.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import resource
import shlex
import signal
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ocpar.bsp.cost_model import (
    SyncCost,
    coordinator_share,
    median_overhead,
    predict,
    serial_time,
    superstep_samples,
    task_times,
)
from ocpar.result_files import load_trace, read_summary

SIZES = (60, 1000, 10_000)
MODEL_AGENTS = (10_000, 100_000)
BASELINE = "baseline"
QUICK_SIZES = (60, 200)
DEFAULT_VARIANTS = ("default=", "offset=--outer offset")
MODEL_WORKERS = tuple(2**k for k in range(11))
#: Worker counts whose predicted efficiency the report prints, with the issue's targets.
EFFICIENCY_TARGETS = {64: 0.85, 1024: 0.7}
#: Options the benchmark sets itself; a variant may not give them.
RESERVED = ("--agents", "--backend", "--workers", "--mode", "--output", "--problem",
            "--quiet", "--scheduler")
MPIRUN = str(Path(sys.executable).parent / "mpirun")
#: The problems besides the built-in examples: the mixed fleet listed by kind (module doc).
SKEWED_FLEET = "mixed-fleet-by-kind"
PROBLEMS = ("point-mass-plane", "crtbp-rigid", SKEWED_FLEET)


def problem_options(problem: str, agents: int) -> list[str]:
    """The ``python -m ocpar.formation`` options that give ``problem`` with ``agents``."""
    if problem == SKEWED_FLEET:
        return ["--problem", "ocpar.examples.formation_mixed_fleet:make", "--problem-arg",
                f"agents={agents}", "--problem-arg", f"unlimited={agents // 2}"]
    return ["--problem", problem, "--agents", str(agents)]


@dataclass(frozen=True)
class Configuration:
    """One way to solve a size: ``backend`` serial | mpi | dask | monolithic, on ``workers``
    workers, with the ``variant``'s extra options ``args``."""

    backend: str
    workers: int
    variant: str
    args: tuple[str, ...]
    source: str | None = None  # PYTHONPATH of a baseline design's runs

    @property
    def name(self) -> str:
        if self.backend == "monolithic":
            return "monolithic"
        where = "serial" if self.backend == "serial" else f"{self.backend}x{self.workers}"
        return f"{where}/{self.variant}" + (f"@{BASELINE}" if self.source else "")

    @property
    def design(self) -> str:
        """``this`` (the checkout the benchmark runs from) or ``baseline``."""
        return BASELINE if self.source else "this"

    def command(self, problem: str, agents: int, out: Path) -> list[str]:
        """The command line of one run."""
        cmd = [sys.executable, "-m", "ocpar.formation", *problem_options(problem, agents),
               *self.args, "--quiet", "--output", str(out)]
        if self.backend == "monolithic":
            return [*cmd, "--mode", "monolithic"]
        if self.backend == "mpi":
            return [MPIRUN, "-n", str(self.workers), *cmd]
        if self.backend == "dask":
            return [*cmd, "--backend", "dask", "--workers", str(self.workers)]
        return [*cmd, "--backend", "serial"]


def parse_variant(text: str) -> tuple[str, tuple[str, ...]]:
    """``NAME=ARGS`` → (NAME, ARGS split like a shell would)."""
    name, sep, args = text.partition("=")
    if not sep or not name or "/" in name or name != name.strip():
        raise argparse.ArgumentTypeError(f"--variant must be NAME=ARGS (NAME without '/' or "
                                         f"spaces), got {text!r}")
    try:
        words = tuple(shlex.split(args))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--variant {name}: {exc}") from None
    for word in words:
        if word.split("=")[0] in RESERVED:
            raise argparse.ArgumentTypeError(
                f"--variant {name}: {word.split('=')[0]} is set by the benchmark itself")
    return name, words


def launch(cmd: list[str], out: Path, limit_s: float, memory_mb: float | None = None,
           source: str | None = None) -> dict:
    """Run ``cmd`` in its own process group, its stderr to ``out/stderr.txt``; kill the group
    after ``limit_s`` seconds. With ``memory_mb`` its address space is capped at that many
    MiB (an allocation beyond it fails, and the run ends as ``error``). ``source``: the
    ``PYTHONPATH`` to run it with (default this process's environment).
    Returns ``process_peak_rss_mb``, the peak resident memory of the largest process it ran
    (from ``wait4``; Linux counts a child's pages from before its ``exec`` too, so this is at
    least the peak of the calling process itself), ``process_s``, its wall time from just
    before the launch to its exit (start-up included; a blocking wait), ``exit_code``, and
    where ``out`` has no result.json afterwards ``status`` ``timeout`` or ``error`` with a
    ``message``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "result.json").unlink(missing_ok=True)
    with open(out / "stderr.txt", "w") as err:
        cap = None if memory_mb is None else int(memory_mb * 2**20)
        env = None if source is None else os.environ | {"PYTHONPATH": source}
        launched = time.monotonic()
        proc = subprocess.Popen(
            cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True, env=env,
            preexec_fn=None if cap is None else
            lambda: resource.setrlimit(resource.RLIMIT_AS, (cap, cap)))
        fired = threading.Event()

        def kill() -> None:
            fired.set()
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)

        killer = threading.Timer(limit_s, kill)
        killer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            killer.cancel()
        ended = time.monotonic()
        proc.returncode = os.waitstatus_to_exitcode(status)
    process = {"process_peak_rss_mb": usage.ru_maxrss / 1024,  # Linux: KiB
               "process_s": ended - launched, "exit_code": proc.returncode}
    if fired.is_set():
        return {"status": "timeout", "message": f"killed after {limit_s:g} s", **process}
    if not (out / "result.json").exists():
        tail = (out / "stderr.txt").read_text().strip().splitlines()[-1:] or [""]
        return {"status": "error", "message": f"exit {proc.returncode}: {tail[0]}", **process}
    return process


def run_once(cmd: list[str], out: Path, limit_s: float, memory_mb: float | None = None,
             source: str | None = None) -> dict:
    """:func:`launch` ``cmd``; returns the result.json's fields (``status`` ``timeout`` or
    ``error`` if there is none) with its ``trace`` and ``launch``'s figures."""
    process = launch(cmd, out, limit_s, memory_mb, source)
    if "status" in process:
        return process
    return read_summary(out) | {"trace": load_trace(out)} | process


def run_figures(result: dict) -> dict:
    """The per-run figures of one result.json (times in s, memory in MiB; None where the run
    has no supersteps, as in monolithic mode)."""
    row = {k: result.get(k) for k in ("status", "message", "process_peak_rss_mb", "process_s")}
    if "trace" not in result:
        return row
    trace = result["trace"]
    wall = result["wall_time_s"]
    tasks = [x for t in trace for x in t["task_wall_s"]]
    peaks = [max(t["worker_peak_rss_mb"][w] for t in trace)
             for w in range(max((len(t["worker_peak_rss_mb"]) for t in trace), default=0))]
    return row | {
        "wall_s": wall,
        "supersteps": len(trace),
        "inner_solves": result["inner_solves"],
        "outer_iterations": result["outer_iterations"],
        "total_cost": result["total_cost"],
        "solve_ms": 1e3 * statistics.median(tasks) if tasks else None,
        "overhead_ms": 1e3 * median_overhead(trace) if trace else None,
        "first_overhead_ms": 1e3 * trace[0]["overhead_s"] if trace else None,
        "coordinator_s": serial_time(wall, trace),
        "coordinator_share": coordinator_share(wall, trace),
        "imbalance": statistics.median(t["imbalance"] for t in trace) if trace else None,
        "imbalances": [t["imbalance"] for t in trace],
        "moved_agents": moved_agents(trace),
        "peak_rss_mb_per_worker": peaks,
    }


def moved_agents(trace: list[dict]) -> int:
    """Agents whose worker changed between consecutive supersteps of contiguous blocks (a
    resident set's), from the block sizes (``worker_tasks``) in the trace."""
    moved = 0
    for before, after in itertools.pairwise(t["worker_tasks"] for t in trace):
        if len(before) != len(after) or sum(before) != sum(after):
            continue  # another kind of superstep, or another worker count
        old = list(itertools.accumulate(before, initial=0))
        new = list(itertools.accumulate(after, initial=0))
        moved += sum(before) - sum(max(0, min(old[w + 1], new[w + 1]) - max(old[w], new[w]))
                                   for w in range(len(before)))
    return moved


MEDIANS = ("wall_s", "supersteps", "inner_solves", "outer_iterations", "total_cost",
           "solve_ms", "overhead_ms", "first_overhead_ms", "coordinator_s",
           "coordinator_share", "imbalance", "moved_agents", "process_peak_rss_mb",
           "process_s")


def summarise(runs: list[dict]) -> dict:
    """Medians over a configuration's runs that gave a result; peak memory: the largest."""
    done = [r for r in runs if "wall_s" in r]
    row: dict = {"runs": len(runs), "results": len(done),
                 "statuses": sorted({r["status"] for r in runs})}
    if not done:
        return row
    for k in MEDIANS:
        values = [r[k] for r in done if r[k] is not None]
        row[k] = statistics.median(values) if values else None
    row["peak_rss_mb_per_worker"] = [max(p) for p in zip(
        *(r["peak_rss_mb_per_worker"] for r in done), strict=True)]
    return row


def compare_costs(size_runs: dict[str, list[dict]], reference: float, rtol: float) -> list:
    """Runs whose total cost differs from ``reference`` by more than ``rtol`` relative."""
    out = []
    for name, runs in size_runs.items():
        for rep, r in enumerate(runs):
            if "total_cost" not in r:
                continue
            cost = r["total_cost"]
            rel = (math.inf if cost is None
                   else abs(cost - reference) / max(abs(reference), 1e-300))
            if not rel <= rtol:
                out.append({"configuration": name, "rep": rep, "total_cost": cost,
                            "relative_difference": rel})
    return out


def median_result(output: Path, agents: int, config: Configuration, runs: list[dict]
                  ) -> dict | None:
    """The result.json of ``config``'s median run (by solve wall time) at ``agents``."""
    done = [(rep, r) for rep, r in enumerate(runs) if "wall_s" in r]
    if not done:
        return None
    rep, _ = sorted(done, key=lambda x: x[1]["wall_s"])[len(done) // 2]
    out = output / f"{agents}-{config.name.replace('/', '-')}-{rep}"
    return read_summary(out) | {"trace": load_trace(out)}


def fit_samples(output: Path, agents: int, config: Configuration, runs: list[dict]
                ) -> list[tuple[int, float, float]]:
    """(P, bytes that crossed, overhead s) per superstep of ``config`` at ``agents``, each the
    median over the repetitions, the first superstep left out (its one-time costs: imports,
    solver builds; reported as ``first_overhead_ms``)."""
    per_rep = []
    for rep, r in enumerate(runs):
        if "wall_s" in r:
            trace = load_trace(output / f"{agents}-{config.name.replace('/', '-')}-{rep}")
            per_rep.append(superstep_samples(trace)[1:])
    if not per_rep or len({len(s) for s in per_rep}) != 1:
        return []
    return [(steps[0][0], statistics.median(s[1] for s in steps),
             statistics.median(s[2] for s in steps)) for steps in zip(*per_rep, strict=True)]


def superstep_bytes(output: Path, agents: int, configs: list[Configuration], reps: dict,
                    variant: str, baseline_traffic: dict | None, design: str,
                    supersteps: int) -> list[float] | None:
    """Each superstep's bytes h (all its tasks and results) of ``design`` at ``agents``:
    from the MPI (else Dask) run with the most workers of this design, from the traffic file
    for the baseline; None where unknown."""
    if design == BASELINE:
        size = (baseline_traffic or {}).get("sizes", {}).get(str(agents))
        if size is None:
            return None
        volumes = [s["sent_bytes"] + s["received_bytes"] for s in size["per_superstep"]]
        if len(volumes) != supersteps:  # another outer path: its median for every superstep
            volumes = [statistics.median(volumes)] * supersteps
        return volumes
    for backend in ("mpi", "dask"):
        ranked = sorted((c for c in configs if c.backend == backend and c.design == design
                         and c.variant == variant and c.workers > 1), key=lambda c: c.workers)
        for c in reversed(ranked):
            result = median_result(output, agents, c, reps[c.name])
            if result is not None and len(result["trace"]) == supersteps:
                share = SyncCost(0, 0, local_chunk=backend == "mpi").crossing(c.workers)
                return [(t["sent_bytes"] + t["received_bytes"]) / share
                        for t in result["trace"]]
    return None


def model(output: Path, agents: int, table: dict, configs: list[Configuration],
          reps: dict, model_agents: list[int], baseline_traffic: dict | None) -> dict | None:
    """Cost-model predictions for ``model_agents`` agents, per design, from that design's
    fastest serial configuration measured at ``agents``, with each parallel backend's
    constants fitted to this design's supersteps measured at ``agents`` (module docstring)."""
    out: dict = {"agents": agents, "model_agents": model_agents, "designs": {},
                 "backends": {}}
    fitted: dict[str, SyncCost] = {}
    for design in ("this", BASELINE):
        serial = {c.name: table["configurations"][c.name]["wall_s"] for c in configs
                  if c.workers == 1 and c.design == design and c.backend != "monolithic"
                  and "wall_s" in table["configurations"][c.name]}
        if not serial:
            continue
        base = next(c for c in configs if c.name == min(serial, key=serial.get))
        result = median_result(output, agents, base, reps[base.name])
        assert result is not None
        tasks = task_times(result["trace"], use="cpu")
        serial_s = serial_time(result["wall_time_s"], result["trace"])
        if not fitted:
            for backend in ("mpi", "dask"):
                samples = [sample for c in configs if c.backend == backend
                           and c.design == "this" and c.variant == base.variant
                           for sample in fit_samples(output, agents, c, reps[c.name])]
                if samples:
                    fitted[backend] = SyncCost.fit_supersteps(samples, backend == "mpi")
            out["backends"] = {b: vars(s) for b, s in fitted.items()}
        volumes = superstep_bytes(output, agents, configs, reps, base.variant,
                                  baseline_traffic, design, len(tasks))
        row: dict = {"from": base.name, "supersteps": len(tasks), "serial_s": serial_s,
                     "superstep_bytes": volumes, "predictions": {}}
        for n in model_agents:
            factor = max(round(n / agents), 1)
            scaled = [times * factor for times in tasks]
            row["predictions"][str(n)] = {
                backend: [vars(p) | {"coordinator_share": p.coordinator_share}
                          for p in predict(scaled, MODEL_WORKERS, "blocks", sync,
                                           serial_s * factor,
                                           None if volumes is None
                                           else [h * factor for h in volumes])]
                for backend, sync in fitted.items()}
        out["designs"][design] = row
    return out if out["designs"] else None


def plot(report: dict, path: Path) -> None:
    from ocpar.plotting import pyplot, save

    plt = pyplot()
    fig, (ax_t, ax_e) = plt.subplots(1, 2, figsize=(12, 4.8))
    names = sorted({n for size in report["sizes"].values() for n in size["configurations"]})
    # colour: backend and workers; line style: variant
    wheres = sorted({n.split("/")[0] for n in names})
    styles = {v: ("-", "--", ":", "-.")[k % 4] for k, v in enumerate(report["variants"])}
    for name in names:
        where, _, variant = name.partition("/")
        variant, _, baseline = variant.partition("@")
        style = {"color": f"C{wheres.index(where) % 10}",
                 "ls": ":" if baseline else styles.get(variant, "-")}
        xs, ys, xt, yt = [], [], [], []
        for agents, size in sorted(report["sizes"].items(), key=lambda kv: int(kv[0])):
            row = size["configurations"].get(name)
            if row is None:
                continue
            if "wall_s" in row:
                xs.append(int(agents))
                ys.append(row["wall_s"])
            elif "timeout" in row["statuses"]:
                xt.append(int(agents))
                yt.append(report["limits_s"]["monolithic" if name == "monolithic"
                                             else "ocpar"])
        ax_t.plot(xs, ys, marker="o", label=name, **style)
        if xt:
            ax_t.plot(xt, yt, "x", ms=9, color=style["color"])
    ax_t.set_xscale("log")
    ax_t.set_yscale("log")
    ax_t.set_xlabel("agents")
    ax_t.set_ylabel("solve wall time (s), median; x: timed out")
    ax_t.legend(fontsize=7)
    ax_t.grid(alpha=0.3, which="both")
    predicted = report.get("model")
    if predicted:
        lines = {"this": "-", BASELINE: ":"}
        for design, row in predicted["designs"].items():
            for k, (n, by_backend) in enumerate(row["predictions"].items()):
                for backend, points in by_backend.items():
                    ax_e.plot([p["workers"] for p in points],
                              [p["efficiency"] for p in points], lines[design],
                              marker="os"[k % 2], ms=4,
                              color=f"C{2 * (backend == 'dask') + k}",
                              label=f"{backend}, {int(n):,} agents, {design}")
        for p, target in EFFICIENCY_TARGETS.items():
            ax_e.plot([p], [target], "k^", ms=8)
        ax_e.set_title(f"cost model σ = a + b·log2 P + g·h fitted at {predicted['agents']:,} "
                       "agents (▲ targets)", fontsize=9)
        ax_e.legend(fontsize=6)
    ax_e.set_xscale("log", base=2)
    ax_e.set_ylim(0, 1.05)
    ax_e.set_xlabel("workers P")
    ax_e.set_ylabel("predicted efficiency T(1)/(P·T(P))")
    ax_e.grid(alpha=0.3, which="both")
    save(fig, path)


def fmt(value: float | None, width: int, spec: str) -> str:
    """``value`` formatted by ``spec`` right-aligned in ``width`` characters; "-" if None."""
    return f"{'-' if value is None else format(value, spec):>{width}s}"


def print_report(report: dict) -> None:
    for agents, size in report["sizes"].items():
        print(f"\n{agents} agents: speedups against "
              f"{size.get('fastest_serial', '- (no serial result)')}")
        print(f"{'configuration':22s}{'runs':>5s}{'wall s':>9s}{'speedup':>8s}{'effic':>7s}"
              f"{'steps':>6s}{'solves':>8s}{'solve ms':>9s}{'ovh ms':>8s}{'1st ms':>8s}"
              f"{'coord':>7s}{'imbal':>6s}{'moved':>7s}{'MiB/worker':>12s}"
              f"{'total cost':>20s}")
        for name, r in size["configurations"].items():
            if "wall_s" not in r:
                print(f"{name:22s}{r['runs']:5d}  {', '.join(r['statuses'])}")
                continue
            mem = "/".join(f"{m:.0f}" for m in r["peak_rss_mb_per_worker"]) or \
                f"{r['process_peak_rss_mb']:.0f}"
            print(f"{name:22s}{r['results']:5d}{fmt(r['wall_s'], 9, '.3f')}"
                  f"{fmt(r.get('speedup'), 8, '.2f')}{fmt(r.get('efficiency'), 7, '.2f')}"
                  f"{fmt(r['supersteps'], 6, '.0f')}{fmt(r['inner_solves'], 8, '.0f')}"
                  f"{fmt(r['solve_ms'], 9, '.3f')}{fmt(r['overhead_ms'], 8, '.2f')}"
                  f"{fmt(r['first_overhead_ms'], 8, '.2f')}"
                  f"{fmt(r['coordinator_share'], 7, '.1%')}{fmt(r['imbalance'], 6, '.2f')}"
                  f"{fmt(r['moved_agents'], 7, '.0f')}{mem:>12s}"
                  f"{fmt(r['total_cost'], 20, '.12e')}")
        for flag in size["cost_disagreements"]:
            print(f"  COST DISAGREES: {flag['configuration']} rep {flag['rep']}: "
                  f"{flag['total_cost']} (relative difference {flag['relative_difference']:.1e})")
    predicted = report.get("model")
    if not predicted:
        return
    print(f"\ncost model fitted at {predicted['agents']} agents:")
    for backend, sync in predicted["backends"].items():
        print(f"  {backend}: σ(P, h) = {sync['a_s'] * 1e3:.3f} ms + {sync['b_s'] * 1e3:.3f} ms·"
              f"log2 P + {sync['g_s_per_byte'] * 1e9:.3f} ns/byte · h")
    for design, row in predicted["designs"].items():
        volumes = row["superstep_bytes"]
        print(f"  {design}: from {row['from']} ({row['supersteps']} supersteps, serial part "
              f"{row['serial_s']:.3f} s, h per superstep "
              + ("unknown" if volumes is None else
                 "/".join(f"{h / 1e6:.2f}" for h in volumes) + " MB") + ")")
        for n, by_backend in row["predictions"].items():
            for backend, points in by_backend.items():
                effs = ", ".join(f"{p['efficiency']:.2f}" for p in points
                                 if p["workers"] >= 8)
                print(f"    {int(n):7,d} agents {backend}: efficiency at 8…1024 workers {effs}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", nargs="+", type=int, default=None,
                        help=f"sizes (default {' '.join(map(str, SIZES))}; --quick: "
                             f"{' '.join(map(str, QUICK_SIZES))})")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes, 2 repetitions, short limits: for trying the script")
    parser.add_argument("--problem", default="point-mass-plane", choices=PROBLEMS,
                        help=f"built-in example, or {SKEWED_FLEET} (module doc)")
    parser.add_argument("--variant", action="append", type=parse_variant, default=None,
                        metavar='NAME="ARGS"',
                        help="an option set of the ocpar runs, repeatable (default: "
                             + " and ".join(f'{v.split("=")[0]}="{v.split("=", 1)[1]}"'
                                            for v in DEFAULT_VARIANTS) + ")")
    parser.add_argument("--backends", nargs="+", choices=("serial", "mpi", "dask"),
                        default=["serial", "mpi", "dask"])
    parser.add_argument("--workers", nargs="+", type=int, default=[1, 2],
                        help="worker counts of mpi and dask (default 1 2: the 1-worker runs "
                             "give the cost model's synchronisation fit)")
    parser.add_argument("--no-monolithic", action="store_true", help="skip --mode monolithic")
    parser.add_argument("--repeat", type=int, default=None, help="repetitions (default 3; "
                        "--quick: 2)")
    parser.add_argument("--time-limit", type=float, default=None,
                        help="seconds before an ocpar run is killed (default 1800; --quick 120)")
    parser.add_argument("--monolithic-limit", type=float, default=None,
                        help="seconds before a monolithic run is killed (default 120; "
                             "--quick 30)")
    parser.add_argument("--monolithic-memory", type=float, default=8192,
                        help="address-space cap of a monolithic run (MiB, default 8192): its "
                             "coupling's Jacobian is dense in the angles (n² entries)")
    parser.add_argument("--cost-rtol", type=float, default=1e-8,
                        help="relative tolerance of the total-cost agreement check")
    parser.add_argument("--baseline-src", default=None, metavar="DIR",
                        help="also run every ocpar configuration with PYTHONPATH=DIR (another "
                             "design's src), named ...@baseline")
    parser.add_argument("--baseline-traffic", type=Path, default=None, metavar="FILE",
                        help="the baseline's superstep_traffic.json (its supersteps' bytes)")
    parser.add_argument("--model-agents", nargs="+", type=int, default=list(MODEL_AGENTS),
                        help="agents the cost model predicts for (default 10000 100000)")
    parser.add_argument("--output", type=Path, default=Path("runs/formation-bench"))
    args = parser.parse_args()
    sizes = sorted(set(args.agents or (QUICK_SIZES if args.quick else SIZES)))
    repeat = args.repeat or (2 if args.quick else 3)
    limit = args.time_limit or (120.0 if args.quick else 1800.0)
    mono_limit = args.monolithic_limit or (30.0 if args.quick else 120.0)
    variants = args.variant or [parse_variant(v) for v in DEFAULT_VARIANTS]
    if (min(sizes) < 2 or repeat < 1 or min(args.workers) < 1
            or min(limit, mono_limit, args.monolithic_memory) <= 0):
        parser.error("--agents ≥ 2, --repeat ≥ 1, --workers ≥ 1 and positive limits")
    if len({name for name, _ in variants}) != len(variants):
        parser.error("--variant names must be distinct")
    if "serial" not in args.backends:
        parser.error("--backends must include serial (the speedups' baseline)")
    if repeat < 3:
        print(f"note: {repeat} repetitions: the issue asks for medians of at least 3")

    sources = [None] if args.baseline_src is None else [None, args.baseline_src]
    configs = [Configuration(b, p, name, extra, source) for source in sources
               for name, extra in variants
               for b in args.backends for p in ([1] if b == "serial" else args.workers)]
    if not args.no_monolithic:
        configs.append(Configuration("monolithic", 1, "monolithic", ()))
    runs: dict[int, dict[str, list[dict]]] = {n: {c.name: [] for c in configs} for n in sizes}
    # configuration → the smallest size at which it timed out or ended without a result
    timed_out: dict[str, int] = {}
    start = time.perf_counter()
    for rep in range(repeat):  # repetitions outermost
        for agents in sizes:
            for c in configs:
                if agents >= timed_out.get(c.name, math.inf):
                    skipped = {"status": "skipped", "message": f"no result at "
                               f"{timed_out[c.name]} agents (timeout or error)"}
                    runs[agents][c.name].append(skipped)
                    continue
                out = args.output / f"{agents}-{c.name.replace('/', '-')}-{rep}"
                mono = c.backend == "monolithic"
                result = run_once(c.command(args.problem, agents, out), out,
                                  mono_limit if mono else limit,
                                  args.monolithic_memory if mono else None, c.source)
                row = run_figures(result)
                runs[agents][c.name].append(row)
                if row["status"] in ("timeout", "error"):
                    timed_out[c.name] = min(agents, timed_out.get(c.name, math.inf))
                wall = f"{row['wall_s']:.3f} s" if "wall_s" in row else row["message"]
                print(f"rep {rep} {agents:6d} agents {c.name:22s} {row['status']:13s} {wall}",
                      flush=True)

    report: dict = {"problem": args.problem, "repeat": repeat,
                    "baseline_src": args.baseline_src,
                    "variants": {name: list(extra) for name, extra in variants},
                    "limits_s": {"ocpar": limit, "monolithic": mono_limit},
                    "cost_rtol": args.cost_rtol, "benchmark_wall_s": 0.0, "sizes": {}}
    for agents in sizes:
        rows = {c.name: summarise(runs[agents][c.name]) for c in configs}
        serial = {c.name: rows[c.name]["wall_s"] for c in configs
                  if c.workers == 1 and c.backend != "monolithic" and "wall_s" in rows[c.name]}
        size: dict = {"configurations": rows, "runs": runs[agents], "cost_disagreements": []}
        if serial:
            fastest = min(serial, key=serial.get)
            size["fastest_serial"] = fastest
            for c in configs:
                if "wall_s" in rows[c.name]:
                    rows[c.name]["speedup"] = serial[fastest] / rows[c.name]["wall_s"]
                    rows[c.name]["efficiency"] = rows[c.name]["speedup"] / c.workers
            if rows[fastest]["total_cost"] is not None:
                size["cost_disagreements"] = compare_costs(
                    runs[agents], rows[fastest]["total_cost"], args.cost_rtol)
        report["sizes"][str(agents)] = size
    largest = max((n for n in sizes if "fastest_serial" in report["sizes"][str(n)]),
                  default=None)
    if largest is not None:
        traffic = (json.loads(args.baseline_traffic.read_text())
                   if args.baseline_traffic is not None else None)
        report["model"] = model(args.output, largest, report["sizes"][str(largest)], configs,
                                runs[largest], args.model_agents, traffic)
    report["benchmark_wall_s"] = time.perf_counter() - start
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "formation_bench.json").write_text(json.dumps(report, indent=1))
    plot(report, args.output / "formation_bench.png")
    print_report(report)
    print(f"\nbenchmark took {report['benchmark_wall_s']:.0f} s; wrote "
          f"{args.output / 'formation_bench.json'} and {args.output / 'formation_bench.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
