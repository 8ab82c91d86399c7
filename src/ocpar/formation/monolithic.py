"""The monolithic formulation (paper §III): every agent's NLP variables, the angles φ and the
coupling c(φ) = 0 in one CasADi NLP, solved by IPOPT in the coordinator process. The final
positions are the curve's symbolic z(φ_i), so any curve works. Each agent's part is the NLP of
its shape's transcription, the one its inner problems solve (the agent-shape interface of
:mod:`ocpar.ocp.endpoint_agents`: a DMOC agent's, or an ODE agent's multiple shooting), its
boundary data p with the end position's entries the curve's point: any fleet, mixed ones too.

It is the reference for the paper's equivalence theorem (§IV-B): from the same initial guess it
must reach the same optimum as the hierarchical scheme. With obstacles, every agent's NLP
carries them as its inner problems do (:mod:`ocpar.ocp.obstacles`), and the side each agent
passes each obstacle on is the start's: each agent's path starts as its own inner optimum at
the initial angles (the cheapest side, as in the hierarchical scheme's inner solves), as does
every ODE agent's (its default guess is a straight line, far from a nonlinear model's path).

With a minimum separation D (DMOC agents: their paths between nodes are segments) every pair
that comes within D of each other gets, on each interval, a separating plane: a normal ν (|ν| ≤
1, variables of the NLP) with ν·(p_i − p_j) ≥ D at the interval's two nodes, so that the whole
segment of their relative position stays D from the origin (a segment lies at distance ≥ D from
the origin exactly when such a ν exists: the plane is no approximation). Pairs are added by
constraint generation: solve, find the pairs whose continuous paths come within D
(:func:`~ocpar.formation.keep_out.separation.close_pairs`), add their planes and solve again
from the last point, until no pair breaks D (at most :data:`SEPARATION_ROUNDS` solves).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.formation.finish import padded_paths
from ocpar.formation.keep_out.separation import close_pairs
from ocpar.formation.problem import FormationProblem
from ocpar.ocp import (
    DmocShape,
    DmocTranscription,
    MsEndpointShape,
    MsEndpointTranscription,
    transcription,
)
from ocpar.ocp.solver_options import ipopt

#: An agent's NLP: its shape's transcription.
AgentNlp = DmocTranscription | MsEndpointTranscription


@dataclass
class MonolithicSolution:
    """φ (n,), per-agent costs (n,), trajectories (n, N+1, nq; a mixed fleet's narrower
    paths padded with NaN), controls (n, N, nu), IPOPT's
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
    #: with a minimum separation: the pairs (m, 2) that carry separating planes
    separated_pairs: np.ndarray | None = None


#: Most solves of the constraint generation for a minimum separation (module docstring).
SEPARATION_ROUNDS = 10


def solve_monolithic(
    problem: FormationProblem, phi0: np.ndarray, tol: float, max_iterations: int,
    min_separation: float | None = None,
) -> MonolithicSolution:
    """Solve the whole formation as one NLP from the initial angles ``phi0``: each agent's
    NLP on its own shape (DMOC or multiple shooting; a mixed fleet), with its bounds and
    inequalities, the angles
    free, the coupling = 0; with ``min_separation`` D (length unit) every two agents' paths
    at least D apart (module docstring)."""
    pairs = np.zeros((0, 2), np.intp)
    x0, lam0 = None, None
    for _ in range(SEPARATION_ROUNDS if min_separation is not None else 1):
        sol, x0, lam0 = _solve(problem, phi0, tol, max_iterations, min_separation, pairs,
                               x0, lam0)
        if min_separation is None or not np.all(np.isfinite(sol.trajectories)):
            return sol
        close = close_pairs(problem.positions(sol.trajectories), min_separation * (1 - 1e-9))
        new = np.array([p for p in map(tuple, close) if p not in set(map(tuple, pairs))],
                       np.intp).reshape(-1, 2)
        if not len(new):
            return sol
        pairs = np.concatenate([pairs, new])
        x0 = np.concatenate([x0[:-_plane_count(problem, len(pairs) - len(new))]
                             if len(pairs) > len(new) else x0,
                             _plane_guess(problem, sol.trajectories, pairs)])
        lam0 = None
    sol.success = False
    sol.status = (f"{sol.status}; pairs still within the separation after "
                  f"{SEPARATION_ROUNDS} rounds of planes")
    return sol


