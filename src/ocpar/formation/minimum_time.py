"""Minimum final time of a formation: the least common T at which every agent reaches the
formation under its limits, the formation's freedom (a rotation, the assignment of agents to
its points) chosen for it: a bottleneck, not a sum.

The result states a bracket [T_lo, T_hi] with T_hi (1 − tol) ≤ T_lo: at T* = T_hi the
formation is solved and verified as any run is (:mod:`ocpar.formation.verify`), its
assignment onto the formation's points the energy-optimal one among the reachable pairs
(the energy tie-break); phase 1 (:mod:`ocpar.formation.feasibility`'s elastic inner
problems) of that formation at T_hi (1 − tol) has a positive total slack. Below T_lo:

* **exact reach sets** (point masses at rest at both ends under box or norm limits, onto a
  circle's equidistant formation; :mod:`ocpar.ocp.reach`): the sets grow as T², so agent i
  reaches displacement Δ in T exactly when T² ≥ ν_i(Δ), ν_i its set's need at T = 1, and
  T*² = min_θ min_σ max_i ν_i(z_σ(i)(θ) − s_i): a bottleneck assignment at each rotation θ
  (:func:`bottleneck`) and over θ a branch and bound with the Lipschitz constant
  R · max_i 1/(smallest reach of agent i at T = 1), R the radius (:func:`search_rotation`).
  Its lower bound proves that no formation is reachable below T_lo.
* **otherwise** (any model, limit, path constraint, obstacle, curve or coupling): bisection
  of ``time_bounds`` in log T, each T tested by phase 1 over the formation's freedom
  (:func:`~ocpar.formation.feasibility.phase_one`), a T where no agent can reach the curve at
  all (the problem refuses it) or phase 1 ends above its tolerance counted infeasible. Phase
  1 is a local search: below T_lo it found no formation, which proves none only where its
  search is exhaustive (``proven`` False in the result).
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.couplings.coupling import PotentialCoupling
from ocpar.formation.feasibility import (
    SLACK_TOL,
    NoFeasibleFormation,
    elastic_shape,
    phase_one,
)
from ocpar.formation.final_time import (
    TimeOptions,
    at_duration,
    task_columns,
    time_bounds,
)
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import Fleet, FormationResult
from ocpar.formation.targets.slots import Slots
from ocpar.ocp import solve_tasks
from ocpar.ocp.reach import Reach, rest_to_rest_reach

#: Shifts of the rotation's first grid per agent (the branch and bound over the rotation).
ROTATION_GRID = 32
#: Evaluations of the bottleneck over the rotation at most.
ROTATION_EVALUATIONS = 200_000


def exact_reach(problem: FormationProblem) -> list[Reach] | None:
    """Each agent's exact reach set at T = 1 where the bracket comes from them (a circle's
    equidistant formation, no obstacles, every agent with one: :func:`minimum_reach`), else
    None (bisection with phase 1)."""
    if not (problem.on_circle and problem.coupling == PotentialCoupling()) or problem.obstacles:
        return None
    try:
        return minimum_reach(problem)
    except ValueError:
        return None


def check_minimum_time(problem: FormationProblem, options: TimeOptions) -> None:
    """ValueError (one line) where the minimum time cannot be asked of ``problem``: without
    exact reach sets it needs ``time_bounds`` to bisect."""
    if options.final_time == "minimum" and options.time_bounds is None \
            and exact_reach(problem) is None:
        raise ValueError("final_time 'minimum': needs time_bounds (T_min, T_max) to bisect "
                         "(no exact reach sets: not point masses at rest under box or norm "
                         "limits onto a circle without obstacles)")


def minimum_reach(problem: FormationProblem) -> list[Reach]:
    """Each agent's exact reach set at T = 1 (:func:`~ocpar.ocp.reach.rest_to_rest_reach`),
    or ValueError where one has none or a side of it is empty (no finite time then)."""
    reaches = {}
    for shape, agents in problem.agents_by_shape().items():
        reach = rest_to_rest_reach(shape.with_duration(1.0))
        if reach is None or not (np.all(problem.start_velocities[agents] == 0)
                                 and np.all(problem.final_velocities(agents) == 0)):
            raise ValueError("final_time 'minimum': needs point masses at rest at both ends "
                             "under box or norm thrust limits (exact reach sets)")
        if not np.all(np.isfinite(reach.upper) & (reach.upper > 0) & (reach.lower < 0)):
            raise ValueError("final_time 'minimum': the thrust limits must bound every "
                             "direction and allow every one (lo < 0 < hi)")
        reaches[shape] = reach
    return [reaches[shape] for shape in problem.shapes]


def bottleneck(costs: np.ndarray) -> tuple[float, np.ndarray]:
    """The bottleneck assignment of the square matrix ``costs`` (n, n): the least t such
    that agents i can be given distinct columns σ(i) with costs[i, σ(i)] ≤ t, and such a
    σ (n,) (threshold search over the sorted entries, a bipartite matching each)."""
    # imported here: scipy.sparse costs ~0.2 s of every formation run's start-up
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    values = np.unique(costs)
    lo, hi = 0, len(values) - 1
    best = None
    while lo <= hi:
        mid = (lo + hi) // 2
        match = maximum_bipartite_matching(csr_matrix(costs <= values[mid]),
                                           perm_type="column")
        if np.all(match >= 0):
            best, hi = match, mid - 1
        else:
            lo = mid + 1
    assert best is not None
    return float(values[lo]), best


@dataclasses.dataclass
class RotationSearch:
    """The least bottleneck ν over the rotation θ: ``value`` (the best found, T² in the
    time unit squared at T = 1's reach), ``lower`` the proven lower bound, ``theta`` (rad)
    and ``assignment`` (n,) where found, ``evaluations`` of the bottleneck."""

    value: float
    lower: float
    theta: float
    assignment: np.ndarray
    evaluations: int


def search_rotation(problem: FormationProblem, reaches: list[Reach], gap: float
                    ) -> RotationSearch:
    """min over θ of the bottleneck assignment of ν_i(z_j(θ) − s_i) (module docstring) to
    a relative ``gap`` between the best value and the lower bound, by branch and bound."""
    n = problem.agents
    spacing = 2 * math.pi / n
    starts = problem.positions(problem.starts)
    radius = problem.curve.radius
    slope = radius * max(1 / min(np.min(r.upper), np.min(-r.lower)) for r in reaches)
    groups: dict[int, list[int]] = {}
    for i, r in enumerate(reaches):
        groups.setdefault(id(r), []).append(i)

    def evaluate(theta: float) -> tuple[float, np.ndarray]:
        points = problem.final_positions(theta + spacing * np.arange(n))
        costs = np.empty((n, n))
        for members in groups.values():
            rows = np.array(members)
            costs[rows] = reaches[members[0]].need(points[None] - starts[rows, None])
        return bottleneck(costs)

    grid = np.linspace(0.0, spacing, ROTATION_GRID * n + 1)
    values = [evaluate(float(t)) for t in grid]
    best = min(range(len(grid)), key=lambda k: values[k][0])
    found = [values[best][0], float(grid[best]), values[best][1]]
    heap = [(0.5 * (values[k][0] + values[k + 1][0]) - 0.5 * slope * (grid[k + 1] - grid[k]),
             float(grid[k]), float(grid[k + 1]), values[k][0], values[k + 1][0])
            for k in range(len(grid) - 1)]
    heapq.heapify(heap)
    evaluations = len(grid)
    while heap and evaluations < ROTATION_EVALUATIONS:
        bound, a, b, fa, fb = heap[0]
        if found[0] - bound <= gap * found[0]:
            break
        heapq.heappop(heap)
        mid = 0.5 * (a + b)
        fm, assignment = evaluate(mid)
        evaluations += 1
        if fm < found[0]:
            found = [fm, mid, assignment]
        for lo, hi, flo, fhi in ((a, mid, fa, fm), (mid, b, fm, fb)):
            lower = 0.5 * (flo + fhi) - 0.5 * slope * (hi - lo)
            if lower < found[0] * (1 - gap):
                heapq.heappush(heap, (lower, lo, hi, flo, fhi))
    lower = min(heap[0][0], found[0]) if heap else found[0]
    return RotationSearch(found[0], max(lower, 0.0), found[1], found[2], evaluations)


@dataclasses.dataclass
class Bracket:
    """The minimum time's bracket: no formation found below ``low``, one reachable at
    ``high`` with the parameters ``phi`` (of ``problem``'s curve), ``proven`` whether
    ``low`` is a proof (exact reach sets) or phase 1's local search; ``fields`` what the
    method adds to the result's ``final_time``; ``inner_solves`` it made."""

    low: float
    high: float
    phi: np.ndarray
    proven: bool
    fields: dict
    inner_solves: int = 0


def reach_bracket(problem: FormationProblem, reaches: list[Reach], tol: float) -> Bracket:
    """The bracket from exact reach sets (module docstring)."""
    found = search_rotation(problem, reaches, tol)
    n = problem.agents
    phi = found.theta + 2 * math.pi / n * np.arange(n)
    return Bracket(math.sqrt(found.lower), math.sqrt(found.value) * (1 + tol / 4), phi,
                   found.value - found.lower <= tol * found.value,
                   {"method": "reach sets", "rotation": found.theta,
                    "bottleneck_need": found.value, "rotation_evaluations": found.evaluations,
                    "bottleneck_assignment": found.assignment.tolist()})


def _reachable(problem: FormationProblem, backend: Backend, duration: float,
               phi0: np.ndarray | None) -> tuple[np.ndarray | None, float, int]:
    """Phase 1 at ``duration``: the feasible parameters it found (None if none), the least
    total slack (0 where found, +inf where the problem refuses T) and its inner solves."""
    try:
        at = at_duration(problem, duration)
    except ValueError:   # some agent reaches no point of the curve at all
        return None, math.inf, 0
    start = at.initial_phi() if phi0 is None else phi0
    try:
        found = phase_one(at, backend, start)
    except NoFeasibleFormation as exc:
        return None, exc.slack, 0
    return found.phi, found.slack, found.inner_solves


def phase_one_bracket(problem: FormationProblem, backend: Backend, low: float, high: float,
                      tol: float, progress: Callable[[str], None] | None) -> Bracket:
    """The bracket by bisection of [``low``, ``high``] in log T with phase 1 (module
    docstring); ValueError if phase 1 finds no formation at ``high``."""
    phi, _, solves = _reachable(problem, backend, high, None)
    if phi is None:
        raise ValueError(f"final_time 'minimum': phase 1 finds no formation reachable at "
                         f"T_max = {high:g}")
    tests = 2
    below, slack, count = _reachable(problem, backend, low, phi)
    solves += count
    if below is not None:   # reachable at T_min already: the answer is the bound
        return Bracket(low, low, below, True, {"method": "phase 1", "at_bound": "T_min",
                                               "tests": tests}, solves)
    while high * (1 - tol) > low:
        middle = math.sqrt(low * high)
        found, middle_slack, count = _reachable(problem, backend, middle, phi)
        solves, tests = solves + count, tests + 1
        if found is None:
            low, slack = middle, middle_slack
        else:
            high, phi = middle, found
        if progress is not None:
            progress(f"minimum time: T in [{low:.12g}, {high:.12g}] (phase 1)")
    return Bracket(low, high, phi, False, {"method": "phase 1", "tests": tests,
                                           "phase_one_least_slack_at_low": slack}, solves)


def solve_minimum_time(problem: FormationProblem, backend: Backend, options: TimeOptions,
                       solve: Callable[..., FormationResult],
                       progress: Callable[[str], None] | None = None,
                       output: Path | None = None) -> FormationResult:
    """The least common T at which a formation is reachable (module docstring). Returns the
    formation solved by ``solve`` at T_hi onto the bracket's formation points, with
    ``final_time``: T, the ``bracket``, ``proven``, the method's figures and phase 1's total
    slack at T_hi (1 − ``time_tol``) of the returned formation."""
    tol = options.time_tol
    start, first_trace = time.perf_counter(), len(backend.traces)
    reaches = exact_reach(problem)
    low, high = time_bounds(options)
    if reaches is not None:
        bracket = reach_bracket(problem, reaches, tol)
    else:
        bracket = phase_one_bracket(problem, backend, low, high, tol, progress)
    t_lo, t_hi = bracket.low, bracket.high
    if progress is not None:
        progress(f"minimum time: T in [{t_lo:.12g}, {t_hi:.12g}] ({bracket.fields['method']})")
    n = problem.agents
    points = problem.final_positions(bracket.phi)
    fixed = dataclasses.replace(options, final_time="fixed", ordering="keep")
    onto = dataclasses.replace(at_duration(problem, t_hi), curve=Slots(points),
                               coupling=PotentialCoupling())
    result = solve(onto, backend, fixed, None, progress, output)
    slots = np.asarray(result.phi, float)
    ok = np.all(np.isfinite(slots))
    chosen = np.reshape(bracket.phi, (n, -1))[np.nan_to_num(slots).astype(np.intp)]
    phi = np.reshape(chosen, problem.parameter_shape) if ok else \
        np.full(problem.parameter_shape, np.nan)
    # phase 1 at T_hi (1 − tol) of the formation returned
    t_check = min(t_lo, t_hi * (1 - tol))
    shapes = tuple(elastic_shape(shape.with_duration(t_check)) for shape in problem.shapes)
    params = problem.boundary_params_rows(np.arange(n), chosen if ok else bracket.phi)
    slack = backend.superstep_columns(solve_tasks, task_columns(shapes, params))
    solved = np.asarray(slack.column("success"), bool)
    total_slack = float(np.sum(np.asarray(slack.column("cost"), float))) if solved.all() \
        else math.nan
    at_bound = bracket.fields.get("at_bound") == "T_min"
    proof = ("exact reach sets, rotation and assignment searched: a bottleneck"
             if bracket.fields["method"] == "reach sets" else "phase 1's local search")
    words = (f"minimum time T* = {t_hi:.12g} (solved there: the energy-optimal assignment "
             f"onto the formation's points), none reachable below {t_lo:.12g} ({proof}; "
             f"T_hi/T_lo - 1 = {t_hi / t_lo - 1:.1e}); phase 1 at T = {t_check:.12g}: total "
             f"slack {total_slack:.3e}")
    status = result.status
    if at_bound:
        words = f"minimum time at T_min = {t_hi:.12g}: reachable there (solved)"
    elif not (t_hi * (1 - tol) <= t_lo):
        status, words = "not_converged", words + (
            f"; the search stopped short of the bracket's width ({bracket.fields})")
    elif not total_slack > SLACK_TOL:
        status, words = "not_converged", words + "; phase 1 does not confirm the lower end"
    if not low <= t_hi <= high:
        status, words = "failed", words + f"; outside time_bounds [{low:g}, {high:g}]"
    fields = {"mode": "minimum", "T": t_hi, "bracket": [t_lo, t_hi], "time_tol": tol,
              "proven": bracket.proven, "phase_one_T": t_check,
              "phase_one_slack": total_slack if math.isfinite(total_slack) else None,
              **bracket.fields, "message": words}
    return dataclasses.replace(
        result, status=status, phi=phi,
        message=words if result.converged else f"{result.message}; {words}",
        on_circle=problem.on_circle, final_time=fields,
        inner_solves=result.inner_solves + n + bracket.inner_solves,
        fleet=Fleet.of(at_duration(problem, t_hi), phi), trace=backend.traces[first_trace:],
        wall_time_s=time.perf_counter() - start)


__all__ = ["Bracket", "RotationSearch", "bottleneck", "check_minimum_time", "exact_reach",
           "minimum_reach", "phase_one_bracket", "reach_bracket", "search_rotation",
           "solve_minimum_time"]
