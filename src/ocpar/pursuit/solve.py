"""The pursuit scheme's Python API: :func:`solve_pursuit`."""

from __future__ import annotations

import time
from collections.abc import Callable

from ocpar.bsp import Backend
from ocpar.bsp.serial import SerialBackend
from ocpar.models.labels import control_labels, state_labels, time_unit
from ocpar.ocp import MsSolution, solve_task
from ocpar.ocp.solver_options import solver_options, used
from ocpar.pursuit.problem import PursuitProblem
from ocpar.pursuit.result import PursuitResult
from ocpar.pursuit.slp import (
    FEASIBILITY_TOL,
    PursuitSettings,
    full_horizon_shape,
    full_horizon_task,
    run_levels,
    window_shape,
)
from ocpar.pursuit.validate import discrete_residual, rk_check

MODES = ("pbms", "ms")
#: Largest N for which a PBMS run also solves the full-horizon MS problem for comparison.
REFERENCE_MAX_SAMPLES = 1001


def check_mode(problem: PursuitProblem, mode: str, settings: PursuitSettings) -> None:
    """ValueError unless ``mode`` is one of :data:`MODES` and applies to ``problem``: the train
    (``pbms``) is the paper's sampled local pursuit, whose agents leave Δ apart and intercept
    each other on one clock over a fixed horizon (its window and update ``settings`` checked
    against N); a free final time is solved by ``ms``, which has no window."""
    if mode not in MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {', '.join(MODES)}")
    if mode == "pbms" and problem.free_time:
        raise ValueError("mode pbms: the pursuit train needs a fixed final time (its agents "
                         "intercept each other on one clock); solve a free final time with "
                         "mode ms (--mode ms)")
    if mode == "pbms":
        settings.check(problem.samples)


def solve_full_horizon(problem: PursuitProblem, backend: Backend,
                       settings: PursuitSettings | None = None) -> MsSolution:
    """Plain multiple shooting over [0, T] with N samples, from agent 0's trajectory, as one
    task on the backend (with the ``settings``' solver options)."""
    task = full_horizon_task(problem, *problem.feasible_trajectory(),
                             options=None if settings is None else settings.solver_options)
    return backend.superstep(solve_task, [task])[0]