def _plane_count(problem: FormationProblem, pairs: int) -> int:
    """Variables of ``pairs`` pairs' separating planes: one normal (p,) per interval."""
    return pairs * problem.common_shape.intervals * len(problem.position_indices)


def _plane_guess(problem: FormationProblem, trajectories: np.ndarray, pairs: np.ndarray
                 ) -> np.ndarray:
    """Each pair's normals, interval by interval: its relative position at the interval's
    midpoint, made unit (flattened: pair, interval, axis)."""
    p = problem.positions(trajectories)
    mid = 0.5 * (p[:, :-1] + p[:, 1:])
    rel = mid[pairs[:, 0]] - mid[pairs[:, 1]]
    return (rel / np.maximum(np.linalg.norm(rel, axis=-1, keepdims=True), 1e-300)).ravel()


def _solve(problem: FormationProblem, phi0: np.ndarray, tol: float, max_iterations: int,
           min_separation: float | None, pairs: np.ndarray, x0: np.ndarray | None,
           lam0: np.ndarray | None) -> tuple[MonolithicSolution, np.ndarray, np.ndarray]:
    """One IPOPT solve with the separating planes of ``pairs`` (from ``x0``, the default
    start if None): the solution, its primal point and constraint multipliers."""
    nlps: list[AgentNlp] = [transcription(shape) for shape in problem.shapes]
    n = problem.agents
    offsets = np.concatenate([[0], np.cumsum([nlp.nw for nlp in nlps])])
    phi = ca.SX.sym("phi", n)
    w = ca.SX.sym("w", int(offsets[-1]))
    given = problem.boundary_params_rows(np.arange(n), phi0)
    params = [_ending_at(shape, given[i], problem.curve.point(phi[i]))
              for i, shape in enumerate(problem.shapes)]
    w_i = [w[offsets[i] : offsets[i + 1]] for i in range(n)]
    costs = ca.vertcat(*[nlps[i].cost(w_i[i], params[i]) for i in range(n)])
    coupling_rows = problem.coupling.expr(phi, problem.curve)
    planes = ca.SX.sym("planes", _plane_count(problem, len(pairs)))
    separation = _separation_rows(problem, nlps, w_i, params, pairs, planes, min_separation)
    g = ca.vertcat(*[nlps[i].constraints(w_i[i], params[i]) for i in range(n)],
                   coupling_rows, separation)
    x = ca.vertcat(w, phi, planes)
    nlp = {"x": x, "f": ca.sum1(costs), "g": g}
    bounds = _bounds(nlps, coupling_rows.numel(), n, len(pairs) * problem.common_shape.intervals,
                     planes.numel())
    # IPOPT relaxes inequalities by 1e-8 (relative) unless told not to
    exact = ({"bound_relax_factor": 0.0}
             if any(d.has_inequalities for d in nlps) or len(pairs) else {})
    # the user's ipopt.* solver options, as the first agent's shape has them
    solver = ca.nlpsol("formation", "ipopt", nlp, ipopt(
        problem.common_shape.solver_options, tol, max_iterations, **exact))

    if x0 is None:
        x0 = np.concatenate([_start(nlps[i], problem.boundary_params(i, phi0[i]))
                             for i in range(n)] + [phi0])
    start = time.perf_counter()
    out = solver(x0=x0, **bounds, **({} if lam0 is None else {"lam_g0": lam0}))
    elapsed = time.perf_counter() - start
    stats = solver.stats()
    x_opt = np.asarray(out["x"]).ravel()
    phi_opt = x_opt[offsets[-1]:offsets[-1] + n]
    agent_costs = np.asarray(ca.Function("costs", [x], [costs])(x_opt)).ravel()
    rows = np.asarray(ca.Function("g", [x], [g])(x_opt)).ravel()
    paths = [nlps[i].unpack(x_opt[offsets[i] : offsets[i + 1]],
                             problem.boundary_params(i, phi_opt[i])) for i in range(n)]
    return MonolithicSolution(
        phi=phi_opt,
        agent_costs=agent_costs,
        trajectories=padded_paths([q for q, _ in paths], problem.node_width),
        controls=np.stack([u for _, u in paths]),
        success=bool(stats["success"]),
        status=str(stats["return_status"]),
        iterations=int(stats["iter_count"]),
        solve_time_s=elapsed,
        violation=violation(rows, x_opt, bounds),
        separated_pairs=pairs if min_separation is not None else None,
    ), x_opt, np.asarray(out["lam_g"]).ravel()


