#!/usr/bin/env python
"""ODE agents against DMOC point masses on the batched path: a formation of n unicycles
(:class:`~ocpar.models.Unicycle`, RK4 multiple shooting) and one of n unit point masses
(DMOC), from the same starts (spread on the line y = -30 over [-27, 33], at rest; the
unicycles facing +y) onto the same circle (radius 10 about the origin), N = 10 intervals over
T = 10. Usage::

    python scripts/ode_agents_speed.py --agents 10000 --repeats 3 --runs serial
    python scripts/ode_agents_speed.py --agents 10000 --repeats 3 --runs mpi

``serial`` (in this process, the variants interleaved in each repetition, after a warm-up
solve of each): per agent per inner iteration (the solve's wall time, and the process's CPU
time over the solve (steadier on a shared machine), over its inner solves)
of the point masses, the unicycles by the Riccati Newton (:mod:`ocpar.ocp.riccati`, the
default) and by sparse QR on the whole KKT matrix (``newton.kkt_solver = qr``, the solver
before it). ``mpi``: the Riccati unicycles' solve wall time by ``python -m ocpar.formation``
under ``mpirun -n 1`` (the fastest serial configuration) and ``mpirun -n 2``, alternating.
Medians of ``--repeats``; ratios of medians taken in the same run. Writes
``ode_agents_speed.json`` (every sample and the medians; a second ``--runs`` adds its part to
the file) and ``ode_agents_speed.png`` in ``--output``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, MsEndpointShape, solve_formation
from ocpar.models import PointMass, Unicycle

SCRIPTS = Path(__file__).resolve().parent
#: The serial variants, in the order they are measured and plotted.
VARIANTS = ("point masses (DMOC)", "unicycles, Riccati Newton", "unicycles, sparse QR Newton")


def _line(agents: int) -> np.ndarray:
    return np.column_stack([np.linspace(-27.0, 33.0, agents), np.full(agents, -30.0)])


def point_masses(agents: int = 10_000) -> FormationProblem:
    """n unit point masses from the line onto the circle (module docstring)."""
    return FormationProblem("masses", DmocShape(PointMass(dim=2), intervals=10, duration=10.0),
                            Circle(radius=10.0), _line(agents))


def unicycles(agents: int = 10_000, kkt_solver: str = "riccati") -> FormationProblem:
    """n unicycles from the line (facing +y, at rest) onto the circle, at rest, heading free;
    their Newton steps' KKT solver ``kkt_solver`` (``riccati`` or ``qr``)."""
    return FormationProblem(
        "unicycles", MsEndpointShape(Unicycle(), intervals=10, duration=10.0, free_end=(2,),
                                     solver_options={"newton.kkt_solver": kkt_solver}),
        Circle(radius=10.0),
        np.column_stack([_line(agents), np.full(agents, np.pi / 2), np.zeros(agents)]),
        final_state=np.array([np.nan, 0.0]))


def serial(agents: int, repeats: int) -> dict:
    """Per agent per inner iteration (µs) of each variant, every repetition, and the
    medians (module docstring)."""
    problems = dict(zip(VARIANTS, (point_masses(agents), unicycles(agents),
                                   unicycles(agents, "qr")), strict=True))
    samples: dict[str, list[float]] = {name: [] for name in VARIANTS}
    cpu: dict[str, list[float]] = {name: [] for name in VARIANTS}
    runs = {}
    for problem in problems.values():
        solve_formation(problem)   # warm-up: builds the solvers
    for rep in range(repeats):
        for name, problem in problems.items():
            start = time.process_time()
            result = solve_formation(problem)
            cpu[name].append(1e6 * (time.process_time() - start) / result.inner_solves)
            if result.status != "converged":
                raise RuntimeError(f"{name}: {result.status}: {result.message}")
            samples[name].append(1e6 * result.wall_time_s / result.inner_solves)
            runs[name] = {"outer_iterations": result.outer_iterations,
                          "inner_solves": result.inner_solves, "retries": result.retries,
                          "total_cost": result.total_cost}
        print(f"repetition {rep + 1}/{repeats}: " + ", ".join(
            f"{name} {samples[name][-1]:.2f} µs ({cpu[name][-1]:.2f} µs CPU)"
            for name in VARIANTS), flush=True)
    medians = {name: statistics.median(values) for name, values in samples.items()}
    cpu_medians = {name: statistics.median(values) for name, values in cpu.items()}
    mass, mass_cpu = medians[VARIANTS[0]], cpu_medians[VARIANTS[0]]
    return {"us_per_agent_per_inner_iteration": medians, "samples_us": samples, "runs": runs,
            "ratio_to_point_masses": {name: medians[name] / mass for name in VARIANTS[1:]},
            "riccati_speedup_over_qr": medians[VARIANTS[2]] / medians[VARIANTS[1]],
            "cpu_us_per_agent_per_inner_iteration": cpu_medians, "cpu_samples_us": cpu,
            "cpu_ratio_to_point_masses": {name: cpu_medians[name] / mass_cpu
                                          for name in VARIANTS[1:]},
            "cpu_riccati_speedup_over_qr": cpu_medians[VARIANTS[2]] / cpu_medians[VARIANTS[1]]}


