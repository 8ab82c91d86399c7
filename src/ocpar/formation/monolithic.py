"""The monolithic formulation (paper §III): every agent's DMOC variables, the angles φ and the
coupling c(φ) = 0 in one CasADi NLP, solved by IPOPT in the coordinator process. The final
positions are the curve's symbolic z(φ_i), so any curve works.

It is the reference for the paper's equivalence theorem (§IV-B): from the same initial guess it
must reach the same optimum as the hierarchical scheme. With obstacles, every agent's NLP
carries them with the same planes (:mod:`ocpar.ocp.obstacles`), and the side each agent
passes each obstacle on is the start's: each agent's path starts as its own inner optimum at
the initial angles (the cheapest side, as in the hierarchical scheme's inner solves).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.formation.problem import FormationProblem
from ocpar.ocp import DmocTranscription, dmoc_problem
from ocpar.ocp.ipopt import ipopt_options


@dataclass
class MonolithicSolution:
    """φ (n,), per-agent costs (n,), trajectories (n, N+1, nq), controls (n, N, nu), IPOPT's
    verdict, and ``violation``: the returned point's largest constraint or bound violation
    (the model's units; checked here, not taken from IPOPT)."""

    phi: np.ndarray
    agent_costs: np.ndarray
    trajectories: np.ndarray
    controls: np.ndarray
    success: bool
    status: str
    iterations: int
    solve_time_s: float
    violation: float = 0.0


def solve_monolithic(
    problem: FormationProblem, phi0: np.ndarray, tol: float, max_iterations: int
) -> MonolithicSolution:
    """Solve the whole formation as one NLP from the initial angles ``phi0``: each agent's
    DMOC NLP on its own shape (a mixed fleet), with its bounds and inequalities, the angles
    free, the coupling = 0."""
    dmocs = [dmoc_problem(shape) for shape in problem.shapes]
    n = problem.agents
    offsets = np.concatenate([[0], np.cumsum([dmoc.nw for dmoc in dmocs])])
    phi = ca.SX.sym("phi", n)
    w = ca.SX.sym("w", int(offsets[-1]))
    end_velocities = problem.final_velocities(np.arange(n))
    params = [
        ca.vertcat(problem.starts[i], problem.start_velocities[i], problem.curve.point(phi[i]),
                   problem.final_attitude, end_velocities[i])
        for i in range(n)
    ]
    w_i = [w[offsets[i] : offsets[i + 1]] for i in range(n)]
    costs = ca.vertcat(*[dmocs[i].cost(w_i[i], params[i]) for i in range(n)])
    coupling_rows = problem.coupling.expr(phi, problem.curve)
    g = ca.vertcat(*[dmocs[i].constraints(w_i[i], params[i]) for i in range(n)], coupling_rows)
    x = ca.vertcat(w, phi)
    nlp = {"x": x, "f": ca.sum1(costs), "g": g}
    bounds = _bounds(dmocs, coupling_rows.numel(), n)
    # IPOPT relaxes inequalities by 1e-8 (relative) unless told not to
    exact = ({"bound_relax_factor": 0.0} if any(d.has_inequalities for d in dmocs) else {})
    solver = ca.nlpsol("formation", "ipopt", nlp, ipopt_options(tol, max_iterations, **exact))

    x0 = np.concatenate([_start(dmocs[i], problem.boundary_params(i, phi0[i]))
                         for i in range(n)] + [phi0])
    start = time.perf_counter()
    out = solver(x0=x0, **bounds)
    elapsed = time.perf_counter() - start
    stats = solver.stats()
    x_opt = np.asarray(out["x"]).ravel()
    phi_opt = x_opt[offsets[-1]:]
    agent_costs = np.asarray(ca.Function("costs", [x], [costs])(x_opt)).ravel()
    rows = np.asarray(ca.Function("g", [x], [g])(x_opt)).ravel()
    paths = [dmocs[i].unpack(x_opt[offsets[i] : offsets[i + 1]],
                             problem.boundary_params(i, phi_opt[i])) for i in range(n)]
    return MonolithicSolution(
        phi=phi_opt,
        agent_costs=agent_costs,
        trajectories=np.stack([q for q, _ in paths]),
        controls=np.stack([u for _, u in paths]),
        success=bool(stats["success"]),
        status=str(stats["return_status"]),
        iterations=int(stats["iter_count"]),
        solve_time_s=elapsed,
        violation=violation(rows, x_opt, bounds),
    )


def violation(rows: np.ndarray, x: np.ndarray, bounds: dict) -> float:
    """max(lbg − g, g − ubg, lbx − x, x − ubx, 0) of the constraint rows ``rows`` and the
    point ``x`` under IPOPT's ``bounds`` (scalars broadcast); +∞ if not finite."""
    if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(x))):
        return float("inf")
    lbg, ubg = (np.broadcast_to(bounds[k], rows.shape) for k in ("lbg", "ubg"))
    lbx, ubx = (np.broadcast_to(bounds.get(k, fill), x.shape)
                for k, fill in (("lbx", -np.inf), ("ubx", np.inf)))
    return float(max(0.0, np.max(lbg - rows), np.max(rows - ubg), np.max(lbx - x),
                     np.max(x - ubx)))


def _start(dmoc: DmocTranscription, params: np.ndarray) -> np.ndarray:
    """Agent's start: the default guess; with obstacle planes its inner optimum at ``params``
    (its side of each obstacle; the default guess if that solve fails)."""
    guess = dmoc.default_guess(params)
    if not dmoc.n_planes:
        return guess
    solution = dmoc.solve(params)
    return dmoc.full_guess(dmoc.warm_start(solution), params) if solution.success else guess


def _bounds(dmocs: list[DmocTranscription], n_coupling: int, n_angles: int
            ) -> dict[str, np.ndarray | float]:
    """IPOPT's bounds for the stacked agents' NLPs, the coupling rows (= 0) and the free
    angles: none where no agent has inequalities (the NLP of old)."""
    if not any(dmoc.has_inequalities for dmoc in dmocs):
        return {"lbg": 0, "ubg": 0}
    free = np.full(n_angles, np.inf)
    return {"lbg": np.concatenate([d.lbg for d in dmocs] + [np.zeros(n_coupling)]),
            "ubg": np.concatenate([d.ubg for d in dmocs] + [np.zeros(n_coupling)]),
            "lbx": np.concatenate([d.lbx for d in dmocs] + [-free]),
            "ubx": np.concatenate([d.ubx for d in dmocs] + [free])}
