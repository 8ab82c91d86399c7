"""Thrust-limited searches priced by the reach set first (issue 47, item 4): six point masses
in 3-D onto a sphere (the potential, ``--ordering optimal``) under |u| ≤ U and under a box
limit, both below the free optimum's peak, and a thrust-limited fleet onto an ellipse with
``--critical any``. Writes one JSON record per case (cost, status, supersteps, inner solves,
solve time, serial; each limited solve's time against the batched unconstrained solve of its
shape, :func:`per_solve`), then the same ratio on larger batches (:func:`batches`) to stdout
or ``--output``, with the machine's load.

    python scripts/reach_first.py [--cases sphere-norm,sphere-box,ellipse-any]
        [--batches 36,200] [--output F]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import casadi as ca
import numpy as np

from ocpar.formation import DmocShape, FormationProblem
from ocpar.formation.couplings.coupling import PotentialCoupling
from ocpar.formation.solve import FormationOptions, solve_formation
from ocpar.formation.targets.curve import Ellipse
from ocpar.formation.targets.surface import SphereSurface
from ocpar.models import PointMass
from ocpar.ocp.constraints import PathConstraint

#: The thrust limit as a fraction of the free (unlimited) optimum's peak |u|.
FRACTION = 0.8
#: The seed of the sphere case's start directions.
SEED = 4


def sphere_problem(**limit) -> FormationProblem:
    """Six unit masses at rest at radius 3 in seeded random directions onto the sphere of
    radius 2 about the origin (T = 2, N = 10), ``limit`` the shape's thrust fields."""
    directions = np.random.default_rng(SEED).normal(size=(6, 3))
    starts = 3.0 * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return FormationProblem(name="sphere6", curve=SphereSurface(radius=2.0),
                            shape=DmocShape(PointMass(dim=3), 10, 2.0, **limit), starts=starts)


def ellipse_problem(**limit) -> FormationProblem:
    """Five unit planar masses at rest outside the ellipse 3 × 1.5 onto it (the potential's
    isolated critical sets), T = 2, N = 10."""
    angles = np.array([0.3, 1.5, 2.9, 4.1, 5.2])
    starts = np.column_stack([4.0 * np.cos(angles), 2.5 * np.sin(angles)])
    return FormationProblem(name="ellipse5", curve=Ellipse(semi_axes=(3.0, 1.5),
                                                           center=np.zeros(2)),
                            starts=starts, coupling=PotentialCoupling(),
                            shape=DmocShape(PointMass(dim=2), 10, 2.0, **limit))


def limited(make, kind: str, options: FormationOptions) -> FormationProblem:
    """``make``'s problem under a ``kind`` (``norm`` or ``box``) thrust limit at
    :data:`FRACTION` of its free optimum's peak (of |u| or of max |u_j|)."""
    free = solve_formation(make(), options=options)
    if free.status != "converged":
        raise RuntimeError(f"free solve: {free.message}")
    if kind == "norm":
        u_max = FRACTION * float(np.linalg.norm(free.controls, axis=2).max())
        return make(path_constraints=(PathConstraint(lambda u: ca.sumsqr(u),
                                                     upper=u_max**2, name="thrust"),))
    u_max = FRACTION * float(np.abs(free.controls).max())
    dim = free.controls.shape[2]
    return make(control_bounds=((-u_max, u_max),) * dim)


CASES = {
    "sphere-norm": (sphere_problem, "norm", {}),
    "sphere-box": (sphere_problem, "box", {}),
    "ellipse-any": (ellipse_problem, "norm", {"critical": "any"}),
}


def run(case: str) -> dict:
    make, kind, extra = CASES[case]
    options = FormationOptions(ordering="optimal", **extra)
    problem = limited(make, kind, options)
    start = time.perf_counter()
    result = solve_formation(problem, options=options)
    seconds = time.perf_counter() - start
    return {"case": case, "limit": kind, "fraction": FRACTION, "status": result.status,
            "total_cost": result.total_cost if result.status == "converged" else None,
            "supersteps": result.supersteps, "inner_solves": result.inner_solves,
            "failed_solves": result.failed_solves, "seconds": round(seconds, 3),
            "message": result.message,
            "backend": "serial", "load": [round(x, 2) for x in os.getloadavg()],
            "per_solve": per_solve(make(), problem, result.phi)
            if result.status == "converged" else None}


