"""Free and minimum final time of a formation: the common horizon T as an outer variable.

``free`` (:func:`solve_free_time`): min over T in [T_min, T_max] of F(T) + w T, where F(T) is
the formation's optimum Σ_i Ĵ_i at horizon T (the outer problem over φ solved at T, as for
a fixed T). By the envelope theorem F'(T) = Σ_i ∂J_i*/∂T at the formation's optimum: each
agent's inner problem with T as its last parameter (``DmocShape.free_duration``) gives
∂J_i*/∂T from its parameters' multiplier and ∂²J_i*/∂T² from its KKT system
(:mod:`ocpar.ocp.duration`), summed on the workers over fixed units of agents (the same
numbers on any number of workers). A safeguarded Newton step on F'(T) + w = 0 with the
curvature Σ_i ∂²J_i*/∂T² (exact where the formation's optimum φ* does not move with T to
first order in the cost, e.g. point masses from rest to rest, J ∝ 1/T³; a bisection step
where the Newton step leaves the bracket of the root) gives the next T; the formation is
re-solved there from the previous φ. T stops at a bound where F' + w keeps its sign there.

``minimum`` (:func:`solve_minimum_time`): the least T at which some formation on a circle
(a rotation θ and an assignment of agents to the n equidistant points) is reachable by
every agent under its thrust limit, for point masses at rest at both ends under box or norm
limits, whose DMOC reach sets are exact (:mod:`ocpar.ocp.reach`) and grow as T²: agent i
reaches displacement Δ in T exactly when T² ≥ ν_i(Δ), ν_i the need of its reach set at
T = 1. So T*² = min_θ min_σ max_i ν_i(z_σ(i)(θ) − s_i): a bottleneck assignment at each θ
(threshold search with a bipartite matching), and over θ a branch and bound with the
Lipschitz constant R · max_i 1/(smallest reach of agent i at T = 1) (R the radius). Its
lower bound proves that no formation is reachable below T_lo; at T_hi ≥ T_lo (1 + tol)⁻¹
the formation at the best θ is solved (the energy-optimal assignment onto its n points
among the reachable pairs: the energy tie-break) and verified; phase 1
(:mod:`ocpar.formation.feasibility`'s elastic inner problems) is solved at T_lo for that
formation, and its total slack must be positive.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching

from ocpar.bsp import Backend
from ocpar.bsp.columns import LISTED, Columns
from ocpar.bsp.partition import unit_size
from ocpar.formation.couplings.coupling import PotentialCoupling
from ocpar.formation.feasibility import SLACK_TOL, elastic_shape
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import Fleet, FormationResult
from ocpar.formation.targets.slots import Slots
from ocpar.ocp import DmocShape, OcpTask, solve_tasks
from ocpar.ocp.duration import DurationSums, DurationUnit, duration_sums
from ocpar.ocp.reach import Reach, rest_to_rest_reach

if TYPE_CHECKING:
    from ocpar.formation.solve import FormationOptions

#: What the final time is (:class:`~ocpar.formation.FormationOptions` ``final_time``).
FINAL_TIMES = ("fixed", "free", "minimum")
#: Newton steps in T at most (each a formation solve at one T).
TIME_ITERATIONS = 50
#: Shifts of the rotation's first grid per agent (minimum time's branch and bound).
ROTATION_GRID = 32
#: Evaluations of the bottleneck over the rotation at most.
ROTATION_EVALUATIONS = 200_000


def at_duration(problem: FormationProblem, duration: float) -> FormationProblem:
    """``problem`` over the horizon ``duration`` (the model's time unit)."""
    return problem.with_shapes(lambda shape: shape.with_duration(duration))


def task_columns(shapes: tuple[DmocShape, ...], params: np.ndarray) -> Columns:
    """Columns of :class:`~ocpar.ocp.OcpTask`: task k on ``shapes[k]`` with ``params[k]``."""
    columns = Columns.of(OcpTask, len(params), shape=shapes[0], params=params,
                         warm_start=None, multipliers=None, fallback=None)
    if len(set(shapes)) > 1:
        columns.fields["shape"] = (LISTED, list(shapes))
    return columns


def duration_derivatives(problem: FormationProblem, backend: Backend, phi: np.ndarray
                         ) -> DurationSums:
    """Σ_i J_i*, ∂J_i*/∂T and ∂²J_i*/∂T² of ``problem``'s agents ending at ``phi`` at its
    horizon T: one superstep of their inner problems with T a parameter, summed per unit of
    :func:`~ocpar.bsp.partition.unit_size` agents on the workers, the units' sums added here
    in unit order."""
    n, duration = problem.agents, problem.common_shape.duration
    shapes = tuple(dataclasses.replace(shape, free_duration=True) for shape in problem.shapes)
    params = np.hstack([problem.boundary_params_rows(np.arange(n), np.reshape(
        phi, problem.parameter_shape)), np.full((n, 1), duration)])
    size = unit_size(n)
    units = [DurationUnit(task_columns(shapes[a:a + size], params[a:a + size]))
             for a in range(0, n, size)]
    sums = backend.superstep(duration_sums, units)
    total = sums[0]
    for part in sums[1:]:
        total = total + part
    return total


def check_final_time(problem: FormationProblem, options: FormationOptions) -> None:
    """ValueError (one line) where ``options``' final time does not apply to ``problem``."""
    if options.final_time == "fixed":
        return
    what = f"final_time {options.final_time!r}"
    if options.mode != "hierarchical":
        raise ValueError(f"{what}: applies to the hierarchical mode")
    if options.min_separation is not None:
        raise ValueError(f"{what}: not with min_separation (the separation rounds' keep-out "
                         "solves do not take a free duration yet)")
    if options.final_time == "free":
        if options.time_bounds is None:
            raise ValueError(f"{what}: needs time_bounds (T_min, T_max)")
        if not options.time_weight > 0:
            raise ValueError(f"{what}: needs a time_weight w > 0 (the cost is sum J_i + w T)")
    if options.final_time == "minimum":
        if not (problem.on_circle and problem.coupling == PotentialCoupling()):
            raise ValueError(f"{what}: applies to a circle with the equidistant formation "
                             "(the default coupling)")
        minimum_reach(problem)


def time_bounds(options: FormationOptions) -> tuple[float, float]:
    """``options.time_bounds`` as (T_min, T_max) with 0 < T_min ≤ T_max < ∞, or ValueError."""
    bounds = options.time_bounds
    if bounds is None:
        return 0.0, math.inf
    low, high = bounds
    return low, high


# ----------------------------------------------------------------------------------------
# free common T
# ----------------------------------------------------------------------------------------

def solve_free_time(problem: FormationProblem, backend: Backend, options: FormationOptions,
                    solve: Callable[..., FormationResult], phi0: np.ndarray | None = None,
                    progress: Callable[[str], None] | None = None,
                    output: Path | None = None) -> FormationResult:
    """min over T of F(T) + w T (module docstring), each F(T) a formation solve by ``solve``
    (:func:`~ocpar.formation.solve_formation` with ``options`` at a fixed T). Returns the
    formation solve at the last T with ``final_time`` set: T, w, the objective
    Σ J_i + w T, dF/dT + w there, the bound it stopped at (if any), the iterations (each
    T, Σ J_i, dF/dT) and why it stopped."""
    fixed = dataclasses.replace(options, final_time="fixed")
    low, high = time_bounds(options)
    weight, tol = options.time_weight, options.time_tol
    duration = float(np.clip(problem.common_shape.duration, low, high))
    lower, upper = low, high   # the bracket of the root of F' + w
    phi, history, solves, outer = phi0, [], 0, 0
    start, first_trace = time.perf_counter(), len(backend.traces)
    result: FormationResult | None = None   # the last solve that did not fail
    reason, at_bound, slope, solved_at = "", None, math.nan, duration
    previous: tuple[float, float] | None = None   # the last (T, F'(T)) solved
    infeasible = -math.inf   # the largest T found infeasible
    for _ in range(TIME_ITERATIONS):
        try:
            attempt = solve(at_duration(problem, duration), backend, fixed, phi, progress,
                            output)
        except ValueError as exc:   # no formation reachable at this T (exact reach sets)
            attempt, words = None, str(exc)
        if attempt is not None:
            solves += attempt.inner_solves
            outer += max(attempt.outer_iterations, 0)
            words = attempt.message
            if result is None or attempt.status != "failed":   # the last one solved
                result, solved_at = attempt, duration
        if attempt is None or attempt.status == "failed":   # F(T) = +inf: T goes up
            history.append({"T": duration, "cost": None, "infeasible": words})
            lower = infeasible = duration
            new = 0.5 * (lower + upper) if math.isfinite(upper) else min(2 * duration, high)
            if duration >= high or abs(new - duration) <= tol * duration:
                reason = f"no formation solved at T = {duration:.12g}: {words}"
                break
            duration = new
            continue
        if not attempt.converged:
            reason = f"the formation solve at T = {duration:.12g} did not converge"
            break
        sums = duration_derivatives(at_duration(problem, duration), backend, result.phi)
        solves += sums.solves
        if sums.failed:
            reason = (f"{sums.failed} inner solve(s) with T a parameter failed at T = "
                      f"{duration:.12g} ({sums.first_failure})")
            break
        slope = sums.gradient + weight
        history.append({"T": duration, "cost": sums.cost, "dcost_dT": sums.gradient,
                        "d2cost_dT2": sums.curvature})
        if progress is not None:
            progress(f"final time T = {duration:.12g}: sum J {sums.cost:.12g}, "
                     f"dF/dT + w = {slope:.3e}")
        if (duration <= low and slope >= 0) or (duration >= high and slope <= 0):
            at_bound = "T_min" if duration <= low else "T_max"
            reason = f"at {at_bound}: dF/dT + w = {slope:.3e} points out of the bounds"
            break
        if abs(slope) <= tol * (abs(sums.gradient) + weight):
            reason = f"|dF/dT + w| = {abs(slope):.1e} below tolerance"
            break
        if slope > 0:
            upper = duration
        else:
            lower = duration
        curvature = sums.curvature
        if previous is not None and previous[0] != duration:   # the secant of exact F'
            curvature = (sums.gradient - previous[1]) / (duration - previous[0])
        previous = (duration, sums.gradient)
        new = _next_duration(duration, sums.gradient, curvature, weight)
        if new >= upper and upper == high and slope < 0:   # to the bound, then stop there
            new = high
        elif new <= lower and lower == low and slope > 0 and infeasible < low:
            new = low
        elif not lower < new < upper:   # no Newton step inside the bracket: bisect it
            new = 0.5 * (lower + upper) if math.isfinite(upper) else 2.0 * duration
        if abs(new - duration) <= tol * duration:
            reason = (f"at the least T solved, infeasible at T = {infeasible:.12g}: "
                      f"dF/dT + w = {slope:.3e} > 0 there"
                      if slope > 0 and lower == infeasible else
                      f"step in T below tolerance ({abs(new - duration):.1e})")
            break
        duration, phi = new, result.phi
    else:
        reason = f"{TIME_ITERATIONS} steps in T without meeting the tolerance"
    if result is None:
        raise ValueError(f"final_time 'free': {reason}")
    stationary = solved_at == duration and reason.startswith(("|dF/dT", "at T_", "step in T",
                                                              "at the least T"))
    status = result.status if stationary or not result.converged else "not_converged"
    duration = solved_at
    fields = {"mode": "free", "T": duration, "time_weight": weight,
              "time_bounds": [low, high], "objective": (result.total_cost + weight * duration
                                                        if result.converged else None),
              "dF_dT_plus_w": slope if math.isfinite(slope) else None,
              "at_bound": at_bound, "iterations": history, "message": reason}
    return dataclasses.replace(result, status=status, final_time=fields,
                               inner_solves=solves, outer_iterations=outer,
                               wall_time_s=time.perf_counter() - start,
                               trace=backend.traces[first_trace:],
                               message=f"{result.message}; free final time: {reason}")


def _next_duration(duration: float, gradient: float, curvature: float, weight: float
                   ) -> float:
    """The Newton step's T for F'(T) + w = 0 given F' (``gradient``) and F''
    (``curvature``): in log–log coordinates where F decreases and is convex (log(−F') =
    log w, linear in log T: exact in one step for F ∝ T^k, e.g. point masses from rest to
    rest, k = −3), else on F' + w itself; NaN where neither applies."""
    if gradient < 0 and curvature > 0:
        order = duration * curvature / gradient   # d log(−F') / d log T < 0
        return duration * (weight / -gradient) ** (1 / order)
    if curvature > 0:
        return duration - (gradient + weight) / curvature
    return math.nan


# ----------------------------------------------------------------------------------------
# minimum time
# ----------------------------------------------------------------------------------------

def minimum_reach(problem: FormationProblem) -> list[Reach]:
    """Each agent's exact reach set at T = 1 (:func:`~ocpar.ocp.reach.rest_to_rest_reach`),
    or ValueError where one has none or a side of it is empty (no finite time then)."""
    reaches = {}
    for shape, agents in problem.agents_by_shape().items():
        reach = rest_to_rest_reach(shape.with_duration(1.0))
        at_rest = (np.all(problem.start_velocities[agents] == 0)
                   and np.all(problem.final_velocities(agents) == 0))
        if reach is None or not at_rest:
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


def solve_minimum_time(problem: FormationProblem, backend: Backend, options: FormationOptions,
                       solve: Callable[..., FormationResult],
                       progress: Callable[[str], None] | None = None,
                       output: Path | None = None) -> FormationResult:
    """The least common T at which a formation is reachable (module docstring): the bracket
    [T_lo, T_hi] with T_hi (1 − ``time_tol``) ≤ T_lo, no formation reachable below T_lo (the
    reach sets' bound), the formation solved and verified at T_hi by ``solve``, phase 1's
    total slack at T_lo for that formation. Returns the solve at T_hi with ``final_time``."""
    tol = options.time_tol
    start, first_trace = time.perf_counter(), len(backend.traces)
    reaches = minimum_reach(problem)
    found = search_rotation(problem, reaches, tol)
    proven = found.value - found.lower <= tol * found.value
    t_lo = math.sqrt(found.lower)
    t_hi = math.sqrt(found.value) * (1 + tol / 4)
    if progress is not None:
        progress(f"minimum time: bottleneck over the rotation, {found.evaluations} "
                 f"evaluations, T in [{t_lo:.12g}, {t_hi:.12g}]")
    low, high = time_bounds(options)
    n, spacing = problem.agents, 2 * math.pi / problem.agents
    angles = found.theta + spacing * np.arange(n)
    points = problem.final_positions(angles)
    fixed = dataclasses.replace(options, final_time="fixed", ordering="keep")
    onto = dataclasses.replace(at_duration(problem, t_hi), curve=Slots(points),
                               coupling=PotentialCoupling())
    result = solve(onto, backend, fixed, None, progress, output)
    slots = np.asarray(result.phi, float)
    phi = np.where(np.isfinite(slots), found.theta + spacing * np.nan_to_num(slots), np.nan)
    # phase 1 at T_lo (and below T_hi (1 − tol)) for the formation found
    t_check = min(t_lo, t_hi * (1 - tol))
    shapes = tuple(elastic_shape(shape.with_duration(t_check)) for shape in problem.shapes)
    params = problem.boundary_params_rows(np.arange(n), np.where(np.isfinite(phi), phi, angles))
    slack = backend.superstep_columns(solve_tasks, task_columns(shapes, params))
    ok = np.asarray(slack.column("success"), bool)
    total_slack = float(np.sum(np.asarray(slack.column("cost"), float))) if ok.all() \
        else math.nan
    words = (f"minimum time T* = {t_hi:.12g} (feasible, solved there), no formation "
             f"reachable below {t_lo:.12g} (exact reach sets, rotation and assignment "
             f"searched: a bottleneck); phase 1 at T = {t_check:.12g}: total slack "
             f"{total_slack:.3e}")
    status = result.status
    if not proven:
        status, words = "not_converged", words + (
            f"; the rotation search stopped after {found.evaluations} evaluations short of "
            f"the gap (lower bound {t_lo:.12g})")
    elif not total_slack > SLACK_TOL:
        status, words = "not_converged", words + "; phase 1 does not confirm the lower end"
    if not low <= t_hi <= high:
        status, words = "failed", words + f"; outside time_bounds [{low:g}, {high:g}]"
    fields = {"mode": "minimum", "T": t_hi, "bracket": [t_lo, t_hi], "time_tol": tol,
              "proven": proven, "rotation": found.theta, "bottleneck_need": found.value,
              "rotation_evaluations": found.evaluations, "phase_one_T": t_check,
              "phase_one_slack": total_slack if math.isfinite(total_slack) else None,
              "bottleneck_assignment": found.assignment.tolist(), "message": words}
    return dataclasses.replace(
        result, status=status, message=f"{result.message}; {words}", phi=phi,
        on_circle=True, final_time=fields, inner_solves=result.inner_solves + n,
        fleet=Fleet.of(at_duration(problem, t_hi), phi), trace=backend.traces[first_trace:],
        wall_time_s=time.perf_counter() - start)


__all__ = ["FINAL_TIMES", "RotationSearch", "at_duration", "bottleneck", "check_final_time",
           "duration_derivatives", "search_rotation", "solve_free_time", "solve_minimum_time"]
