"""The MACS scheme's Python API: :func:`solve_macs`."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.serial import SerialBackend
from ocpar.macs.algorithm import Macs, MacsOutcome, MacsSettings
from ocpar.macs.archive import Member
from ocpar.macs.local_search import STATIONARITY_TOL, search_settings
from ocpar.macs.metrics import (
    generational_distance,
    hypervolume,
    inverted_generational_distance,
    spacing,
)
from ocpar.macs.objectives import objective_functions
from ocpar.macs.problem import MacsProblem
from ocpar.macs.result import MacsResult
from ocpar.models.labels import control_labels, state_labels, time_unit
from ocpar.ocp import dfet_problem
from ocpar.ocp.solver_options import used


def resimulated_objectives(problem: MacsProblem, z: np.ndarray) -> np.ndarray:
    """J (m,) of a solution with its control law integrated accurately (not the DFET's own
    state estimate)."""
    return objective_functions(problem).resimulated(z)


def hypervolume_box(problem: MacsProblem, front: np.ndarray) -> np.ndarray | None:
    """The points whose ideal and nadir normalise the hypervolume: the problem's reference
    front, or else the final ``front`` itself (then the figure compares the iterations of one
    run, not runs); None if they have no extent in some objective."""
    box = problem.reference_front if problem.reference_front is not None else front
    return box if len(box) >= 2 and np.all(np.ptp(box, axis=0) > 0) else None


def refinement_fields(members: list[Member], evaluations: int, rounds: int = 0,
                      extra_evaluations: int = 0) -> dict:
    """The members' refinement outcome as :class:`MacsResult` fields (none if the
    refinement did not run): with its ``evaluations``, its ``rounds`` of checks and the
    evaluations of those after the first (``extra_evaluations``)."""
    if not members or members[0].stationarity is None:
        return {}
    return {"refined": np.array([mb.refined for mb in members]),
            "moved": np.array([mb.moved for mb in members]),
            "improvement": np.array([mb.improvement for mb in members]),
            "settled": np.array([mb.settled for mb in members]),
            "stationarity": np.array([mb.stationarity for mb in members]),
            "tradeoff": np.array([mb.tradeoff for mb in members]),
            "refinement_evaluations": evaluations, "refinement_rounds": rounds,
            "refinement_extra_evaluations": extra_evaluations}


def spread_fields(settings: MacsSettings, outcome: MacsOutcome,
                  front: np.ndarray) -> dict | None:
    """The final placement's outcome (None if it did not run: ``no_spread``, not two
    objectives, or fewer than two members): its evaluations, targets placed (of the
    ``archive_size`` − 2 inner ones) and the ``front``'s spacing
    (:func:`~ocpar.macs.metrics.spacing`)."""
    if settings.no_spread or front.shape[1] != 2 or len(front) < 2:
        return None
    return {"evaluations": outcome.spread_evaluations, "placed": outcome.spread_placed,
            "targets": settings.archive_size - 2, **spacing(front)}


def failure_message(outcome: MacsOutcome) -> str:
    """The status line of a run with no feasible archive member: how many searches failed
    (all of them) and the first one's IPOPT status."""
    return (f"no feasible archive member: all {outcome.failed_searches} searches failed "
            f"({outcome.evaluations} evaluations), the first {outcome.first_failure}")


def run_status(members: list[Member], outcome: MacsOutcome) -> tuple[str, str]:
    """The run's status and message: ``failed`` with no feasible member; ``converged`` only if
    every archive member is (settled, and Pareto-stationary within
    :data:`~ocpar.macs.local_search.STATIONARITY_TOL`, by the final refinement); else
    ``not_converged``, naming how many members are not (or that the refinement, which
    checks them, was skipped)."""
    if not members:
        return "failed", failure_message(outcome)
    if members[0].stationarity is None:
        return ("not_converged", "the final refinement was skipped (no_refine): no archive "
                "member's Pareto stationarity was checked")
    stationary = np.array([mb.stationarity for mb in members]) <= STATIONARITY_TOL
    converged = np.array([mb.settled for mb in members], bool) & stationary
    if converged.all():
        return "converged", ""
    late = np.flatnonzero(~converged)
    shown = ", ".join(str(i) for i in late[:10]) + (", ..." if len(late) > 10 else "")
    return ("not_converged",
            f"{len(late)} of {len(members)} archive members not converged (not settled, or "
            f"Pareto-stationarity residual above {STATIONARITY_TOL:g}): members {shown}")