def solve_pursuit(
    problem: PursuitProblem,
    settings: PursuitSettings | None = None,
    backend: Backend | None = None,
    mode: str = "pbms",
    reference: bool = True,
    progress: Callable[[str], None] | None = None,
) -> PursuitResult:
    """Solve ``problem`` by pursuit-based multiple shooting (``mode="pbms"``) or by plain
    multiple shooting over the whole horizon (``mode="ms"``).

    With ``reference`` (and N ≤ 1001) a PBMS run also solves the full-horizon MS problem
    afterwards, for comparison. ``progress`` gets one line per superstep. The returned
    trajectory is checked as returned: a run is converged only if it meets the dynamics, the
    target set and the path constraints to :data:`~ocpar.pursuit.slp.FEASIBILITY_TOL`. A
    free final time takes ``mode="ms"`` (:func:`check_mode`); the result's ``time`` is then
    the found T's grid.
    """
    settings = settings or PursuitSettings()
    check_mode(problem, mode, settings)
    backend = backend or SerialBackend()
    first_trace = len(backend.traces)
    start = time.perf_counter()
    initial_x, _ = problem.feasible_trajectory()
    reference_headline, reference_x = None, None

    if mode == "ms":
        sol = solve_full_horizon(problem, backend, settings)
        x, u = sol.x, sol.u
        # a fixed horizon is the problem's (N·h may differ from it in the last bit)
        final_time = sol.final_time if problem.free_time else problem.duration
        status = "converged" if sol.success else "failed"
        message, agents, solves = sol.status, 0, 1
        failed, in_flight, headlines = int(not sol.success), 1, []
        retries = sol.attempts - 1
        stop_reason, remaining, agents_per_level = None, None, []
        remaining_method, certificate, train = None, None, {}
    else:
        outcome = run_levels(problem, settings, backend, progress)
        x, u, final_time = outcome.x, outcome.u, problem.duration
        status = "converged" if outcome.converged else "not_converged"
        message, agents = outcome.message, sum(outcome.agents_per_level)
        solves = outcome.subproblem_solves
        failed, in_flight, headlines = (outcome.failed_solves, outcome.max_in_flight,
                                        outcome.headlines)
        retries = outcome.retries
        stop_reason, remaining = outcome.stop_reason, outcome.remaining
        remaining_method = outcome.remaining_method
        certificate = None if outcome.certificate is None else outcome.certificate.headline
        agents_per_level = outcome.agents_per_level
        train = {"result_source": outcome.result_source,
                 "train_headline": outcome.train_headline,
                 "train_cost": problem.cost(outcome.best.x, outcome.best.u),
                 "train_remaining": outcome.train_remaining,
                 "train_remaining_method": outcome.train_remaining_method,
                 "windows": outcome.windows, "window": settings.window,
                 "update": settings.update, "epsilon": settings.epsilon,
                 "levels": settings.levels}
    trace = backend.traces[first_trace:]
    wall = time.perf_counter() - start
    timings = {}
    if mode == "pbms" and reference and problem.samples <= REFERENCE_MAX_SAMPLES:
        ref = solve_full_horizon(problem, backend, settings)
        if ref.success:
            reference_headline, reference_x = problem.headline_value(ref.x, ref.u), ref.x
        timings["reference_s"] = time.perf_counter() - start - wall
    checking = time.perf_counter()
    check = rk_check(problem, u, final_time)
    violation = discrete_residual(problem, x, u, final_time)
    timings["verification_s"] = time.perf_counter() - checking
    if status == "converged" and not violation <= FEASIBILITY_TOL:
        status = "not_converged"
        message += (f"; the returned trajectory breaks the dynamics, target set or path "
                    f"constraints by {violation:.2e} > {FEASIBILITY_TOL:g}")
    if failed and mode == "pbms":
        failures = (f"{failed} of {solves} subproblem solves failed, the first "
                    f"{outcome.failures[0]}")
        # the status line leads with them when the run did not converge
        message = (f"{message}; {failures}" if status == "converged"
                   else f"{failures}; {message}")
    return PursuitResult(
        problem=problem.name, samples=problem.samples, mode=mode,
        backend=backend.name, workers=backend.workers, status=status, message=message,
        headline_key=problem.headline_key, headline_name=problem.headline_name,
        headline_unit=problem.headline_unit,
        headline=problem.headline_value(x, u, final_time),
        cost_key=problem.cost_key, cost=problem.cost(x, u, final_time),
        agents=agents, subproblem_solves=solves, failed_solves=failed, retries=retries,
        max_agents_in_flight=in_flight,
        constraint_violation=violation,
        rk_terminal_error=check.terminal_error, rk_checks=check.values,
        wall_time_s=wall, timings=timings, x=x, u=u, initial_x=initial_x,
        headlines=headlines,
        time=problem.times(final_time), time_unit=time_unit(problem.model),
        final_time=final_time, free_final_time=problem.free_time, plan_time=problem.grid,
        states=state_labels(problem.model, problem.model.nx),
        controls=control_labels(problem.model, problem.model.nu),
        reference_headline=reference_headline, reference_x=reference_x, trace=trace,
        stop_reason=stop_reason, estimated_remaining=remaining,
        remaining_method=remaining_method, certificate_headline=certificate,
        agents_per_level=agents_per_level, **train,
        solver_options=solver_record(problem, settings, mode),
    )


def solver_record(problem: PursuitProblem, settings: PursuitSettings, mode: str) -> dict:
    """result.json's ``solver_options``: the run's, and the options the agents' subproblems
    (``window``, PBMS: N_Δ samples) and the full-horizon MS NLP (``full_horizon``) are built
    with (:func:`ocpar.ocp.solver_options.used`)."""
    settings_by_nlp = {"full_horizon": full_horizon_shape(
        problem, settings.solver_options).solver_settings()}
    if mode == "pbms":
        settings_by_nlp = {"window": window_shape(problem, settings, settings.window - 1)
                           .solver_settings()} | settings_by_nlp
    return used(solver_options(settings.solver_options), settings_by_nlp)
