"""The minimum separation imposed exactly in the hierarchical scheme: close agents' inner
problems solved together with their separating planes, the formation's rotation
re-optimised under them.

The exact problem (:mod:`ocpar.formation.monolithic`) gives each close pair (i, j) and
interval k a normal ν (|ν| ≤ 1, a variable) with ν·(r_i − r_j) ≥ D at the interval's two
nodes: the segment of their relative position then keeps D from the origin, and such a ν
exists whenever it does. These rows couple only the two agents of a pair, so with the final
angles φ fixed the monolithic NLP falls apart into independent problems, one per connected
component (*cluster*) of the graph of constrained pairs: each cluster's agents' DMOC NLPs,
their pairs' planes and rows, the members' boundary data as parameters
(:func:`solve_cluster`; an agent in no pair is a cluster of one, its own inner problem).
The hierarchical problem

    min over θ of V(θ) = Σ_clusters J*_C(φ(θ))

then has the monolithic optimum: θ is the common shift of the formation's family of
solutions of c(φ) = 0 (:meth:`~ocpar.formation.couplings.coupling.Coupling.family`: a circle's
rotation, equal arc length); where the coupling has no such family the angles stay the outer
solve's: the optimum where its solutions are isolated; where they are not (a sphere's
rotations, a user's coupling with free directions) the answer is separated but not searched
over them, and says so (``success`` False). dV/dθ = Σ_i (dJ*/dq_N,i)·z′(φ_i) dφ_i/dθ from the
clusters' multipliers of their parameters (envelope theorem); θ is found by the secant method
on dV/dθ from the outer solve's optimum (:func:`_minimise_shift`), one superstep of
independent cluster solves per evaluation.

The pairs are found by constraint generation, as in the monolithic mode: the start's are
those whose separated paths from the separation rounds come within (1 +
:data:`~ocpar.formation.keep_out.rounds.NEIGHBOUR_MARGIN`) D; a cluster solve adds its members'
pairs that come within D and solves again (at most :data:`CLUSTER_ROUNDS` times); after each
superstep any two agents of different clusters within D join one (and the superstep is
repeated at the same θ). A cluster's planes start along each interval's closest direction on
the latest paths, its paths from the latest ones (warm start).

An agent in no pair (a cluster of one) is its own inner problem: those are solved together by
the batched inner solves (:func:`~ocpar.ocp.solve_tasks`, one more superstep), not as one
IPOPT NLP each.

The price: a cluster's problem is solved as one NLP on one worker, so the work per superstep
is that of the largest cluster: a crowd whose separation binds everywhere (every agent a
neighbour's neighbour) is one cluster, i.e. the monolithic NLP. Above :data:`MAX_CLUSTER`
agents the exact separation does not run: the rounds' answer stands, separated, and the run
says that its optimality is not proven (its cost's increase over the unconstrained optimum,
a relaxation, bounds the gap where that optimum is the global one). The 1,000 point masses
at D = 0.05 are one cluster of 1,000 (every neighbour within 1.5 D).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.couplings.coupling import ShiftFamily
from ocpar.formation.keep_out.rounds import (
    NEIGHBOUR_MARGIN,
    Separation,
    _direction,
)
from ocpar.formation.keep_out.separation import SEPARATION_RTOL, close_pairs, segment_closest
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import Slots
from ocpar.ocp import DmocShape, dmoc_problem, solve_tasks
from ocpar.ocp.ipopt import ipopt_options

#: Solves of a cluster's constraint generation at most (as the monolithic mode's).
CLUSTER_ROUNDS = 10
#: Supersteps of the shift's secant search at most.
MAX_EVALUATIONS = 40
#: Converged when |dV/dθ| ≤ this · Σ_i |dJ_i/dθ|, or the step is below this · (1 + |θ|).
SHIFT_RTOL = 1e-10
#: The secant search's first step probes dV/dθ this far (rad) from the start.
PROBE = 1e-3
#: IPOPT's tolerance for a cluster's NLP.
CLUSTER_TOL = 1e-12
#: Agents in one cluster at most: a larger one would be solved as one NLP on one worker
#: (the monolithic problem in disguise); the exact separation then stops and the rounds'
#: answer stands, its optimality not proven (:attr:`ExactSeparation.largest` says how large).
MAX_CLUSTER = 32


@dataclass(frozen=True)
class ClusterTask:
    """One cluster's solve: its members' DMOC ``shapes`` (one per member), boundary data
    ``params`` (members, 4 nq), ``pairs`` (P, 2) of member indices that carry planes,
    ``distance`` D, the configuration entries that are a position ``positions`` (d), and
    the warm start: each member's inner nodes and controls ``guess``
    (members, (N−1) nq + N nu)."""

    shapes: tuple[DmocShape, ...]
    params: np.ndarray
    pairs: np.ndarray
    distance: float
    positions: tuple[int, ...]
    guess: np.ndarray


@dataclass
class ClusterOutcome:
    """A cluster's solve: member ``costs`` (members,), paths ``q`` (members, N+1, nq),
    controls ``u`` (members, N, nu), ``end_gradient`` dJ*/dq_N (members, nq), the ``pairs``
    (P, 2) that carry planes at the end (the task's and those added), IPOPT's ``success`` and
    ``status``, and its solves."""

    costs: np.ndarray
    q: np.ndarray
    u: np.ndarray
    end_gradient: np.ndarray
    pairs: np.ndarray
    success: bool
    status: str
    solves: int = 1


@lru_cache(maxsize=64)
def _cluster_nlp(shapes: tuple[DmocShape, ...], pairs: tuple[tuple[int, int], ...],
                 positions: tuple[int, ...]) -> tuple[ca.Function, dict, ca.Function, np.ndarray]:
    """The cluster's NLP solver (IPOPT; x = members' w, then each pair's normals interval by
    interval; p = members' boundary data, then D), its bounds, the members' costs as a
    function of (x, p), and the offsets of each member's w in x (members + 1,)."""
    dmocs = [dmoc_problem(shape) for shape in shapes]
    nq, intervals = dmocs[0].nq, dmocs[0].n
    dim, positions = len(positions), list(positions)
    offsets = np.concatenate([[0], np.cumsum([d.nw for d in dmocs])]).astype(int)
    w = ca.SX.sym("w", int(offsets[-1]))
    p = ca.SX.sym("p", 4 * nq * len(dmocs) + 1)
    distance = p[-1]
    planes = ca.SX.sym("planes", len(pairs) * intervals * dim)
    w_i = [w[offsets[m]:offsets[m + 1]] for m in range(len(dmocs))]
    p_i = [p[4 * nq * m: 4 * nq * (m + 1)] for m in range(len(dmocs))]
    nodes = [dmocs[m].nodes(w_i[m], p_i[m]) for m in range(len(dmocs))]
    rows = []
    for e, (a, b) in enumerate(pairs):
        for k in range(intervals):
            nu = planes[(e * intervals + k) * dim:(e * intervals + k + 1) * dim]
            for node in (k, k + 1):
                rows.append(ca.dot(nu, nodes[a][node][positions] - nodes[b][node][positions])
                            - distance)
            rows.append(1 - ca.sumsqr(nu))
    costs = ca.vertcat(*[dmocs[m].cost(w_i[m], p_i[m]) for m in range(len(dmocs))])
    g = ca.vertcat(*[dmocs[m].constraints(w_i[m], p_i[m]) for m in range(len(dmocs))], *rows)
    x = ca.vertcat(w, planes)
    exact = {"bound_relax_factor": 0.0}
    solver = ca.nlpsol("cluster", "ipopt", {"x": x, "p": p, "f": ca.sum1(costs), "g": g},
                       ipopt_options(CLUSTER_TOL, 3000, **exact))
    free = np.full(planes.numel(), np.inf)
    bounds = {"lbg": np.concatenate([d.lbg for d in dmocs] + [np.zeros(len(rows))]),
              "ubg": np.concatenate([d.ubg for d in dmocs] + [np.full(len(rows), np.inf)]),
              "lbx": np.concatenate([d.lbx for d in dmocs] + [-free]),
              "ubx": np.concatenate([d.ubx for d in dmocs] + [free])}
    return solver, bounds, ca.Function("costs", [x, p], [costs]), offsets


def solve_cluster(task: ClusterTask) -> ClusterOutcome:
    """Engine kernel: the cluster's NLP (module docstring) from its warm start, with
    constraint generation over its members' pairs."""
    dmocs = [dmoc_problem(shape) for shape in task.shapes]
    nq = dmocs[0].nq
    positions = list(task.positions)
    guess = [dmocs[m].full_guess(task.guess[m], task.params[m]) for m in range(len(dmocs))]
    paths = np.stack([dmocs[m].unpack(guess[m], task.params[m])[0] for m in range(len(dmocs))])
    pairs = [tuple(map(int, pair)) for pair in np.asarray(task.pairs).reshape(-1, 2)]
    p = np.concatenate([np.ravel(task.params), [task.distance]])
    solves = 0
    while True:
        solver, bounds, costs, offsets = _cluster_nlp(task.shapes, tuple(pairs),
                                                      task.positions)
        x0 = np.concatenate([*guess, _normals(paths[:, :, positions], pairs, task.distance)])
        out = solver(x0=x0, p=p, **bounds)
        solves += 1
        stats = solver.stats()
        x = np.asarray(out["x"]).ravel()
        lam_p = np.asarray(out["lam_p"]).ravel()
        guess = [x[offsets[m]:offsets[m + 1]] for m in range(len(dmocs))]
        unpacked = [dmocs[m].unpack(guess[m], task.params[m]) for m in range(len(dmocs))]
        paths = np.stack([q for q, _ in unpacked])
        if not np.all(np.isfinite(paths)):
            break
        close = close_pairs(paths[:, :, positions], task.distance * (1 - SEPARATION_RTOL))
        new = [tuple(map(int, pair)) for pair in close if tuple(map(int, pair)) not in pairs]
        if not new or solves >= CLUSTER_ROUNDS:
            break
        pairs = sorted(set(pairs) | set(new))
    gradient = -lam_p[:-1].reshape(len(dmocs), 4 * nq)[:, 2 * nq: 3 * nq]
    return ClusterOutcome(
        costs=np.asarray(costs(x, p)).ravel(), q=paths,
        u=np.stack([u for _, u in unpacked]), end_gradient=gradient,
        pairs=np.array(pairs, np.intp).reshape(-1, 2), success=bool(stats["success"]),
        status=str(stats["return_status"]), solves=solves)


def _normals(positions: np.ndarray, pairs: Sequence[tuple[int, int]], distance: float
             ) -> np.ndarray:
    """Start normals (flattened: pair, interval, axis): each interval's direction of the
    pair's relative position at its closest time on the paths ``positions`` (m, N+1, d)."""
    if not pairs:
        return np.zeros(0)
    a, b = np.array(pairs).T
    rel = positions[a] - positions[b]                     # (P, N+1, d)
    start, end = rel[:, :-1].reshape(-1, rel.shape[2]), rel[:, 1:].reshape(-1, rel.shape[2])
    _, s = segment_closest(start, end)
    return _direction((1 - s[:, None]) * start + s[:, None] * end, end - start,
                      distance).ravel()


@dataclass
class ExactSeparation:
    """Outcome of :func:`separate_exactly`: angles ``phi`` (n,) rad, paths ``q`` (n, N+1,
    nq), controls ``u`` (n, N, nu), ``costs`` (n,), the constrained ``pairs`` (P, 2) at the
    end, the largest cluster's size ``largest``, ``evaluations`` (supersteps),
    ``inner_solves`` (cluster NLP solves, and the inner solves of agents in no pair),
    ``failed_solves``, ``rotation`` θ (rad; 0 without
    a family), ``slope`` the last |dV/dθ| relative to Σ|dJ_i/dθ|, ``success`` and a
    ``message``; ``too_large`` where a cluster had more than :data:`MAX_CLUSTER` agents (then
    the rest is the rounds' answer, ``largest`` that cluster's size)."""

    phi: np.ndarray
    q: np.ndarray
    u: np.ndarray
    costs: np.ndarray
    pairs: np.ndarray
    largest: int = 0
    evaluations: int = 0
    inner_solves: int = 0
    failed_solves: int = 0
    rotation: float = 0.0
    slope: float = float("nan")
    success: bool = False
    message: str = ""
    too_large: bool = False


def clusters(agents: int, pairs: np.ndarray) -> list[np.ndarray]:
    """The connected components (sorted member lists, ordered by their first member) of the
    graph on ``agents`` vertices with edges ``pairs`` (P, 2)."""
    parent = list(range(agents))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in np.asarray(pairs).reshape(-1, 2).tolist():
        ra, rb = root(a), root(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    groups: dict[int, list[int]] = {}
    for a in range(agents):
        groups.setdefault(root(a), []).append(a)
    return [np.array(members) for members in groups.values()]


def separate_exactly(problem: FormationProblem, backend: Backend, phi: np.ndarray,
                     rounds: Separation, distance: float,
                     progress: Callable[[str], None] | None = None) -> ExactSeparation:
    """The exact separation (module docstring) from the separation ``rounds``' paths at the
    outer solve's angles ``phi`` (rad), for the minimum separation ``distance`` D (length
    unit). Problems with obstacles are not supported (ValueError)."""
    if problem.obstacles:
        raise ValueError("the exact separation does not take obstacles yet")
    n = problem.agents
    shapes = problem.shapes
    family: ShiftFamily | None = (problem.coupling.family(phi, problem.curve)
                                  if problem.parameters == 1
                                  and not isinstance(problem.curve, Slots) else None)
    fixed = np.reshape(np.asarray(phi, float), problem.parameter_shape)
    pairs = close_pairs(problem.positions(rounds.q), distance * (1 + NEIGHBOUR_MARGIN))
    state = ExactSeparation(phi=fixed, q=rounds.q.copy(), u=rounds.u.copy(),
                            costs=rounds.costs.copy(), pairs=pairs)

    def angles(theta: float) -> tuple[np.ndarray, np.ndarray]:
        """φ (the outer solve's at θ = 0, bit for bit) and dφ/dθ (n,) at the shift θ."""
        if family is None:
            return fixed, np.zeros(n)
        phi_now, slope, _ = family.angles(theta)
        return (fixed if theta == 0 else phi_now), slope

    evaluated: list[float] = []

    def evaluate(theta: float) -> tuple[float, float, float]:
        """V, dV/dθ and Σ|dJ_i/dθ| at θ (one superstep, repeated while clusters join)."""
        evaluated.append(theta)
        phi_now, slope = angles(theta)
        params = problem.boundary_params_rows(np.arange(n), phi_now)
        for _ in range(n):
            groups = clusters(n, state.pairs)
            alone = np.array([m[0] for m in groups if len(m) == 1], np.intp)
            groups = [m for m in groups if len(m) > 1]
            if groups and max(len(m) for m in groups) > MAX_CLUSTER:
                raise _TooLarge(max(len(m) for m in groups))
            index = {}
            for g, members in enumerate(groups):
                for local, agent in enumerate(members.tolist()):
                    index[agent] = (g, local)
            local_pairs = [[] for _ in groups]
            for a, b in state.pairs.tolist():
                g, la = index[a]
                local_pairs[g].append((la, index[b][1]))
            tasks = [ClusterTask(
                shapes=tuple(shapes[i] for i in members.tolist()), params=params[members],
                pairs=np.array(local_pairs[g], np.intp).reshape(-1, 2), distance=distance,
                positions=problem.position_indices,
                guess=np.hstack([state.q[members, 1:-1].reshape(len(members), -1),
                                 state.u[members].reshape(len(members), -1)]))
                for g, members in enumerate(groups)]
            outcomes = backend.superstep(solve_cluster, tasks,
                                         costs=[len(m) ** 3 for m in groups]) if tasks else []
            state.evaluations += 1
            state.largest = max([1, *(len(m) for m in groups)])
            gradient = np.zeros((n, problem.common_shape.model.nq))
            _solve_alone(problem, backend, alone, params[alone], state, gradient)
            found = [state.pairs]
            for members, outcome in zip(groups, outcomes, strict=True):
                state.inner_solves += outcome.solves
                if not outcome.success:
                    state.failed_solves += 1
                    raise _Failed(f"a cluster of {len(members)} agent(s) (first "
                                  f"{members[0]}) failed: {outcome.status}")
                state.q[members], state.u[members] = outcome.q, outcome.u
                state.costs[members] = outcome.costs
                gradient[members] = outcome.end_gradient
                found.append(members[outcome.pairs])
            near = close_pairs(problem.positions(state.q), distance * (1 - SEPARATION_RTOL))
            known = np.unique(np.concatenate(found), axis=0)
            new = [p for p in map(tuple, near.tolist()) if p not in set(map(tuple,
                                                                           known.tolist()))]
            state.pairs = np.unique(np.concatenate([known, np.array(new, np.intp).reshape(
                -1, 2)]), axis=0)
            if not new:
                break
        state.phi = phi_now
        value = float(np.sum(state.costs))
        terms = (np.zeros(n) if family is None else
                 np.sum(gradient * problem.final_position_derivatives(phi_now), axis=1) * slope)
        if progress is not None:
            progress(f"exact separation  superstep {state.evaluations:4d}  cost {value:.12e}  "
                     f"rotation {theta:+.6e} rad  pairs {len(state.pairs)}  largest cluster "
                     f"{state.largest}")
        return value, float(np.sum(terms)), max(float(np.sum(np.abs(terms))), 1e-300)

    try:
        if family is None:
            evaluate(0.0)
            free = (0 if isinstance(problem.curve, Slots) else
                    problem.coupling.free_directions(np.ravel(fixed), problem.curve).shape[1])
            state.success = not free
            state.message = ("the angles are isolated: the clusters only" if not free else
                             f"not the optimum: the angles keep the outer solve's, their "
                             f"{free} free direction(s) (no shift family) are not searched "
                             "under the separation")
            return state
        state.rotation, state.slope, state.success, state.message = _minimise_shift(evaluate)
        if evaluated[-1] != state.rotation:   # the paths of the answer, not of a rejected step
            evaluate(state.rotation)
    except _Failed as exc:
        state.message = str(exc)
    except _TooLarge as exc:   # the rounds' answer stands, as it was
        state = ExactSeparation(phi=fixed, q=rounds.q.copy(), u=rounds.u.copy(),
                                costs=rounds.costs.copy(), pairs=state.pairs,
                                largest=exc.size, evaluations=state.evaluations,
                                inner_solves=state.inner_solves, too_large=True,
                                message=f"not run: a cluster of {exc.size} agents (more than "
                                        f"{MAX_CLUSTER})")
    return state


def _minimise_shift(evaluate: Callable[[float], tuple[float, float, float]]
                    ) -> tuple[float, float, bool, str]:
    """The secant method on dV/dθ from θ = 0 (``evaluate``: V, dV/dθ, Σ|dJ_i/dθ| at θ), the
    first step a probe of :data:`PROBE` rad downhill; a step that raises V beyond rounding is
    halved, as is one where a cluster's solve fails (:class:`_Failed`; it bounds the search);
    once dV/dθ has changed sign, steps stay inside the bracket. Returns θ, the last
    |dV/dθ| relative to Σ|dJ_i/dθ|, whether converged, and the words. The last evaluation
    may be a rejected step's: the caller evaluates θ again if it is not θ's."""
    theta, (value, slope, scale) = 0.0, evaluate(0.0)
    previous = None
    low, high = -np.inf, np.inf
    for _ in range(MAX_EVALUATIONS):
        if abs(slope) <= SHIFT_RTOL * scale:
            return theta, abs(slope) / scale, True, "|dV/dtheta| below tolerance"
        if slope > 0:
            high = min(high, theta)
        else:
            low = max(low, theta)
        if previous is None or previous[1] == slope:
            step = -np.sign(slope) * PROBE
        else:
            curvature = (slope - previous[1]) / (theta - previous[0])
            step = -slope / curvature if curvature > 0 else -np.sign(slope) * 2 * abs(
                theta - previous[0])
        trial = theta + step
        if not low < trial < high:
            trial = (low + high) / 2 if np.isfinite(low) and np.isfinite(high) else \
                theta + np.sign(step) * abs(step) / 2
        for _halving in range(30):
            try:
                t_value, t_slope, t_scale = evaluate(trial)
            except _Failed:   # a cluster failed there: a rejected step, and a bound
                t_value, t_slope = np.inf, np.sign(trial - theta)
            if t_value <= value + 1e-12 * abs(value):
                break
            if t_slope > 0:
                high = min(high, trial)
            else:
                low = max(low, trial)
            trial = theta + (trial - theta) / 2
        else:
            return (theta, abs(slope) / scale, False,
                    "the rotation search stopped: no shift lowers V")
        previous = (theta, slope)
        if abs(trial - theta) <= SHIFT_RTOL * (1 + abs(theta)):
            return trial, abs(t_slope) / t_scale, True, "step below tolerance"
        theta, value, slope, scale = trial, t_value, t_slope, t_scale
    return theta, abs(slope) / scale, False, "the rotation search reached its evaluation limit"


def _solve_alone(problem: FormationProblem, backend: Backend, agents: np.ndarray,
                 params: np.ndarray, state: ExactSeparation, gradient: np.ndarray) -> None:
    """The agents in no pair (``agents`` (m,), boundary data ``params`` (m, 4 nq)): each a
    cluster of one, its own inner problem, solved in one superstep of the batched inner
    solves (:func:`~ocpar.ocp.solve_tasks`) from its latest path; ``state``'s paths,
    controls and costs and the end ``gradient`` dJ*/dq_N (n, nq) updated in place."""
    if not len(agents):
        return
    nq = gradient.shape[1]
    warm = np.hstack([state.q[agents, 1:-1].reshape(len(agents), -1),
                      state.u[agents].reshape(len(agents), -1)])
    sols = backend.superstep_columns(solve_tasks,
                                     problem.task_columns(agents, params, warm_start=warm))
    ok = np.asarray(sols.column("success"), bool)
    state.inner_solves += len(agents)
    if not ok.all():
        state.failed_solves += int(np.sum(~ok))
        raise _Failed(f"the inner solve of agent {agents[~ok][0]} (in no pair) failed: "
                      f"{sols.column('status')[int(np.flatnonzero(~ok)[0])]}")
    state.q[agents] = np.asarray(sols.column("q"))
    state.u[agents] = np.asarray(sols.column("u"))
    state.costs[agents] = np.asarray(sols.column("cost"), float)
    gradient[agents] = np.asarray(sols.column("cost_gradient"), float)[:, 2 * nq:3 * nq]


class _Failed(RuntimeError):
    """A cluster's solve failed."""


class _TooLarge(RuntimeError):
    """A cluster has more than :data:`MAX_CLUSTER` agents."""

    def __init__(self, size: int) -> None:
        super().__init__(size)
        self.size = size


__all__ = ["ClusterOutcome", "ClusterTask", "ExactSeparation", "clusters",
           "separate_exactly", "solve_cluster"]