def mpi(agents: int, repeats: int, output: Path) -> dict:
    """The Riccati unicycles' solve wall time (s) under ``mpirun -n 1`` and ``-n 2``, every
    repetition, the medians and their ratio."""
    from formation_bench import MPIRUN, run_once

    source = os.pathsep.join([str(SCRIPTS.parent / "src"), str(SCRIPTS)])
    samples: dict[str, list[float]] = {"1": [], "2": []}
    for rep in range(repeats):
        for ranks in samples:
            out = output / f"mpi-{ranks}"
            result = run_once([MPIRUN, "-n", ranks, sys.executable, "-m", "ocpar.formation",
                               "--quiet", "--plot", "none", "--problem",
                               "ode_agents_speed:unicycles", "--problem-arg",
                               f"agents={agents}", "--output", str(out)], out, 600.0,
                              source=source)
            if result.get("status") != "converged":
                raise RuntimeError(f"mpirun -n {ranks}: {result.get('status')}: "
                                   f"{result.get('message')}")
            samples[ranks].append(result["wall_time_s"])
        print(f"repetition {rep + 1}/{repeats}: mpirun -n 1 {samples['1'][-1]:.3f} s, "
              f"-n 2 {samples['2'][-1]:.3f} s", flush=True)
    medians = {ranks: statistics.median(values) for ranks, values in samples.items()}
    return {"solve_wall_s": medians, "samples_s": samples,
            "speedup_2_ranks": medians["1"] / medians["2"]}


def plot(report: dict, path: Path) -> None:
    """Per agent per inner iteration of the serial variants; the MPI speedup beside it."""
    from ocpar.plotting import figure

    parts = [part for part in ("serial", "mpi") if part in report]
    fig = figure(figsize=(4.5 * len(parts), 3.8))
    axes = fig.subplots(1, len(parts), squeeze=False)[0]
    for ax, part in zip(axes, parts, strict=True):
        if part == "serial":
            values = report["serial"]["us_per_agent_per_inner_iteration"]
            ax.bar(range(len(values)), list(values.values()), color=["0.5", "C0", "C1"])
            ax.set_xticks(range(len(values)), [n.replace(", ", ",\n") for n in values],
                          fontsize=8)
            for k, value in enumerate(values.values()):
                ax.text(k, value, f"{value:.1f}", ha="center", va="bottom")
            ax.set_ylabel("µs per agent per inner iteration")
            ax.set_title(f"{report['agents']:,} agents, serial (medians)", fontsize=10)
        else:
            values = report["mpi"]["solve_wall_s"]
            ax.bar([f"mpirun -n {r}" for r in values], list(values.values()), color="C0")
            ax.set_ylabel("solve wall time (s)")
            ax.set_title(f"Riccati unicycles: {report['mpi']['speedup_2_ranks']:.2f}× on 2 "
                         f"ranks", fontsize=10)
    fig.savefig(path, dpi=120)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--runs", nargs="+", choices=("serial", "mpi"),
                        default=["serial", "mpi"])
    parser.add_argument("--output", type=Path, default=Path("runs/ode-agents-speed"))
    args = parser.parse_args()
    os.environ["OMP_NUM_THREADS"] = "1"
    args.output.mkdir(parents=True, exist_ok=True)
    path = args.output / "ode_agents_speed.json"
    report = json.loads(path.read_text()) if path.exists() else {}
    if report.get("agents") != args.agents:
        report = {}
    report |= {"agents": args.agents, "repeats": args.repeats}
    if "serial" in args.runs:
        report["serial"] = serial(args.agents, args.repeats)
        part = report["serial"]
        for name, ratio in part["ratio_to_point_masses"].items():
            print(f"{name} / point masses: {ratio:.2f}× "
                  f"(CPU time {part['cpu_ratio_to_point_masses'][name]:.2f}×)")
        print(f"Riccati over sparse QR: {part['riccati_speedup_over_qr']:.2f}× "
              f"(CPU time {part['cpu_riccati_speedup_over_qr']:.2f}×)")
    if "mpi" in args.runs:
        report["mpi"] = mpi(args.agents, args.repeats, args.output)
        print(f"mpirun -n 2 over -n 1: {report['mpi']['speedup_2_ranks']:.2f}×")
    path.write_text(json.dumps(report, indent=1))
    plot(report, args.output / "ode_agents_speed.png")
    print(f"wrote {path} and ode_agents_speed.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