def per_solve(free: FormationProblem, problem: FormationProblem, phi: np.ndarray,
              repeats: int = 7) -> dict:
    """Time per inner solve (ms, the median of ``repeats`` rounds, the variants alternating)
    of the limited ``problem``'s table at the answer ``phi`` (every agent to every point of
    it, the pairs inside the reach set) by :func:`~ocpar.ocp.solve_tasks` (the batched path
    and any failure policy): the same tasks without the limit (``free``: ``newton``, the
    batched unconstrained solve of the shape, and ``sqpmethod``), with it under ``auto``
    (``limited``: ``newton`` first, Newton on a guessed active set for the tasks whose path
    reaches the limit, ``sqpmethod`` for what that misses), with it by ``sqpmethod`` alone
    (``limited_sqpmethod``: ``auto``'s choice before), and the tasks whose cost the limit
    raises (``felt``: an active limit) alone, under ``auto`` and by ``sqpmethod``
    (``felt_sqpmethod``); the IPOPT retries, the tasks each solved by ``sqpmethod``
    (iterations −1) and the ratios of each limited variant to ``free`` (``newton``)."""
    from ocpar.formation.feasibility import outside_reach
    from ocpar.ocp import solve_tasks
    n = problem.agents
    agents = np.repeat(np.arange(n), n)
    ends = np.tile(np.reshape(phi, (n, -1)), (n, 1))
    inside = ~outside_reach(problem, agents, ends if ends.shape[1] > 1 else ends[:, 0])

    def solver(name: str):
        return lambda shape: dataclasses.replace(shape, solver=name)

    variants = {"free": free, "free_sqpmethod": free.with_shapes(solver("sqpmethod")),
                "limited": problem,
                "limited_sqpmethod": problem.with_shapes(solver("sqpmethod"))}
    tasks = {name: shaped.tasks_for(agents[inside], ends[inside].ravel())
             for name, shaped in variants.items()}
    solved = {name: solve_tasks(batch) for name, batch in tasks.items()}
    felt = np.flatnonzero(np.asarray(solved["limited"].column("cost"))
                          > np.asarray(solved["free"].column("cost")) * (1 + 1e-9))
    if len(felt):
        tasks["felt"] = tasks["limited"].take(felt)
        tasks["felt_sqpmethod"] = tasks["limited_sqpmethod"].take(felt)
    times: dict[str, list[float]] = {name: [] for name in tasks}
    for _ in range(repeats):
        for name, batch in tasks.items():
            start = time.perf_counter()
            solved[name] = solve_tasks(batch)
            times[name].append((time.perf_counter() - start) / len(batch))
    record = {name: {"tasks": len(tasks[name]),
                     "ms_per_solve": 1e3 * float(np.median(times[name])),
                     "by_sqpmethod": int(np.sum(np.asarray(solved[name].column("iterations"))
                                                < 0)),
                     "retries": int(np.sum(np.asarray(solved[name].column("attempts")) - 1))}
              for name in tasks}
    unconstrained = record["free"]["ms_per_solve"]
    for name in ("limited", "limited_sqpmethod", "felt", "felt_sqpmethod"):
        if name in record:
            record[name]["ratio"] = record[name]["ms_per_solve"] / unconstrained
    record["ratio_same_solver"] = (record["limited_sqpmethod"]["ms_per_solve"]
                                   / record["free_sqpmethod"]["ms_per_solve"])
    return record


def batches(sizes: list[int], repeats: int = 9) -> list[dict]:
    """Time per solve (ms, medians of ``repeats``, alternating) of k point masses in 3-D from
    rest at the origin to rest at ends 1.0–1.4 away in seeded directions (T = 2, N = 10),
    under |u| ≤ 1.7 (``norm``) or |u_j| ≤ 1.5 (``box``; the limit active on most), under
    ``auto`` and by ``sqpmethod`` alone, against the same tasks without the limit
    (``newton``), for each k in ``sizes``."""
    from ocpar.ocp import OcpTask, solve_tasks
    limits = {"norm": {"path_constraints": (PathConstraint(lambda u: ca.sumsqr(u),
                                                           upper=1.7**2, name="thrust"),)},
              "box": {"control_bounds": ((-1.5, 1.5),) * 3}}
    records = []
    for limit, fields in limits.items():
        for k in sizes:
            directions = np.random.default_rng(7).normal(size=(k, 3))
            ends = (np.linspace(1.0, 1.4, k)[:, None] * directions
                    / np.linalg.norm(directions, axis=1, keepdims=True))
            params = np.hstack([np.zeros((k, 6)), ends, np.zeros((k, 3))])
            shapes = {"free": DmocShape(PointMass(dim=3), 10, 2.0),
                      **{solver: DmocShape(PointMass(dim=3), 10, 2.0, solver=solver, **fields)
                         for solver in ("auto", "sqpmethod")}}
            tasks = {name: [OcpTask(shape, p) for p in params] for name, shape in shapes.items()}
            solved = {name: solve_tasks(batch) for name, batch in tasks.items()}
            times: dict[str, list[float]] = {name: [] for name in tasks}
            for _ in range(repeats):
                for name, batch in tasks.items():
                    start = time.perf_counter()
                    solve_tasks(batch)
                    times[name].append((time.perf_counter() - start) / k)
            ms = {name: 1e3 * float(np.median(t)) for name, t in times.items()}
            records.append({"limit": limit, "tasks": k, "ms_per_solve": ms,
                            "ratio": {name: ms[name] / ms["free"]
                                      for name in ("auto", "sqpmethod")},
                            "failed": {name: int(sum(not s.success for s in solved[name]))
                                       for name in solved},
                            "by_sqpmethod": int(sum(s.iterations < 0 for s in solved["auto"]))})
    return records


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--batches", default="36,200",
                        help="batch sizes of the limited solve against the unconstrained one "
                             "(empty: none)")
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    records = [run(case) for case in args.cases.split(",") if case]
    sizes = [int(k) for k in args.batches.split(",") if k]
    if sizes:
        records.append({"batches": batches(sizes),
                        "load": [round(x, 2) for x in os.getloadavg()]})
    text = json.dumps(records, indent=1)
    if args.output:
        args.output.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
