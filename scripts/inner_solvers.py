#!/usr/bin/env python
"""Per-solve cost of the DMOC inner solvers, side by side in one process.

    python scripts/inner_solvers.py --output runs/inner-solvers

For the paper's point masses (60 agents, a QP each), rigid halo spacecraft (30 agents,
nonlinear) and the mixed fleet of ``ocpar.examples.formation_mixed_fleet`` (12 point masses)
free, with a box thrust limit and with a norm thrust limit (a path constraint; ``newton``
refuses it: not run), all at the initial angles (where the limits of 3 agents bind), the
inner tasks of the initial angles are solved as one chunk by the batched
kernel ``ocpar.ocp:solve_tasks`` with each ``DmocShape.solver`` (``newton``, ``sqpmethod``,
``ipopt``), ``--repeat`` times in turn (repetitions outermost); the first call of each (which
builds the solvers) is not timed. Writes ``inner_solvers.json`` (median ms per solve, the
largest relative cost difference against IPOPT, the tasks that needed the fallback) and
``inner_solvers.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import numpy as np

from ocpar.examples import formation_halo, formation_mixed_fleet, formation_point_masses
from ocpar.ocp import solve_tasks
from ocpar.ocp.batch import SOLVERS
from ocpar.plotting import pyplot, save

PROBLEMS = {"point masses (60)": lambda: formation_point_masses.make(60),
            "halo spacecraft (30)": lambda: formation_halo.make(),
            "fleet, free (12)": lambda: formation_mixed_fleet.make(limit=None),
            "fleet, box limit (12)": lambda: formation_mixed_fleet.make(limit="box"),
            "fleet, norm limit (12)": lambda: formation_mixed_fleet.make(limit="norm")}


def tasks_with(problem, solver: str) -> list | None:
    """The problem's inner tasks at its initial angles, each on its own shape solved by
    ``solver`` (None if a shape refuses that solver)."""
    tasks = problem.tasks(problem.initial_phi()).items()
    try:
        return [dataclasses.replace(t, shape=dataclasses.replace(t.shape, solver=solver))
                for t in tasks]
    except ValueError:
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed chunks per solver")
    parser.add_argument("--output", type=Path, default=Path("runs/inner-solvers"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report = {}
    for label, make in PROBLEMS.items():
        problem = make()
        chunks = {solver: chunk for solver in SOLVERS
                  if (chunk := tasks_with(problem, solver)) is not None}
        solutions = {solver: solve_tasks(chunk) for solver, chunk in chunks.items()}  # builds
        times: dict[str, list[float]] = {solver: [] for solver in chunks}
        for _ in range(args.repeat):
            for solver, chunk in chunks.items():
                start = time.perf_counter()
                solve_tasks(chunk)
                times[solver].append((time.perf_counter() - start) / len(chunk) * 1e3)
        reference = np.array([s.cost for s in solutions["ipopt"]])
        report[label] = {
            solver: {"ms_per_solve": statistics.median(times[solver]),
                     "max_rel_cost_difference_vs_ipopt": float(np.max(np.abs(
                         np.array([s.cost for s in solutions[solver]]) - reference)
                         / np.abs(reference))),
                     "fallbacks": int(sum(s.attempts > 1 for s in solutions[solver]))}
            for solver in chunks}
        for solver, row in report[label].items():
            print(f"{label:22s} {solver:10s} {row['ms_per_solve']:8.4f} ms/solve  "
                  f"cost vs IPOPT {row['max_rel_cost_difference_vs_ipopt']:.1e}  "
                  f"fallbacks {row['fallbacks']}")
    (args.output / "inner_solvers.json").write_text(json.dumps(report, indent=2))
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(10, 4))
    width = 0.8 / len(SOLVERS)
    for k, solver in enumerate(SOLVERS):
        ax.bar(np.arange(len(report)) + k * width,
               [r[solver]["ms_per_solve"] if solver in r else np.nan for r in report.values()],
               width, label=solver)
    ax.set_xticks(np.arange(len(report)) + width, list(report), fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("ms per inner solve (median)")
    ax.set_title("DMOC inner solvers, one chunk per call")
    ax.legend()
    save(fig, args.output / "inner_solvers.png")
    print(f"wrote {args.output / 'inner_solvers.json'}, {args.output / 'inner_solvers.png'}")


if __name__ == "__main__":
    main()
