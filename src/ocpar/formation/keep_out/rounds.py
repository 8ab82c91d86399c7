"""Collision-free reconfiguration: separation rounds of independent keep-out DMOC solves.

After the hierarchical solve without the separation (outer angles φ, inner DMOC paths with
any obstacles), each round reads the latest continuous paths (piecewise linear between
nodes, :mod:`ocpar.formation.keep_out.separation`) and does two things:

1. **Spread** (:func:`spread`, on the coordinator, numpy only): the node positions are pushed
   apart until every pair is ≥ D apart on every interval, the first and last nodes fixed —
   target paths that are separated but need not obey the dynamics. Many cheap projection
   iterations move a crowd as a whole: a band of agents squeezed far below D must widen from
   its middle outwards, which per-agent half-spaces about the squeezed paths cannot ask for
   (an agent between two close partners gets contradictory half-spaces, and the elastic
   penalty leaves it where it is).
2. **Keep-out solves** (one superstep of independent inner problems): every agent the spread
   moved or with a partner within (1 + :data:`RESOLVE_MARGIN`) D on the targets
   (:func:`resolving`) gets keep-out half-spaces (:mod:`ocpar.ocp.dmoc`,
   ``keep_out_slots``) and re-solves its own DMOC problem (the same boundary data, its
   half-spaces as parameters, warm-started from its latest path). The others keep their
   latest path (not their unconstrained optimum: going back re-creates the conflicts),
   which is their target: it meets every half-space a re-solving partner's plane asks of
   it. Most of a large fleet never comes near another (the 60 masses at D = 0.2: 12 agents
   re-solve, 48 keep their unconstrained paths bit for bit).

The half-spaces, moving linearly in time over each interval:

* for each pair (i, j) whose target paths come within (1 + :data:`NEIGHBOUR_MARGIN`) D, and
  each interval k on which they do (:func:`conflicts`): the normal n is the direction of
  r_i − r_j on the targets at the interval's closest time
  (:func:`~ocpar.formation.keep_out.separation.interval_closest`; where they meet, perpendicular to
  their relative velocity), and the plane follows the targets' centre
  c(t) = (r_i + r_j)/2, linear in t on the interval: agent i keeps n·r ≥ n·c(t) + D/2 and
  agent j −n·r ≥ −n·c(t) + D/2 (rows at the interval's two nodes, with c at those nodes).
  n·r(t) − n·c(t) is linear in t on the interval, so holding at both nodes it holds
  throughout, and two agents that satisfy theirs are ≥ D apart at every time of the
  interval (n·(r_i − r_j) ≥ D). On the first and last interval the fixed boundary node must
  satisfy its side too: there n is blended towards that node's direction
  (:data:`BOUNDARY_BLENDS`) until it does (start and final positions are ≥ D apart);
* the targets satisfy all their half-spaces (n·(r_i − r_j) on an interval is smallest at
  the closest time, where it is |r_i − r_j| ≥ D) and the trust region below, so the agents'
  problems are feasible together and no two ask contradictory things: the targets say who
  gives way where;
* a trust region about the targets (:func:`trust_region`: 2 d more moving half-spaces, a
  box of half-width :data:`NEIGHBOUR_MARGIN` D / (2 √d) about each node's target) keeps
  every node within NEIGHBOUR_MARGIN D / 2 of it, so that a pair farther than
  (1 + NEIGHBOUR_MARGIN) D apart on the targets, which gets no half-spaces, cannot meet
  either: paths that meet D stay separated in every later round (without it, agents moving
  back towards their optimum met partners they had no half-space for, and the 1000 masses
  lost the separation of their first round for five rounds);
* the planes are linearisations (sequential convex programming, split per agent like
  buffered Voronoi cells, about the spread targets instead of the latest paths); the common
  motion of a pair does not enter (a static plane per interval would ask agents travelling
  along n to stay behind one another);
* an agent keeps at most K = :data:`KEEP_OUT_SLOTS` half-spaces per interval, those of its
  closest partners (ties by partner index): a dropped one is caught by the next round's
  check. The keep-outs are elastic (exact penalty :data:`PENALTY`), so that an agent whose
  half-spaces cannot all be met (its dynamics cannot follow the targets) moves as far as it
  can instead of failing.

With obstacles (:mod:`ocpar.formation.keep_out.obstacles`) every agent's inner problem already keeps
them clear exactly (its shape carries them, :mod:`ocpar.ocp.obstacles`), in the outer
solve and in the rounds alike: the rounds add only the pairs' half-spaces (and the trust
region), and an agent re-solving keeps the side of each obstacle its latest path passes
(its warm start's planes). The spreading also pushes every segment of the targets inside
an obstacle out of it (along the tangent plane's normal at its point nearest the centre,
:func:`_obstacle_pushes`), so that the targets the half-spaces are built about are
separated and clear; the penalty is per the smaller of D and the smallest obstacle scale.

Each round is one superstep of independent inner problems. Rounds repeat until the exact
closest approach (:func:`~ocpar.formation.keep_out.separation.closest_approach`) is at least D (to a
relative :data:`SEPARATION_RTOL`), every obstacle clearance is ≥ 0
(:func:`~ocpar.formation.keep_out.obstacles.cleared`) and no node moved by more than
:data:`CHANGE_RTOL` · min(D, the smallest obstacle scale) in the last round, or the round
limit; where the exact separation follows (``until_met``), at the first round that meets
D: the later rounds only creep back towards the optimum by the trust region's width a
round (the 200 masses at D = 0.05: 19 of 21 rounds), which the exact separation does in
one superstep.

The keep-out shapes are solved by IPOPT, one task at a time: the batched ``sqpmethod``
(``qrqp``) was tried on the 200 masses at D = 0.05 and took 407 s against IPOPT's 37 s
(loaded machine; ``qrqp`` fails its KKT check on most tasks, whose Hessian is singular in
the slacks and the nodes, and IPOPT then re-solves them); ``sqpmethod`` with qpOASES was
about 2× faster than IPOPT per task, mapped.

The returned paths' separation and clearance are computed, not assumed: a run that misses D
or an obstacle says by how much.

ODE agents (:class:`~ocpar.ocp.MsEndpointShape`) take the same half-spaces, imposed on the
polyline through their RK4 sub-step states (:mod:`ocpar.ocp.ms_endpoint`), and the same
targets about their nodes; their separation is measured where the verification measures it,
on the dense re-integration (:func:`~ocpar.formation.verify.checked_positions`), which may
bulge between two sub-step states by about (h/steps)² |r̈| / 8: where it falls short of D once
the rounds have settled (no node moved by more than :data:`CHANGE_RTOL` · D), the
half-spaces' D is raised by the shortfall (1 + :data:`SPREAD_MARGIN`) and the rounds go on.

The final angles φ stay those of the outer solve (with its obstacles; the keep-outs move the
paths, not the formation); the cost increase over the outer solve's paths is reported. With
``ordering optimal`` the ordering comes first (fewer close passes to undo), then the outer
solve, then the rounds. The rounds' answer is separated, not optimal: the exact separation
(:mod:`ocpar.formation.keep_out.exact`) starts from it and reaches the monolithic optimum.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import Columns
from ocpar.formation.keep_out.obstacles import Clearance, Obstacle, cleared, closest_obstacle
from ocpar.formation.keep_out.separation import (
    SEPARATION_RTOL,
    ClosestApproach,
    close_pairs,
    closest_approach,
    interval_closest,
    segment_closest,
)
from ocpar.formation.problem import FormationProblem
from ocpar.formation.verify import checked_positions
from ocpar.ocp import solve_tasks
from ocpar.ocp.batch import AUTO_SOLVER
from ocpar.ocp.dmoc import UNUSED_OFFSET, DmocShape

#: Partners' keep-out half-spaces per agent and interval (the DMOC shape has 2 d slots more:
#: the trust region's).
KEEP_OUT_SLOTS = 8
#: Pairs whose paths come within (1 + this) D get half-spaces: the constrained pairs at
#: distance D stay in, and neighbours about to come close join before they do.
NEIGHBOUR_MARGIN = 0.5
#: Agents with a partner within (1 + this) D on a round's targets re-solve in it, with those
#: the spread moved (:func:`resolving`); the others keep their paths.
RESOLVE_MARGIN = 0.1
#: The rounds have stopped changing the paths once no node moves by more than this · D.
CHANGE_RTOL = 1e-2
#: The keep-outs' penalty ρ per unit of slack (:mod:`ocpar.ocp.dmoc`), in units of the
#: largest unconstrained agent cost per D: large enough to be exact, small enough for the QP.
PENALTY = 10.0
#: The coordinator's spreading pushes pairs closer than D to D (1 + this) ...
SPREAD_MARGIN = 1e-3
#: ... in at most this many iterations.
SPREAD_ITERATIONS = 2000
SPREAD_LIST_MARGIN = 3.0
#: Below this distance (relative to D) a pair's direction is taken from the first axis.
DEGENERATE_RTOL = 1e-12


@dataclass
class Separation:
    """Outcome of :func:`separate`: ``q`` (n, N+1, nq) paths, ``u`` (n, N, nu) controls,
    ``costs`` (n,); ``closest`` the exact closest approach of ``q`` (an ODE agent's dense
    re-integration, module docstring); ``met`` whether it is
    ≥ D (1 − :data:`SEPARATION_RTOL`); ``rounds`` rounds (one superstep of keep-out solves
    each);
    ``change`` the largest node move of the last round (length unit); ``inner_solves``,
    ``failed_solves`` (kept their previous path), ``retries``; ``dropped`` half-spaces left
    out for want of slots over all rounds; with obstacles ``clearance`` the smallest obstacle
    clearance of ``q`` and ``cleared`` whether it is ≥ 0 (None and True without)."""

    q: np.ndarray
    u: np.ndarray
    costs: np.ndarray
    closest: ClosestApproach
    met: bool
    rounds: int
    change: float
    inner_solves: int = 0
    failed_solves: int = 0
    retries: int = 0
    dropped: int = 0
    clearance: Clearance | None = None
    cleared: bool = True


def keep_out_problem(problem: FormationProblem) -> FormationProblem:
    """The problem with every agent's DMOC shape given :data:`KEEP_OUT_SLOTS` + 2 d slots on
    its d positions (partners' half-spaces, then the trust region's, :func:`trust_region`;
    its obstacles, if any, stay in its shape); an ODE agent's
    (:class:`~ocpar.ocp.MsEndpointShape`, the rows on the polyline through its sub-step
    states) under IPOPT, a DMOC agent's under the ``auto`` solver: batched by the
    convex QP's interior point where the NLP is one (point masses), else IPOPT (measured on
    the 60 point masses' first round: 18 ms per solve, all solved; ``sqpmethod``/``qrqp``
    110 ms per solve, 14 of 32 failing its KKT check)."""
    slots = KEEP_OUT_SLOTS + 2 * len(problem.position_indices)
    return problem.with_shapes(lambda shape: dataclasses.replace(
        shape, keep_out_slots=slots, keep_out_positions=problem.position_indices,
        solver=AUTO_SOLVER if isinstance(shape, DmocShape) else "ipopt"))


#: Blends of a boundary interval's normal towards the fixed node's direction, tried in order.
BOUNDARY_BLENDS = (0.0, 0.25, 0.5, 0.75, 1.0)


def conflicts(positions: np.ndarray, distance: float, margin: float = NEIGHBOUR_MARGIN
              ) -> np.ndarray:
    """Entries (m, 3) (i, j, k), i < j, sorted: pairs whose paths (positions (n, N+1, d))
    come within (1 + ``margin``) D on interval k."""
    pairs = close_pairs(positions, distance * (1 + margin))
    gap, _ = interval_closest(positions, pairs)
    row, k = np.nonzero(gap <= distance * (1 + margin))
    return np.column_stack([pairs[row], k])


def half_spaces(positions: np.ndarray, entries: np.ndarray, distance: float, slots: int
                ) -> tuple[np.ndarray, int]:
    """Keep-out data (n, N, slots, d + 2) per agent, interval and slot: normal (d) and the
    offsets at the interval's two nodes (unused slots: 0 and
    :data:`~ocpar.ocp.dmoc.UNUSED_OFFSET`), built from the node positions (n, N+1, d) for
    each entry (agent a, partner b, interval k) of ``entries`` (m, 3): agent a keeps
    n·r ≥ n·r_b(t) + D on interval k, as the module docstring says; and the number of
    half-spaces dropped for want of slots (the farthest partners' on an interval)."""
    n, nodes, dim = positions.shape
    intervals = nodes - 1
    data = np.zeros((n, intervals, slots, dim + 2))
    data[..., dim:] = UNUSED_OFFSET
    if not len(entries):
        return data, 0
    a, b, k = entries.T
    start, end = positions[a, k] - positions[b, k], positions[a, k + 1] - positions[b, k + 1]
    gap, s = segment_closest(start, end)
    normal = _direction((1 - s[:, None]) * start + s[:, None] * end, end - start, distance)
    # an interval with a fixed node: blend towards that node's direction until it holds there
    for fixed, rel in ((k == 0, start), (k == intervals - 1, end)):
        rows = np.flatnonzero(fixed)
        normal[rows] = _boundary_normal(normal[rows], rel[rows], distance)
    # the plane follows the partner's path r_b(t), linear on the interval: n·r ≥ n·r_b(t) + D
    offsets = np.column_stack([
        np.einsum("md,md->m", normal, (positions[a, node] + positions[b, node]) / 2)
        for node in (k, k + 1)]) + distance / 2
    order = np.lexsort((b, gap, k, a))
    a, k = a[order], k[order]
    group = a * intervals + k
    first = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    rank = np.arange(len(group)) - np.repeat(first, np.diff(np.r_[first, len(group)]))
    keep = rank < slots
    chosen = order[keep]
    data[a[keep], k[keep], rank[keep], :dim] = normal[chosen]
    data[a[keep], k[keep], rank[keep], dim:] = offsets[chosen]
    return data, int(np.sum(~keep))


def trust_region(target: np.ndarray, distance: float) -> np.ndarray:
    """Keep-out data (n, N, 2d, d + 2) holding each agent within the box
    |r − r*(t)|_∞ ≤ h about its target path r* (n, N+1, d), as 2 d moving half-spaces per
    interval, ±e_c·r ≥ ±e_c·r*(t) − h, with h = :data:`NEIGHBOUR_MARGIN` D / (2 √d): a node
    then moves at most NEIGHBOUR_MARGIN D / 2 from its target, so a pair more than
    (1 + NEIGHBOUR_MARGIN) D apart on the targets (no half-spaces between them) stays ≥ D
    apart at every time."""
    n, nodes, dim = target.shape
    normals = np.concatenate([np.eye(dim), -np.eye(dim)])                 # (2d, d)
    offsets = np.einsum("cd,nkd->nkc", normals, target) \
        - NEIGHBOUR_MARGIN * distance / (2 * np.sqrt(dim))                 # (n, N+1, 2d)
    data = np.empty((n, nodes - 1, 2 * dim, dim + 2))
    data[..., :dim] = normals
    data[..., dim] = offsets[:, :-1]
    data[..., dim + 1] = offsets[:, 1:]
    return data


def spread(positions: np.ndarray, distance: float, obstacles: Sequence[Obstacle] = ()
           ) -> tuple[np.ndarray, int]:
    """Target paths (n, N+1, d): the node positions (n, N+1, d) pushed apart until every pair
    is ≥ D apart on every interval of the piecewise-linear paths, and out of ``obstacles``
    (:func:`_obstacle_pushes`), the first and last nodes fixed; and the iterations taken (at
    most :data:`SPREAD_ITERATIONS`).

    Jacobi projection (position-based dynamics): each iteration, every pair-interval closer
    than D at its closest point s ∈ [0, 1] asks both agents to move apart along their
    difference there by δ/2, δ what it lacks of D (1 + :data:`SPREAD_MARGIN`), spread over
    the interval's two nodes in proportion (1 − s, s); each node moves by the mean of what it
    is asked (the pairs within reach are found anew once a node has moved
    :data:`SPREAD_LIST_MARGIN` D / 2 since they were last; between listings only the pairs
    with a node moved in the last iteration are measured again). Many cheap iterations carry a push
    through a crowd, which one round of per-agent solves cannot (a squeezed band must widen
    as a whole)."""
    target = positions.copy()
    n, nodes, _ = target.shape
    goal = distance * (1 + SPREAD_MARGIN)
    # pairs farther than (1 + SPREAD_LIST_MARGIN) D apart when listed cannot come closer than
    # D before some node has moved SPREAD_LIST_MARGIN D / 2: list them anew only then
    points = target.reshape(-1, target.shape[2])       # a view: node (a, k) is row a (N+1) + k
    listed = target.copy()
    first, second = _listed(target, distance)
    start, end, gap, s = _entry_gaps(points, first, second)
    for iteration in range(SPREAD_ITERATIONS):
        short = np.flatnonzero(gap < distance)
        pushed = _obstacle_pushes(target, obstacles)
        if not len(short) and not len(pushed[0]):
            return target, iteration
        s_short = s[short]
        rel = (1 - s_short[:, None]) * start[short] + s_short[:, None] * end[short]
        direction = _direction(rel, end[short] - start[short], distance)
        # moving node k by a (1 − s) and node k+1 by a s moves the point at s by
        # a ((1 − s)² + s²): a makes it δ/2
        amount = (goal - gap[short]) / 2 / ((1 - s_short) ** 2 + s_short ** 2)
        # every (agent, node) asked to move, in the order np.add.at would add them
        agent, node, step = pushed
        weights = [weight[:, None] * direction
                   for weight in (amount * (1 - s_short), amount * s_short)]
        flat = np.concatenate([first[short], second[short], first[short] + 1,
                               second[short] + 1, agent * nodes + node])
        steps = np.concatenate([weights[0], -weights[0], weights[1], -weights[1], step])
        count = np.bincount(flat, minlength=n * nodes).reshape(n, nodes)
        push = np.column_stack([np.bincount(flat, steps[:, c], minlength=n * nodes)
                                for c in range(steps.shape[1])]).reshape(target.shape)
        push[:, [0, -1]] = 0
        moved = np.any(push != 0, axis=-1)
        target += push / np.maximum(count, 1)[..., None]
        # only the moved nodes' distance from where the pairs were listed can have grown
        agents = np.flatnonzero(np.any(moved, axis=1))
        if np.linalg.norm(target[agents] - listed[agents], axis=-1).max(initial=0.0) \
                >= SPREAD_LIST_MARGIN * distance / 2:
            listed = target.copy()
            first, second = _listed(target, distance)
            start, end, gap, s = _entry_gaps(points, first, second)
            continue
        moved = moved.ravel()
        stale = np.flatnonzero(moved[first] | moved[first + 1] | moved[second]
                               | moved[second + 1])
        start[stale], end[stale], gap[stale], s[stale] = _entry_gaps(points, first[stale],
                                                                     second[stale])
    return target, SPREAD_ITERATIONS


def _listed(target: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """The pair-intervals (i, j, k) within (1 + :data:`SPREAD_LIST_MARGIN`) D on the paths
    ``target`` (n, N+1, d) (:func:`conflicts`, in its order) as the rows of node k of i and
    of j among the n (N+1) nodes, (m,) each."""
    i, j, k = conflicts(target, distance, SPREAD_LIST_MARGIN).T
    nodes = target.shape[1]
    return i * nodes + k, j * nodes + k


def _entry_gaps(points: np.ndarray, first: np.ndarray, second: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For the pair-intervals whose start nodes are rows ``first`` and ``second`` (m,) of
    the nodes ``points`` (n (N+1), d): the relative positions r_i − r_j at the interval's
    start and end (m, d) each, the closest distance on it (m,) and the fraction s (m,)
    where it occurs."""
    start = points[first] - points[second]
    end = points[first + 1] - points[second + 1]
    gap, s = segment_closest(start, end)
    return start, end, gap, s


def _obstacle_pushes(target: np.ndarray, obstacles: Sequence[Obstacle]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moves that take the paths ``target`` (n, N+1, d) out of ``obstacles``: each
    segment whose clearance is < 0 has its point nearest the centre (at s, in the obstacle's
    scaled space) moved along the normal of the tangent plane there by its depth below it +
    :data:`SPREAD_MARGIN` · the obstacle's scale, spread over the segment's two nodes in
    proportion (1 − s, s) as :func:`spread` does; agents (m,), nodes (m,) and moves (m, d),
    length unit."""
    agents, nodes, steps = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros((0, target.shape[2]))]
    for obstacle in obstacles:
        gap, s = obstacle.clearance(target[:, :-1], target[:, 1:])
        a, k = np.nonzero(gap < 0)
        s = s[a, k]
        point = (1 - s[:, None]) * target[a, k] + s[:, None] * target[a, k + 1]
        normal, offset = obstacle.plane(point)
        size = np.linalg.norm(normal, axis=1)
        depth = (offset - np.einsum("md,md->m", normal, point)) / size \
            + SPREAD_MARGIN * obstacle.scale
        amount = depth / ((1 - s) ** 2 + s ** 2)
        for node, weight in ((k, amount * (1 - s)), (k + 1, amount * s)):
            agents.append(a)
            nodes.append(node)
            steps.append((weight / size)[:, None] * normal)
    return np.concatenate(agents), np.concatenate(nodes), np.concatenate(steps)


def _direction(relative: np.ndarray, velocity: np.ndarray, distance: float) -> np.ndarray:
    """Unit rows along ``relative`` (m, d); where it is shorter than
    :data:`DEGENERATE_RTOL` · ``distance`` (the agents meet), a unit vector perpendicular to
    the relative ``velocity`` (m, d) (the first axis if that is zero too)."""
    length = np.linalg.norm(relative, axis=1)
    degenerate = length <= DEGENERATE_RTOL * distance
    if np.any(degenerate):
        v = velocity[degenerate]
        axis = np.eye(v.shape[1])[np.argmin(np.abs(v), axis=1)]
        speed_sq = np.einsum("md,md->m", v, v)
        along = np.einsum("md,md->m", axis, v) / np.where(speed_sq > 0, speed_sq, 1.0)
        relative = relative.copy()
        relative[degenerate] = axis - along[:, None] * v
        length = np.linalg.norm(relative, axis=1)
    return relative / length[:, None]


def _boundary_normal(normal: np.ndarray, rel: np.ndarray, distance: float) -> np.ndarray:
    """Normals (m, d) for intervals with a fixed node where the pair's relative position is
    ``rel`` (m, d), |rel| ≥ D: ``normal`` blended towards rel/|rel|
    (:data:`BOUNDARY_BLENDS`, first that fits) until n·rel ≥ D, so that both agents'
    fixed nodes satisfy their half-spaces."""
    towards = rel / np.linalg.norm(rel, axis=1)[:, None]
    chosen = towards.copy()
    for w in reversed(BOUNDARY_BLENDS):
        blend = (1 - w) * normal + w * towards
        blend /= np.maximum(np.linalg.norm(blend, axis=1), 1e-300)[:, None]
        fits = np.einsum("md,md->m", blend, rel) >= distance
        chosen[fits] = blend[fits]
    return chosen


def resolving(positions: np.ndarray, target: np.ndarray, entries: np.ndarray,
              distance: float) -> np.ndarray:
    """The agents (sorted) that re-solve in a round, from the node positions before it
    (n, N+1, d), the spread ``target`` (n, N+1, d) and the half-spaces' ``entries`` (m, 3)
    (agent, partner, interval): those the spread moved and those with a partner within
    (1 + :data:`RESOLVE_MARGIN`) D on the targets. The others keep their paths, which are
    their targets: they satisfy every half-space a re-solving partner is given about them,
    and a re-solving agent stays within the trust region of its target, so no pair comes
    closer than D that the half-spaces do not cover (module docstring)."""
    moved = np.flatnonzero(np.any(target != positions, axis=(1, 2)))
    a, b, k = entries.T
    start, end = target[a, k] - target[b, k], target[a, k + 1] - target[b, k + 1]
    gap, _ = segment_closest(start, end)
    near = a[gap <= distance * (1 + RESOLVE_MARGIN)]
    return np.union1d(moved, near)


def resolve_with_keep_outs(slotted: FormationProblem, backend: Backend, agents: np.ndarray,
                           boundary: np.ndarray, data: np.ndarray, penalty: float,
                           outcome: Separation) -> None:
    """One round of keep-out solves, one superstep: ``agents`` re-solve on their keep-out
    shapes (``slotted``) with boundary data ``boundary`` (n, 4 nq), keep-out data ``data``
    (n, N, slots, d + 2) and the penalty ρ, warm-started from the ``outcome``'s latest paths
    and controls, which are updated in place with its costs (a failed solve keeps its
    agent's latest path), and its round and solve counts."""
    q, u, costs = outcome.q, outcome.u, outcome.costs
    warm = slotted.common_shape.previous_guesses(q[agents], u[agents])
    params = np.hstack([boundary[agents], data[agents].reshape(len(agents), -1),
                        np.full((len(agents), 1), penalty)])
    sols = backend.superstep_columns(solve_tasks,
                                     slotted.task_columns(agents, params, warm_start=warm))
    ok = np.asarray(sols.column("success"), dtype=bool)
    solved = agents[ok]
    q[solved] = np.asarray(sols.column("q"))[ok]
    u[solved] = np.asarray(sols.column("u"))[ok]
    costs[solved] = np.asarray(sols.column("cost"), float)[ok]
    outcome.inner_solves += len(agents)
    outcome.failed_solves += int(np.sum(~ok))
    outcome.retries += int(np.sum(np.asarray(sols.column("attempts")) - 1))
    outcome.rounds += 1


def separate(problem: FormationProblem, backend: Backend, phi: np.ndarray, base: Columns,
             distance: float, max_rounds: int,
             progress: Callable[[str], None] | None = None, until_met: bool = False
             ) -> Separation:
    """Separation rounds (module docstring) from the inner solutions ``base`` without D
    (a :class:`~ocpar.bsp.columns.Columns` of :class:`~ocpar.ocp.DmocSolution`, one per
    agent, at angles ``phi`` (n,) rad) to a minimum separation ``distance`` D (length unit),
    at most ``max_rounds`` rounds; with ``problem``'s obstacles, clear of them too.
    ``until_met``: stop at the first round whose paths are separated (and clear), not once
    they stop moving (the exact separation that follows needs a separated start only)."""
    slotted = keep_out_problem(problem)
    obstacles = problem.obstacles
    scale = min([distance, *(o.scale for o in obstacles)])
    n = problem.agents
    free_cost = np.asarray(base.column("cost"), float)
    q, u = np.array(base.column("q"), float), np.array(base.column("u"), float)
    costs = free_cost.copy()
    boundary = problem.boundary_params_rows(np.arange(n), phi)
    penalty = PENALTY * max(float(np.max(free_cost)), 1e-300) / scale
    closest, met, clearance, clear = _measure(problem, q, u, distance)
    outcome = Separation(q, u, costs, closest, met, 0, 0.0, clearance=clearance, cleared=clear)
    planes = distance   # the half-spaces' D: raised where ODE paths dip between sub-steps
    while not (outcome.met and outcome.cleared
               and (outcome.rounds == 0 or until_met or outcome.change <= CHANGE_RTOL * scale)
               ) and outcome.rounds < max_rounds:
        before = problem.positions(q)
        target, iterations = spread(before, planes, obstacles)
        entries = conflicts(target, planes)
        entries = np.concatenate([entries, entries[:, [1, 0, 2]]])   # both agents of a pair
        partners, dropped = half_spaces(target, entries, planes, KEEP_OUT_SLOTS)
        data = [partners, trust_region(target, planes)]
        agents = resolving(before, target, entries, planes)
        if not len(agents):   # met, and no pair within reach: no agent would move
            outcome.change = 0.0
            break
        resolve_with_keep_outs(slotted, backend, agents, boundary, np.concatenate(data, axis=2),
                               penalty, outcome)
        outcome.change = float(np.abs(problem.positions(q) - before).max())
        outcome.dropped += dropped
        outcome.closest, outcome.met, outcome.clearance, outcome.cleared = _measure(
            problem, q, u, distance)
        if problem.ode_agents and not outcome.met and outcome.change <= CHANGE_RTOL * scale:
            planes += (distance - outcome.closest.distance) * (1 + SPREAD_MARGIN)
        if progress is not None:
            c = outcome.clearance
            progress(f"separation round {outcome.rounds:3d}  spread {iterations:5d} it  "
                     f"agents {len(agents):6d}  closest {outcome.closest.distance:.6e} "
                     f"(agents {outcome.closest.agents[0]}, {outcome.closest.agents[1]})  "
                     + (f"clearance {c.distance:.6e} (agent {c.agent}, obstacle "
                        f"{c.obstacle})  " if obstacles else "")
                     + f"moved {outcome.change:.1e}  cost {float(np.sum(costs)):.12e}  "
                     f"dropped {dropped}")
    return outcome


def _measure(problem: FormationProblem, q: np.ndarray, u: np.ndarray, distance: float
             ) -> tuple[ClosestApproach, bool, Clearance | None, bool]:
    """The closest approach of paths ``q`` (n, N+1, nq) under controls ``u`` (n, N, nu) on
    the positions the verification checks (:func:`~ocpar.formation.verify.checked_positions`:
    an ODE agent's dense re-integration), whether it is ≥ ``distance`` D
    (1 − :data:`SEPARATION_RTOL`); their obstacle clearance and whether it is clear (None
    and True without obstacles)."""
    positions = checked_positions(problem, q, u, separation=True)
    duration = problem.common_shape.duration
    closest = closest_approach(positions, duration)
    met = closest.distance >= distance * (1 - SEPARATION_RTOL)
    if not problem.obstacles:
        return closest, met, None, True
    clearance = closest_obstacle(positions, problem.obstacles, duration)
    return closest, met, clearance, cleared(clearance, problem.obstacles)