def _ending_at(shape: DmocShape | MsEndpointShape, params: np.ndarray, point: ca.SX) -> ca.SX:
    """The boundary data ``params`` (n_params,) with the end position's entries (those of
    the agent-shape interface, :mod:`ocpar.ocp.endpoint_agents`) the symbolic ``point`` (d,)."""
    entries = shape.boundary_size + shape.end_position_entries(point.numel())
    symbolic = ca.SX(ca.DM(params))
    for k, entry in enumerate(entries.tolist()):
        symbolic[entry] = point[k]
    return symbolic


def _separation_rows(problem: FormationProblem, nlps: list[DmocTranscription],
                     w_i: list[ca.SX], params: list[ca.SX], pairs: np.ndarray, planes: ca.SX,
                     distance: float | None) -> ca.SX:
    """Per pair and interval: ν·(p_i − p_j) − D at the interval's two nodes (≥ 0) and
    1 − |ν|² (≥ 0), ν the pair's normal there (module docstring); none without pairs."""
    if not len(pairs):
        return ca.SX(0, 1)
    index = list(problem.position_indices)
    nodes = [nlps[i].nodes(w_i[i], params[i]) for i in range(problem.agents)]
    d, intervals = len(index), problem.common_shape.intervals
    rows = []
    for k, (i, j) in enumerate(pairs):
        for t in range(intervals):
            nu = planes[(k * intervals + t) * d:(k * intervals + t + 1) * d]
            for node in (t, t + 1):
                rel = nodes[i][node][index] - nodes[j][node][index]
                rows.append(ca.dot(nu, rel) - distance)
            rows.append(1 - ca.sumsqr(nu))
    return ca.vertcat(*rows)


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


def _start(nlp: AgentNlp, params: np.ndarray) -> np.ndarray:
    """Agent's start: its inner optimum at ``params`` where its shape re-solves from its
    previous solution (:attr:`~ocpar.ocp.DmocShape.resolves_from_previous`: obstacle planes'
    sides, every ODE agent; the default guess if that solve fails), else the default guess."""
    guess = nlp.default_guess(params)
    if not nlp.shape.resolves_from_previous:
        return guess
    solution = nlp.solve(params)
    return nlp.full_guess(nlp.warm_start(solution), params) if solution.success else guess


def _bounds(nlps: list[AgentNlp], n_coupling: int, n_angles: int,
            plane_intervals: int = 0, n_planes: int = 0) -> dict[str, np.ndarray | float]:
    """IPOPT's bounds for the stacked agents' NLPs, the coupling rows (= 0), the free angles
    and, with a minimum separation, the planes' rows (≥ 0, three per pair and interval) and
    free normals: none where nothing has inequalities (the NLP of old)."""
    if not any(nlp.has_inequalities for nlp in nlps) and not plane_intervals:
        return {"lbg": 0, "ubg": 0}
    free = np.full(n_angles + n_planes, np.inf)
    rows = 3 * plane_intervals
    return {"lbg": np.concatenate([d.lbg for d in nlps] + [np.zeros(n_coupling + rows)]),
            "ubg": np.concatenate([d.ubg for d in nlps]
                                  + [np.zeros(n_coupling), np.full(rows, np.inf)]),
            "lbx": np.concatenate([d.lbx for d in nlps] + [-free]),
            "ubx": np.concatenate([d.ubx for d in nlps] + [free])}
