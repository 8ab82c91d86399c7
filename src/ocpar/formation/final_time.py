"""Free final time of a formation: one common horizon T as an outer variable, or each
agent's own T_i as a variable of its inner problem.

``free`` (:func:`solve_free_time`): min over T in [T_min, T_max] of Σ_i J_i + w T. Each
agent's inner problem takes T as its last parameter (``free_duration`` of ``DmocShape`` and
``MsEndpointShape``), which gives ∂J_i*/∂T from its parameters' multiplier (the envelope
theorem) and ∂²J_i*/∂T², ∂²J_i*/∂q_N∂T from its KKT system.

* Where the outer problem is the shift Newton over a family φ(θ) (:func:`joint_family`), T
  is an outer variable beside θ (:func:`solve_jointly`): each superstep solves the agents at
  (θ, T), T set on the workers, and returns the sums of J and its first and second
  derivatives in (θ, T) per reduction unit (:mod:`ocpar.formation.outer_step`), so that one
  Newton step moves both (:mod:`ocpar.formation.joint_time`); one fixed-T formation solve at
  the T found gives the answer.
* Elsewhere (:func:`solve_by_sequence`) F(T), the formation's optimum at T, is a formation
  solve per T, F'(T) = Σ_i ∂J_i*/∂T at its optimum and Σ_i ∂²J_i*/∂T² one superstep
  after it (:mod:`ocpar.ocp.duration`), summed on the workers over fixed units of agents
  (the same numbers on any number of workers). A safeguarded Newton step on F'(T) + w = 0
  (in log–log coordinates where F falls and is convex: exact in one step for F ∝ T^k, point
  masses from rest to rest having J ∝ 1/T³), its curvature Σ_i ∂²J_i*/∂T² at the first T
  and the secant of the exact F' after (the reduced curvature where φ* moves with T), a
  bisection step where it leaves the bracket of the root, gives the next T; the formation is
  re-solved there from the previous φ. T stops at a bound where F' + w points outward; a T
  where no formation is solved counts as F = +∞.

``free_per_agent`` (:func:`solve_per_agent_time`): each agent's own T_i in [T_min, T_max],
its inner cost J_i + w T_i: T_i a variable of its inner problem (the shapes' ``time_bounds``,
``time_weight``), so the outer problem sees the same contract (the optimum over T_i, its
gradient and Hessian in q_N from the KKT system) and is solved as for a fixed T. Each
agent's paths are checked at its own T_i (:mod:`ocpar.formation.finish`); the closest
approach is that of the paths on the union of the agents' node times, each agent held at its
target after its T_i (:func:`closest_across_horizons`: exact, every path linear between
those times).

``minimum``: :mod:`ocpar.formation.minimum_time`. This module also holds what both share:
the problem at another T (:func:`at_duration`), tasks on given shapes (:func:`task_columns`),
the time bounds.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import LISTED, Columns
from ocpar.bsp.partition import unit_size
from ocpar.formation.couplings.coupling import ShiftFamily
from ocpar.formation.feasibility import InnerSolveFailed, feasible_window
from ocpar.formation.hierarchical import OuterObjective
from ocpar.formation.joint_time import joint_newton, next_duration
from ocpar.formation.keep_out.separation import ClosestApproach, closest_approach
from ocpar.formation.outer_step import prepare_workers
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import FormationResult
from ocpar.formation.targets.slots import Slots
from ocpar.formation.verify import near_collision, near_collision_words
from ocpar.ocp import DmocShape, OcpTask
from ocpar.ocp.batch import AUTO_SOLVER
from ocpar.ocp.duration import DurationSums, DurationUnit, duration_sums


class TimeOptions(Protocol):
    """What this module reads of a formation solve's options
    (:class:`ocpar.formation.FormationOptions`, which imports this module)."""

    mode: str
    outer: str
    outer_tol: float
    max_outer_iterations: int
    ordering: str
    min_separation: float | None
    final_time: str
    time_bounds: tuple[float, ...] | None
    time_weight: float
    time_tol: float

#: What the final time is (:class:`~ocpar.formation.FormationOptions` ``final_time``).
FINAL_TIMES = ("fixed", "free", "free_per_agent", "minimum")
#: The most nodes (agents × union of their node times) :func:`closest_across_horizons`
#: resamples (32 MB in 2-D); beyond, the closest approach is not computed (NaN).
UNION_NODES = 2_000_000
#: Newton steps in T at most (each a formation solve at one T).
TIME_ITERATIONS = 50


def at_duration(problem: FormationProblem, duration: float) -> FormationProblem:
    """``problem`` over the horizon ``duration`` (the model's time unit), T fixed in its
    inner problems: a point mass's KKT matrix is then constant, factorised once per batch
    (10,000 solves in 0.10 s, against 0.60 s with T a parameter, whose matrix depends on
    it); building the shape of a new T costs ~10 ms."""
    return problem.with_shapes(lambda shape: dataclasses.replace(
        shape, duration=float(duration), free_duration=False))


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
    n = problem.agents
    problem = problem.with_shapes(lambda shape: dataclasses.replace(shape, free_duration=True))
    shapes = problem.shapes
    params = problem.boundary_params_rows(np.arange(n), np.reshape(phi, problem.parameter_shape))
    size = unit_size(n)
    units = [DurationUnit(task_columns(shapes[a:a + size], params[a:a + size]))
             for a in range(0, n, size)]
    sums = backend.superstep(duration_sums, units)
    total = sums[0]
    for part in sums[1:]:
        total = total + part
    return total


def check_final_time(problem: FormationProblem, options: TimeOptions) -> None:
    """ValueError (one line) where ``options``' final time does not apply (the minimum
    time's own conditions: :func:`~ocpar.formation.minimum_time.check_minimum_time`)."""
    if options.final_time == "fixed":
        return
    what = f"final_time {options.final_time!r}"
    if options.mode != "hierarchical":
        raise ValueError(f"{what}: applies to the hierarchical mode")
    if options.min_separation is not None:
        raise ValueError(f"{what}: not with min_separation (the separation rounds' keep-out "
                         "solves do not take a free duration yet)")
    if options.final_time in ("free", "free_per_agent"):
        if options.time_bounds is None:
            raise ValueError(f"{what}: needs time_bounds (T_min, T_max)")
        if not options.time_weight > 0:
            raise ValueError(f"{what}: needs a time_weight w > 0 (the cost is sum J_i + w T)")
        if any(getattr(shape.model, "time_dependent", False) for shape in problem.shapes):
            raise ValueError(f"{what}: the model is time dependent (tabulated on the "
                             "intervals of one T); T cannot be a parameter of its inner problem")


def time_bounds(options: TimeOptions) -> tuple[float, float]:
    """``options.time_bounds`` as (T_min, T_max) (checked by the options), (0, ∞) where
    none are given."""
    bounds = options.time_bounds
    if bounds is None:
        return 0.0, math.inf
    low, high = bounds
    return low, high


# ----------------------------------------------------------------------------------------
# free common T
# ----------------------------------------------------------------------------------------

def solve_free_time(problem: FormationProblem, backend: Backend, options: TimeOptions,
                    solve: Callable[..., FormationResult], phi0: np.ndarray | None = None,
                    progress: Callable[[str], None] | None = None,
                    output: Path | None = None) -> FormationResult:
    """min over T of F(T) + w T (module docstring): by joint Newton steps in (θ, T)
    (:func:`solve_jointly`) where the outer problem is a shift family's, else by a
    formation solve per T (:func:`solve_by_sequence`). ``solve`` is
    :func:`~ocpar.formation.solve_formation` (with ``options`` at a fixed T); ``phi0`` the
    start (None: the problem's)."""
    family = joint_family(problem, options, phi0)
    if family is not None:
        result = solve_jointly(problem, backend, options, solve, family, progress, output)
        if result is not None:
            return result
    return solve_by_sequence(problem, backend, options, solve, phi0, progress, output)


def joint_family(problem: FormationProblem, options: TimeOptions,
                 phi0: np.ndarray | None) -> ShiftFamily | None:
    """The shift family through the start ``phi0`` (None: the problem's initial angles)
    where the joint (θ, T) search applies: the ``newton`` outer solver, ordering ``keep``,
    a coupling whose solutions through the start form a family
    (:class:`~ocpar.formation.couplings.coupling.ShiftFamily`), no obstacles; else None."""
    if options.outer != "newton" or options.ordering != "keep" or problem.obstacles \
            or isinstance(problem.curve, Slots):
        return None
    start = problem.initial_phi() if phi0 is None else np.asarray(phi0, float).ravel()
    return problem.coupling.family(start, problem.curve)


def solve_jointly(problem: FormationProblem, backend: Backend, options: TimeOptions,
                  solve: Callable[..., FormationResult], family: ShiftFamily,
                  progress: Callable[[str], None] | None = None,
                  output: Path | None = None) -> FormationResult | None:
    """T an outer variable beside the family's shift θ: the agents' inner problems take T
    as their last parameter (set on the workers each superstep) and
    :func:`~ocpar.formation.joint_time.joint_newton` moves (θ, T) together, from T the
    problem's duration (clipped to the bounds) and θ the feasible start of the thrust
    limits' window there (:func:`~ocpar.formation.feasibility.feasible_window`); then one
    formation solve by ``solve`` at the T found, from its angles, gives the answer, checked
    and written as any fixed-T one. None where no formation is solved at the first T (no
    formation within reach, or the first superstep's solves fail): the sequence of
    formation solves then finds a T where one is."""
    low, high = time_bounds(options)
    weight = options.time_weight
    duration = float(np.clip(problem.common_shape.duration, low, high))
    try:
        window = feasible_window(at_duration(problem, duration), family)
    except ValueError:   # no formation within the agents' reach at this T
        return None
    start, first_trace = time.perf_counter(), len(backend.traces)
    timed = problem.with_shapes(lambda shape: dataclasses.replace(
        shape, free_duration=True, duration=duration))
    prepare_workers(timed, backend)
    objective = OuterObjective(timed, backend, progress)
    try:
        search = joint_newton(objective, family, 0.0 if window is None else window.start,
                              duration, weight, (low, high), options.outer_tol,
                              options.time_tol, options.max_outer_iterations)
    except InnerSolveFailed:
        return None
    finally:
        objective.close()
    fixed = dataclasses.replace(options, final_time="fixed")
    result = solve(at_duration(problem, search.duration), backend, fixed,
                   family.angles(search.theta)[0], progress, output)
    reached = search.success and result.converged
    status = "not_converged" if result.converged and not search.success else result.status
    values = search.values
    reason = (f"T and the shift by joint Newton steps, {search.iterations} step(s) in "
              f"{len(search.history)} superstep(s): {search.reason}")
    fields = {"mode": "free", "method": "joint", "T": search.duration,
              "time_weight": weight, "time_bounds": [low, high],
              "objective": result.total_cost + weight * search.duration if reached else None,
              "dF_dT_plus_w": values.time_slope + weight, "at_bound": search.at_bound,
              "iterations": search.history, "message": reason}
    return dataclasses.replace(
        result, status=status, final_time=fields,
        inner_solves=objective.inner_solves + result.inner_solves,
        failed_solves=objective.failed_solves + result.failed_solves,
        retries=objective.retries + result.retries,
        outer_iterations=(search.iterations + result.outer_iterations
                          if result.outer_iterations is not None else None),
        wall_time_s=time.perf_counter() - start, trace=backend.traces[first_trace:],
        message=f"{result.message}; free final time: {reason}")


def solve_by_sequence(problem: FormationProblem, backend: Backend, options: TimeOptions,
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
        new = next_duration(duration, sums.gradient, curvature, weight)
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
    fields = {"mode": "free", "method": "sequence", "T": duration, "time_weight": weight,
              "time_bounds": [low, high], "objective": (result.total_cost + weight * duration
                                                        if result.converged else None),
              "dF_dT_plus_w": slope if math.isfinite(slope) else None,
              "at_bound": at_bound, "iterations": history, "message": reason}
    return dataclasses.replace(result, status=status, final_time=fields,
                               inner_solves=solves, outer_iterations=outer,
                               wall_time_s=time.perf_counter() - start,
                               trace=backend.traces[first_trace:],
                               message=f"{result.message}; free final time: {reason}")


def solve_per_agent_time(problem: FormationProblem, backend: Backend,
                         options: TimeOptions, solve: Callable[..., FormationResult],
                         phi0: np.ndarray | None = None,
                         progress: Callable[[str], None] | None = None) -> FormationResult:
    """Each agent's own T_i (module docstring): the formation solved by ``solve`` with every
    agent's inner problem choosing T_i, each T_i that of its returned path (the result's
    ``durations``, from the agents' finish on the workers). Its arrays come back to the coordinator
    (the velocities need each T_i); ``agent_costs`` are J_i + w T_i."""
    low, high = time_bounds(options)
    weight = options.time_weight
    start = time.perf_counter()
    timed = problem.with_shapes(lambda shape: dataclasses.replace(
        shape, time_bounds=(low, high), time_weight=weight,
        solver=AUTO_SOLVER if shape.solver == "newton" else shape.solver))
    fixed = dataclasses.replace(options, final_time="fixed")
    result = solve(timed, backend, fixed, phi0, progress, None)
    # each agent's T_i is its returned path's (a re-solve from the default guess could end
    # at another local optimum: another side of an obstacle)
    durations = (np.full(problem.agents, np.nan) if result.durations is None
                 or not np.all(np.isfinite(result.phi)) else np.asarray(result.durations, float))
    message = result.message
    if result.verification is not None and result.verification.near_collision is not None:
        message = message.replace(f"; {near_collision_words(result.verification.near_collision)}",
                                  "")   # the check on a common horizon's times: not these
    closest = closest_across_horizons(result.positions, durations, backend)
    verification = result.verification
    if verification is not None:
        near = near_collision(closest, verification.spacing)
        verification = dataclasses.replace(verification, closest=closest, near_collision=near)
        if near is not None:
            message += f"; {near_collision_words(near)}"
    fields = {"mode": "free_per_agent", "T": float(np.max(durations)) if np.all(
        np.isfinite(durations)) else None, "time_weight": weight, "time_bounds": [low, high],
        "at_T_min": int(np.sum(durations <= low)), "at_T_max": int(np.sum(durations >= high))}
    fleet = result.fleet
    if fleet is not None and fields["T"] is not None:   # the time axis: the longest T_i
        fleet = dataclasses.replace(fleet, duration=fields["T"])
    return dataclasses.replace(
        result, final_time=fields, durations=durations, separation=closest, fleet=fleet,
        verification=verification, inner_solves=result.inner_solves,
        message=message + "; each agent its own final time", wall_time_s=time.perf_counter()
        - start)


def closest_across_horizons(positions: np.ndarray, durations: np.ndarray,
                            backend: Backend | None = None) -> ClosestApproach:
    """The closest approach of agents whose node positions ``positions`` (n, N+1, d) are at
    their own times k T_i / N (``durations`` (n,)), each held at its last node after T_i:
    all paths resampled at the union of the node times, where every one is linear between
    consecutive times (:func:`~ocpar.formation.keep_out.separation.closest_approach` on
    them, its time mapped back). NaN where a path or T_i is not finite or the union is
    larger than :data:`UNION_NODES`."""
    n, nodes, dim = positions.shape
    unknown = ClosestApproach(math.nan, (-1, -1), math.nan)
    if not (np.all(np.isfinite(durations)) and np.all(np.isfinite(positions))):
        return unknown
    grids = durations[:, None] * np.linspace(0.0, 1.0, nodes)[None]
    times = np.unique(grids)
    if n * len(times) > UNION_NODES:
        return unknown
    resampled = np.empty((n, len(times), dim))
    for i in range(n):   # np.interp holds the last value after T_i
        for axis in range(dim):
            resampled[i, :, axis] = np.interp(times, grids[i], positions[i, :, axis])
    found = closest_approach(resampled, float(len(times) - 1), backend)
    if not math.isfinite(found.time):
        return found
    k = min(int(found.time), len(times) - 2)
    t = times[k] + (found.time - k) * (times[k + 1] - times[k])
    return ClosestApproach(found.distance, found.agents, float(t))


__all__ = [
    "FINAL_TIMES",
    "at_duration",
    "check_final_time",
    "closest_across_horizons",
    "duration_derivatives",
    "joint_family",
    "solve_by_sequence",
    "solve_free_time",
    "solve_jointly",
    "solve_per_agent_time",
    "task_columns",
    "time_bounds",
]