def solve_macs(
    problem: MacsProblem,
    settings: MacsSettings | None = None,
    backend: Backend | None = None,
    progress: Callable[[str], None] | None = None,
) -> MacsResult:
    """Run MACSoc on ``problem`` until ``settings.max_evaluations`` objective evaluations.

    ``progress`` gets one line per iteration (evaluations, archive size and, with a reference
    front, the hypervolume of the archive's transcribed objectives). GD and IGD are computed
    only against the problem's reference front (None without one).
    """
    settings = settings or MacsSettings()
    backend = backend or SerialBackend()
    reference = problem.reference_front
    first_trace = len(backend.traces)
    start = time.perf_counter()
    macs = Macs(problem, settings, backend, progress,
                indicator=None if reference is None else lambda f: hypervolume(f, reference))
    outcome = macs.run()
    wall = time.perf_counter() - start
    m = problem.n_objectives
    members = sorted(outcome.archive.members, key=lambda member: member.objectives[0])
    # the front as returned: each member's objectives re-simulated from its controls
    front = np.array([resimulated_objectives(problem, mb.z) for mb in members]).reshape(-1, m)
    checked = time.perf_counter() - start - wall
    box = hypervolume_box(problem, front)
    history = [dict(entry, hv=hypervolume(f, box) if box is not None and len(f) else None)
               for entry, f in zip(outcome.history, outcome.fronts, strict=True)]
    known = reference is not None and len(front) > 0
    dfet = dfet_problem(problem.shape)
    status, message = run_status(members, outcome)
    transcribed = np.array([mb.objectives for mb in members]).reshape(-1, m)
    return MacsResult(
        problem=problem.name,
        seed=settings.seed,
        backend=backend.name,
        workers=backend.workers,
        status=status,
        message=message,
        front=front,
        front_transcribed=transcribed,
        decisions=np.array([mb.z[dfet.decision_slice] for mb in members]).reshape(
            -1, dfet.nz - dfet.decision_slice.start),
        states=np.array([dfet.state_nodes_of(mb.z) for mb in members]).reshape(
            -1, dfet.n, problem.shape.order + 1, dfet.nx),
        state_fractions=(np.arange(dfet.n)[:, None] + (dfet.state_nodes + 1) / 2) / dfet.n,
        control_fractions=((np.arange(dfet.n)[:, None] + (dfet.control_nodes + 1) / 2)
                           / dfet.n).ravel(),
        time_unit=time_unit(problem.model),
        states_labels=state_labels(problem.model, dfet.nx),
        controls_labels=control_labels(problem.model, dfet.nu),
        objective_units=problem.objective_units,
        evaluations=outcome.evaluations,
        iterations=outcome.iterations,
        failed_searches=outcome.failed_searches,
        gd=generational_distance(front, reference, interpolate=m == 2) if known else None,
        igd=inverted_generational_distance(front, reference) if known else None,
        hv=hypervolume(front, box) if box is not None else None,
        wall_time_s=wall,
        timings={"verification_s": checked},
        settings=asdict(settings),
        objective_names=problem.objective_names,
        reference_front=reference,
        history=history,
        **refinement_fields(members, outcome.refinement_evaluations, outcome.refinement_rounds,
                            outcome.refinement_extra_evaluations),
        spread=spread_fields(settings, outcome, transcribed),
        trace=backend.traces[first_trace:],
        solver_options=used(macs.solver_options, {
            kind: {"ipopt": value}
            for kind, value in search_settings(macs.solver_options).items()}),
    )
