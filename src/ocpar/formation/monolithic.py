"""The monolithic formulation (paper §III): every agent's DMOC variables, the angles φ and the
coupling c(φ) = 0 in one CasADi NLP, solved by IPOPT in the coordinator process. The final
positions are the curve's symbolic z(φ_i), so any curve works.

It is the reference for the paper's equivalence theorem (§IV-B): from the same initial guess it
must reach the same optimum as the hierarchical scheme.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.formation.potential import coupling_expr
from ocpar.formation.problem import FormationProblem
from ocpar.ocp import dmoc_problem
from ocpar.ocp.ipopt import ipopt_options


@dataclass
class MonolithicSolution:
    """φ (n,), per-agent costs (n,), trajectories (n, N+1, nq), controls (n, N, nu), and
    IPOPT's verdict."""

    phi: np.ndarray
    agent_costs: np.ndarray
    trajectories: np.ndarray
    controls: np.ndarray
    success: bool
    status: str
    iterations: int
    solve_time_s: float


def solve_monolithic(
    problem: FormationProblem, phi0: np.ndarray, tol: float, max_iterations: int
) -> MonolithicSolution:
    """Solve the whole formation as one NLP from the initial angles ``phi0``."""
    dmoc = dmoc_problem(problem.shape)
    n, nw = problem.agents, dmoc.nw
    phi = ca.SX.sym("phi", n)
    w = ca.SX.sym("w", n * nw)
    end_velocities = problem.final_velocities(np.arange(n))
    params = [
        ca.vertcat(problem.starts[i], problem.start_velocities[i], problem.curve.point(phi[i]),
                   problem.final_attitude, end_velocities[i])
        for i in range(n)
    ]
    w_i = [w[i * nw : (i + 1) * nw] for i in range(n)]
    costs = ca.vertcat(*[dmoc.cost(w_i[i], params[i]) for i in range(n)])
    g = ca.vertcat(*[dmoc.constraints(w_i[i], params[i]) for i in range(n)],
                   coupling_expr(phi, problem.curve))
    x = ca.vertcat(w, phi)
    nlp = {"x": x, "f": ca.sum1(costs), "g": g}
    solver = ca.nlpsol("formation", "ipopt", nlp, ipopt_options(tol, max_iterations))

    x0 = np.concatenate(
        [dmoc.default_guess(problem.boundary_params(i, phi0[i])) for i in range(n)] + [phi0]
    )
    start = time.perf_counter()
    out = solver(x0=x0, lbg=0, ubg=0)
    elapsed = time.perf_counter() - start
    stats = solver.stats()
    x_opt = np.asarray(out["x"]).ravel()
    phi_opt = x_opt[n * nw :]
    agent_costs = np.asarray(ca.Function("costs", [x], [costs])(x_opt)).ravel()
    paths = [dmoc.unpack(x_opt[i * nw : (i + 1) * nw], problem.boundary_params(i, phi_opt[i]))
             for i in range(n)]
    return MonolithicSolution(
        phi=phi_opt,
        agent_costs=agent_costs,
        trajectories=np.stack([q for q, _ in paths]),
        controls=np.stack([u for _, u in paths]),
        success=bool(stats["success"]),
        status=str(stats["return_status"]),
        iterations=int(stats["iter_count"]),
        solve_time_s=elapsed,
    )
