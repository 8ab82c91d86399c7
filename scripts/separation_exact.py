#!/usr/bin/env python
"""What the separation rounds leave against an exact monolithic solve with pairwise constraints,
and the hierarchical scheme's exact separation against the monolithic optimum.

    python scripts/separation_exact.py --output runs/separation-exact   # 6 masses, D .25 .5 .75
    python scripts/separation_exact.py --cases --output runs/separation-cases   # issue 42's three

A small case whose unconstrained optimum has two agents pass close: point masses (mass 1, T = 1,
N = 10) starting at rest on two staggered rows below the circle of radius 2 about (0, 6), onto
it at rest, coupled by the formation paper's potential (the 6 masses' agents 2 and 5 come
within 0.10). For each D:

(a) ocpar's hierarchical run with ``min_separation`` D and ``separation="rounds"``: the
    outer solve without separation, then the separation rounds
    (:mod:`ocpar.formation.keep_out.rounds`; φ is not re-optimised); and the default
    (``separation="exact"``, :mod:`ocpar.formation.keep_out.exact`: clusters of close agents
    with their planes, the rotation searched), whose gap to (b) is ``hierarchical_gap``;
(b) the exact monolithic NLP, built here: every agent's DMOC NLP
    (:func:`ocpar.ocp.dmoc_problem` of its shape, its ``constraints`` and ``cost``), the final
    angles free under the coupling rows, and for every pair (i, j) and interval k a plane
    n ∈ R^d with |n|² ≤ 1, n·Δ_k ≥ D and n·Δ_{k+1} ≥ D, Δ = r_i − r_j: the relative position is
    linear in t on the interval, so this holds exactly when the pair stays ≥ D apart on the
    whole continuous (piecewise-linear) interval (the rows of :func:`ocpar.ocp.obstacles.
    obstacle_rows` for a ball of radius D about Δ = 0). IPOPT from the rounds' answer, and
    from the unconstrained one (planes: each interval's nearest-point direction).

Reported per D: each answer's cost, the rounds' cost above the better exact optimum
(relative, ``cost_gap``), the part of it the paths leave at the rounds' φ (``path_gap``:
against the same NLP with φ held at the rounds' angles, no coupling rows), the rotation of the
exact formation against the rounds' (the circular mean of φ_exact − φ_rounds, rad), each
closest approach (exact on the continuous paths), the rounds and IPOPT's verdicts. Writes
``separation_exact.json`` and ``separation_exact.png`` (cost increase over the unconstrained
optimum against D; the paths at the largest D side by side).

``--cases``: the three cases of issue 42 (the paper's 60 point masses with D = 0.5, 12 of them
with D = 4, the 30 halo spacecraft with D = 0.05 km = 50 m, each ``--ordering keep``): the
hierarchical run (exact separation), the separation rounds alone and ``--mode monolithic``,
each one's cost, closest approach, pair and wall time, and the hierarchical and the rounds'
cost relative to the monolithic; for the 12 masses also the all-pairs NLP above (every pair
a plane on every interval, from the monolithic answer). Writes ``separation_cases.json`` and
``separation_cases.png`` (the relative differences, log scale).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from pathlib import Path

import casadi as ca
import numpy as np

from ocpar.examples import formation_halo
from ocpar.examples.formation_point_masses import make as point_masses
from ocpar.formation import Circle, DmocShape, FormationOptions, FormationProblem, solve_formation
from ocpar.formation.monolithic import violation
from ocpar.models import PointMass
from ocpar.ocp import dmoc_problem
from ocpar.ocp.ipopt import ipopt_options
from ocpar.ocp.obstacles import Sphere, guess_planes, obstacle_rows
from ocpar.plotting import pyplot, save


def make_problem(agents: int) -> FormationProblem:
    """``agents`` (even) planar point masses on two staggered rows (spacing 4/(m−1), the
    second row 1 lower and 0.4 to the right) onto the circle of radius 2 about (0, 6)."""
    if agents < 4 or agents % 2:
        raise ValueError(f"agents: must be even and >= 4, got {agents}")
    m = agents // 2
    row = np.linspace(-2.0, 2.0, m)
    starts = np.concatenate([np.stack([row, np.zeros(m)], 1),
                             np.stack([row + 0.4, np.full(m, -1.0)], 1)])
    return FormationProblem(
        name=f"two-rows-{agents}", shape=DmocShape(PointMass(dim=2), intervals=10, duration=1.0),
        curve=Circle(radius=2.0, center=np.array([0.0, 6.0])), starts=starts)


def exact_solve(problem: FormationProblem, distance: float, phi0: np.ndarray,
                trajectories: np.ndarray, controls: np.ndarray, tol: float,
                fix_phi: bool = False) -> dict:
    """The monolithic NLP with the pairwise planes (module docstring) from the angles
    ``phi0`` (n,), node paths ``trajectories`` (n, N+1, nq) and controls (n, N, nu): cost,
    φ, paths, closest approach, IPOPT's status and the returned point's largest violation.
    ``fix_phi``: the angles held at ``phi0`` (no coupling rows): the best paths there."""
    dmocs = [dmoc_problem(shape) for shape in problem.shapes]
    n, nq, intervals = problem.agents, dmocs[0].nq, dmocs[0].n
    offsets = np.concatenate([[0], np.cumsum([d.nw for d in dmocs])])
    phi = ca.SX.sym("phi", n)
    w = ca.SX.sym("w", int(offsets[-1]))
    pairs = list(itertools.combinations(range(n), 2))
    dim = len(problem.position_indices)
    planes = ca.SX.sym("planes", len(pairs) * intervals * dim)
    end_velocities = problem.final_velocities(np.arange(n))
    params = [ca.vertcat(problem.starts[i], problem.start_velocities[i],
                         problem.curve.point(phi[i]), problem.final_attitude, end_velocities[i])
              for i in range(n)]
    w_i = [w[offsets[i]:offsets[i + 1]] for i in range(n)]
    where = list(problem.position_indices)
    nodes = [[params[i][:nq][where]]
             + [w_i[i][k * nq:(k + 1) * nq][where] for k in range(intervals - 1)]
             + [params[i][2 * nq:3 * nq][where]] for i in range(n)]
    ball = [Sphere(np.zeros(dim), distance, "separation")]
    block = intervals * dim
    pair_rows = [row for p, (i, j) in enumerate(pairs)
                 for row in obstacle_rows(ball, [a - b for a, b in zip(nodes[i], nodes[j],
                                                                       strict=True)],
                                          planes[p * block:(p + 1) * block])]
    costs = ca.vertcat(*[dmocs[i].cost(w_i[i], params[i]) for i in range(n)])
    coupling = ca.SX(0, 1) if fix_phi else problem.coupling.expr(phi, problem.curve)
    g = ca.vertcat(*[dmocs[i].constraints(w_i[i], params[i]) for i in range(n)], coupling,
                   *pair_rows)
    x = ca.vertcat(w, phi, planes)
    unbounded = np.full(planes.numel(), np.inf)
    lower = np.concatenate([phi0 if fix_phi else np.full(n, -np.inf), -unbounded])
    upper = np.concatenate([phi0 if fix_phi else np.full(n, np.inf), unbounded])
    bounds = {"lbg": np.concatenate([d.lbg for d in dmocs] + [np.zeros(coupling.numel()),
                                                               np.zeros(len(pair_rows))]),
              "ubg": np.concatenate([d.ubg for d in dmocs] + [np.zeros(coupling.numel()),
                                                               np.full(len(pair_rows), np.inf)]),
              "lbx": np.concatenate([d.lbx for d in dmocs] + [lower]),
              "ubx": np.concatenate([d.ubx for d in dmocs] + [upper])}
    solver = ca.nlpsol("separation_exact", "ipopt", {"x": x, "f": ca.sum1(costs), "g": g},
                       ipopt_options(tol, 3000, bound_relax_factor=0.0))
    positions = problem.positions(trajectories)
    relative = np.stack([positions[i] - positions[j] for i, j in pairs])
    x0 = np.concatenate(
        [dmocs[i].full_guess(np.concatenate([trajectories[i, 1:-1].ravel(), controls[i].ravel()]),
                             problem.boundary_params(i, phi0[i])) for i in range(n)]
        + [phi0, guess_planes(ball, relative).ravel()])
    start = time.perf_counter()
    out = solver(x0=x0, **bounds)
    elapsed = time.perf_counter() - start
    x_opt = np.asarray(out["x"]).ravel()
    phi_opt = x_opt[offsets[-1]:offsets[-1] + n]
    paths = np.stack([dmocs[i].unpack(x_opt[offsets[i]:offsets[i + 1]],
                                      problem.boundary_params(i, phi_opt[i]))[0]
                      for i in range(n)])
    closest = problem.closest_approach(paths)
    stats = solver.stats()
    return {"cost": float(out["f"]), "phi": phi_opt.tolist(), "status": stats["return_status"],
            "success": bool(stats["success"]), "iterations": int(stats["iter_count"]),
            "violation": violation(np.asarray(out["g"]).ravel(), x_opt, bounds),
            "min_separation": closest.distance, "closest_pair": list(closest.agents),
            "solve_time_s": elapsed, "trajectories": paths}


def rotation(phi: np.ndarray, reference: np.ndarray) -> float:
    """The circular mean of φ − reference (rad, in (−π, π])."""
    diff = np.asarray(phi) - np.asarray(reference)
    return float(np.angle(np.mean(np.exp(1j * diff))))


#: Issue 42's cases: name, problem factory, D (length unit), whether the all-pairs NLP runs.
CASES = (("60 point masses", point_masses, 0.5, False),
         ("12 point masses", lambda: point_masses(agents=12), 4.0, True),
         ("30 halo spacecraft", lambda: formation_halo.make(agents=30), 0.05, False))


def cases(output: Path, tol: float) -> None:
    """The ``--cases`` report (module docstring)."""
    report = []
    for name, factory, distance, all_pairs in CASES:
        problem = factory()
        runs = {}
        for label, extra in (("hierarchical", {}), ("rounds", {"separation": "rounds"}),
                             ("monolithic", {"mode": "monolithic"})):
            start = time.perf_counter()
            run = solve_formation(problem, options=FormationOptions(min_separation=distance,
                                                                    **extra))
            runs[label] = run
            runs[label + "_wall"] = time.perf_counter() - start
        mono = runs["monolithic"]
        entry = {"case": name, "agents": problem.agents, "distance": distance}
        for label in ("hierarchical", "rounds", "monolithic"):
            run = runs[label]
            entry[label] = {"status": run.status, "cost": run.total_cost,
                            "min_separation": run.separation.distance,
                            "closest_pair": list(run.separation.agents),
                            "wall_s": runs[label + "_wall"],
                            "relative_to_monolithic": run.total_cost / mono.total_cost - 1,
                            "rotation_rad": rotation(run.phi, mono.phi)}
        if all_pairs:
            independent = exact_solve(problem, distance, mono.phi, mono.trajectories,
                                      mono.controls, tol)
            entry["all_pairs_nlp"] = {k: v for k, v in independent.items()
                                      if k not in ("trajectories", "phi")}
            entry["hierarchical"]["relative_to_all_pairs"] = (
                runs["hierarchical"].total_cost / independent["cost"] - 1)
        report.append(entry)
        print(json.dumps(entry), flush=True)
    (output / "separation_cases.json").write_text(json.dumps(report, indent=1))
    fig, axis = pyplot().subplots(figsize=(7, 4))
    x = np.arange(len(report))
    for shift, label in ((-0.2, "hierarchical"), (0.2, "rounds")):
        values = [max(abs(e[label]["relative_to_monolithic"]), 1e-17) for e in report]
        axis.bar(x + shift, values, width=0.4, label=f"{label} (exact separation)"
                 if label == "hierarchical" else "separation rounds alone")
    axis.set_yscale("log")
    axis.axhline(1e-6, color="0.5", linestyle="--", linewidth=0.8)
    axis.set_xticks(x, [f"{e['case']}\nD = {e['distance']:g}" for e in report], fontsize=8)
    axis.set_ylabel("|cost / monolithic optimum − 1| (1e-17: equal)")
    axis.legend(fontsize=8)
    axis.set_title("minimum separation: hierarchical against monolithic")
    save(fig, output / "separation_cases.png")
    print(f"wrote {output / 'separation_cases.json'}, {output / 'separation_cases.png'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=6)
    parser.add_argument("--distances", type=float, nargs="+", default=[0.25, 0.5, 0.75],
                        help="D values, length unit")
    parser.add_argument("--tol", type=float, default=1e-10, help="IPOPT's tol (exact NLP)")
    parser.add_argument("--cases", action="store_true",
                        help="issue 42's three cases instead (module docstring)")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    if args.cases:
        cases(args.output, args.tol)
        return
    problem = make_problem(args.agents)
    free = solve_formation(problem)
    report: dict = {"problem": problem.name, "agents": problem.agents,
                    "unconstrained": {"status": free.status, "cost": free.total_cost,
                                      "min_separation": free.separation.distance,
                                      "closest_pair": list(free.separation.agents)},
                    "distances": []}
    print("unconstrained", json.dumps(report["unconstrained"]), flush=True)
    paths = {}
    for distance in args.distances:
        start = time.perf_counter()
        kept = solve_formation(problem, options=FormationOptions(min_separation=distance,
                                                                 separation="rounds"))
        wall = time.perf_counter() - start
        hierarchical = solve_formation(problem, options=FormationOptions(
            min_separation=distance))
        exact = {name: exact_solve(problem, distance, run.phi, run.trajectories, run.controls,
                                   args.tol, fix_phi=name == "at_rounds_phi")
                 for name, run in (("from_rounds", kept), ("from_unconstrained", free),
                                   ("at_rounds_phi", kept))}
        solved = [exact[name] for name in ("from_rounds", "from_unconstrained")
                  if exact[name]["success"]]
        best = min(solved, key=lambda e: e["cost"]) if solved else None
        fixed = exact["at_rounds_phi"]
        entry = {
            "distance": distance,
            "rounds": {"status": kept.status, "cost": kept.total_cost, "phi": kept.phi.tolist(),
                       "separation_rounds": kept.separation_rounds,
                       "min_separation": kept.separation.distance,
                       "closest_pair": list(kept.separation.agents), "wall_s": wall},
            "exact": {name: {k: v for k, v in e.items() if k != "trajectories"}
                      for name, e in exact.items()},
            "cost_gap": math.nan if best is None else kept.total_cost / best["cost"] - 1,
            "path_gap": kept.total_cost / fixed["cost"] - 1 if fixed["success"] else math.nan,
            "rotation_rad": math.nan if best is None else rotation(best["phi"], kept.phi),
            "hierarchical": {"status": hierarchical.status, "cost": hierarchical.total_cost,
                             "min_separation": hierarchical.separation.distance,
                             "rotation_rad": rotation(hierarchical.phi, kept.phi)},
            "hierarchical_gap": (math.nan if best is None
                                 else hierarchical.total_cost / best["cost"] - 1),
        }
        report["distances"].append(entry)
        paths[distance] = (kept.trajectories, None if best is None else best["trajectories"])
        print(f"D {distance:g}", json.dumps(entry), flush=True)
    (args.output / "separation_exact.json").write_text(json.dumps(report, indent=1))
    plot(problem, report, paths, args.output / "separation_exact.png")
    print(f"wrote {args.output / 'separation_exact.json'}, {args.output / 'separation_exact.png'}")


def plot(problem: FormationProblem, report: dict, paths: dict, path: Path) -> None:
    """Cost increase over the unconstrained optimum against D (rounds, exact); the paths of
    both at the largest D."""
    fig, (left, right) = pyplot().subplots(1, 2, figsize=(11, 4.5))
    base = report["unconstrained"]["cost"]
    rows = report["distances"]
    d = [r["distance"] for r in rows]
    left.plot(d, [100 * (r["rounds"]["cost"] / base - 1) for r in rows], "o-",
              label="separation rounds (φ kept)")
    for name, style, label in (("from_rounds", "s--", "exact monolithic, from the rounds"),
                               ("from_unconstrained", "x:", "exact monolithic, from unconstrained"),
                               ("at_rounds_phi", "^-.", "exact paths at the rounds' φ")):
        left.plot(d, [100 * (r["exact"][name]["cost"] / base - 1) for r in rows], style,
                  label=label)
    left.set_xlabel("required separation D")
    left.set_ylabel("cost above the unconstrained optimum (%)")
    left.legend(fontsize=8)
    largest = max(paths)
    kept, exact = paths[largest]
    for i in range(problem.agents):
        r = problem.positions(kept)[i]
        right.plot(r[:, 0], r[:, 1], "-", color=f"C{i}", linewidth=1)
        if exact is not None:
            e = problem.positions(exact)[i]
            right.plot(e[:, 0], e[:, 1], "--", color=f"C{i}", linewidth=1)
    ring = problem.curve.points(np.linspace(0.0, 2 * np.pi, 200))
    right.plot(ring[:, 0], ring[:, 1], color="0.7", linewidth=0.8)
    right.set_aspect("equal")
    right.set_title(f"D = {largest:g}: rounds (solid), exact (dashed)", fontsize=9)
    fig.suptitle(f"{problem.name}: separation rounds against the exact monolithic solve")
    save(fig, path)


if __name__ == "__main__":
    main()
