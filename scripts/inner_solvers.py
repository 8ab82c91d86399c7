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

With obstacles (``--obstacles``, or ``--only-obstacles`` for them alone): the mixed fleet
with its ball (radius 2.5) in 2-D and in 3-D (``formation_mixed_fleet.make(dim=3)``), free,
box- and norm-limited, at the initial angles and at the formation's optimum (where the ball
binds for more agents), per agent in one chunk: ``batched`` (each shape's own solver, from
the default guess: an agent's first solve), ``batched, warm`` (the same, each task started
from its solution at angles moved by :data:`WARM_STEP`: a later superstep's re-solve),
``batched, no obstacle`` (the same tasks without the ball: the unconstrained batched solve)
and ``ipopt`` (every shape's solver ``ipopt``), ``--repeat`` times in turn; each with the
tasks whose path the ball binds (a segment within 1e-6 of it at the IPOPT optimum) and the
largest relative cost difference against IPOPT; and the whole formation solve
(``solve_formation``, serial, once compiled), batched, batched without the ball and by
IPOPT, ``--repeat`` times (median s, and per inner solve: that over the run's inner
solves). Written to ``obstacles`` in the JSON and ``inner_solvers_obstacles.png``.
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
from ocpar.formation import FormationOptions, solve_formation
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


#: The warm chunk's tasks start from the solutions at the angles moved by this (rad): a later
#: superstep's re-solve (each agent from its previous path and side).
WARM_STEP = 1e-3
#: The fleet with its ball: (dimension, thrust limit).
OBSTACLE_CASES = [(dim, limit) for dim in (3, 2) for limit in (None, "box", "norm")]


def with_solver(tasks: list, solver: str | None, obstacles: bool = True) -> list:
    """``tasks`` with each shape's solver ``solver`` (None: its own) and, unless
    ``obstacles``, without its obstacles."""
    def shape(s):
        changes = {} if solver is None else {"solver": solver}
        if not obstacles:
            changes.update(obstacles=(), obstacle_positions=())
        return dataclasses.replace(s, **changes)
    return [dataclasses.replace(t, shape=shape(t.shape)) for t in tasks]


def obstacle_report(repeat: int) -> dict:
    """Per-agent ms of the fleet's chunk with its ball: batched, batched without the ball and
    IPOPT (module docstring)."""
    report = {}
    for dim, limit in OBSTACLE_CASES:
        problem = formation_mixed_fleet.make(limit=limit, obstacle=2.5, dim=dim)
        optimum = solve_formation(problem).phi
        runs = {"batched": (problem, FormationOptions()),
                "batched, no obstacle": (formation_mixed_fleet.make(limit=limit, dim=dim),
                                         FormationOptions()),
                "ipopt": (problem, FormationOptions(inner_solver="ipopt"))}
        whole: dict[str, list[float]] = {name: [] for name in runs}
        results = {name: solve_formation(p, options=o) for name, (p, o) in runs.items()}  # builds
        for _ in range(repeat):
            for name, (p, o) in runs.items():
                start = time.perf_counter()
                solve_formation(p, options=o)
                whole[name].append(time.perf_counter() - start)
        label = f"{dim}-D fleet, {limit or 'free'}, whole run"
        seconds = {name: statistics.median(t) for name, t in whole.items()}
        solves = {name: r.inner_solves for name, r in results.items()}
        per_solve = {name: seconds[name] / solves[name] * 1e3 for name in runs}
        report[label] = {"s": seconds, "inner_solves": solves, "ms_per_agent_solve": per_solve,
                         "batched / no obstacle": per_solve["batched"]
                         / per_solve["batched, no obstacle"],
                         "total_cost": {name: r.total_cost for name, r in results.items()}}
        print(f"{label:45s} " + "  ".join(
            f"{name} {seconds[name]:.3f} s ({solves[name]} solves, {per_solve[name]:.3f} ms "
            f"each)" for name in runs) + f"  batched/no obstacle per solve "
            f"{report[label]['batched / no obstacle']:.2f}x  cost "
            f"{results['batched'].total_cost:.10f} / {results['ipopt'].total_cost:.10f}",
            flush=True)
        for where, phi in (("initial", problem.initial_phi()), ("optimum", optimum)):
            tasks = problem.tasks(phi).items()
            near = solve_tasks(with_solver(problem.tasks(phi + WARM_STEP).items(), None))
            chunks = {"batched": with_solver(tasks, None),
                      "batched, warm": [dataclasses.replace(t, warm_start=np.concatenate(
                          [s.q[1:-1].ravel(), s.u.ravel()]))
                          for t, s in zip(with_solver(tasks, None), near, strict=True)],
                      "batched, no obstacle": with_solver(tasks, None, obstacles=False),
                      "ipopt": with_solver(tasks, "ipopt")}
            solutions = {name: solve_tasks(chunk) for name, chunk in chunks.items()}  # builds
            times: dict[str, list[float]] = {name: [] for name in chunks}
            for _ in range(repeat):
                for name, chunk in chunks.items():
                    start = time.perf_counter()
                    solve_tasks(chunk)
                    times[name].append((time.perf_counter() - start) / len(chunk) * 1e3)
            reference = np.array([s.cost for s in solutions["ipopt"]])
            ball = problem.obstacles[0]
            binds = sum(float(ball.clearance(s.q[:-1, :dim], s.q[1:, :dim])[0].min()) < 1e-6
                        for s in solutions["ipopt"])
            label = f"{dim}-D fleet, {limit or 'free'}, {where} ({len(tasks)}, ball binds {binds})"
            report[label] = {name: {
                "ms_per_agent": statistics.median(times[name]),
                "max_rel_cost_difference_vs_ipopt": float(np.max(np.abs(
                    np.array([s.cost for s in solutions[name]]) - reference)
                    / np.abs(reference))) if name != "batched, no obstacle" else None,
                "fallbacks": int(sum(s.attempts > 1 for s in solutions[name]))}
                for name in chunks}
            row = report[label]
            ratio = row["batched"]["ms_per_agent"] / row["batched, no obstacle"]["ms_per_agent"]
            row["batched / no obstacle"] = ratio
            row["batched, warm / no obstacle"] = (row["batched, warm"]["ms_per_agent"]
                                                  / row["batched, no obstacle"]["ms_per_agent"])
            print(f"{label:45s} " + "  ".join(
                f"{name} {r['ms_per_agent']:.4f} ms" for name, r in row.items()
                if isinstance(r, dict)) + f"  batched/no obstacle {ratio:.1f}x  cost vs IPOPT "
                f"{row['batched']['max_rel_cost_difference_vs_ipopt']:.1e}  fallbacks "
                f"{row['batched']['fallbacks']}", flush=True)
    return report


def plot_obstacles(report: dict, path: Path) -> None:
    """Bars of :func:`obstacle_report`'s per-agent times, log scale."""
    report = {label: row for label, row in report.items() if "batched" in row}
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(12, 4.5))
    names = ["batched, no obstacle", "batched", "ipopt"]
    width = 0.8 / len(names)
    for k, name in enumerate(names):
        ax.bar(np.arange(len(report)) + k * width,
               [r[name]["ms_per_agent"] for r in report.values()], width, label=name)
    ax.set_xticks(np.arange(len(report)) + width, list(report), fontsize=6, rotation=30,
                  ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("ms per agent (median)")
    ax.set_title("the mixed fleet with its ball, one chunk per call")
    ax.legend()
    save(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7, help="timed chunks per solver")
    parser.add_argument("--output", type=Path, default=Path("runs/inner-solvers"))
    parser.add_argument("--obstacles", action="store_true",
                        help="also the mixed fleet with its ball, 2-D and 3-D")
    parser.add_argument("--only-obstacles", action="store_true",
                        help="the mixed fleet with its ball alone")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    report = {}
    if args.obstacles or args.only_obstacles:
        report["obstacles"] = obstacle_report(args.repeat)
        plot_obstacles(report["obstacles"], args.output / "inner_solvers_obstacles.png")
        if args.only_obstacles:
            (args.output / "inner_solvers.json").write_text(json.dumps(report, indent=2))
            print(f"wrote {args.output / 'inner_solvers.json'}")
            return
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
    rows = {label: r for label, r in report.items() if label != "obstacles"}
    for k, solver in enumerate(SOLVERS):
        ax.bar(np.arange(len(rows)) + k * width,
               [r[solver]["ms_per_solve"] if solver in r else np.nan for r in rows.values()],
               width, label=solver)
    ax.set_xticks(np.arange(len(rows)) + width, list(rows), fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("ms per inner solve (median)")
    ax.set_title("DMOC inner solvers, one chunk per call")
    ax.legend()
    save(fig, args.output / "inner_solvers.png")
    print(f"wrote {args.output / 'inner_solvers.json'}, {args.output / 'inner_solvers.png'}")


if __name__ == "__main__":
    main()
