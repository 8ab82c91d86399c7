"""The MACS scheme's Python API: :func:`solve_macs`."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.serial import SerialBackend
from ocpar.macs.algorithm import Macs, MacsSettings
from ocpar.macs.metrics import generational_distance, hypervolume, inverted_generational_distance
from ocpar.macs.problems import MacsProblem
from ocpar.macs.reference import reference_front
from ocpar.macs.result import MacsResult
from ocpar.ocp import dfet_problem


def resimulated_objectives(problem: MacsProblem, z: np.ndarray) -> np.ndarray:
    """(J1, J2) of a solution with its control law integrated accurately (not the DFET's own
    state estimate)."""
    dfet = dfet_problem(problem.shape)
    return np.array(problem.objectives(dfet.simulate(z), float(dfet.final_time(z))), float)


def solve_macs(
    problem: MacsProblem,
    settings: MacsSettings | None = None,
    backend: Backend | None = None,
    progress: Callable[[str], None] | None = None,
) -> MacsResult:
    """Run MACSoc on ``problem`` until ``settings.max_evaluations`` objective evaluations.

    ``progress`` gets one line per iteration (evaluations, archive size, hypervolume of the
    archive's transcribed objectives against the reference front).
    """
    settings = settings or MacsSettings()
    backend = backend or SerialBackend()
    reference = reference_front(problem.name)
    first_trace = len(backend.traces)
    start = time.perf_counter()
    macs = Macs(problem, settings, backend, progress,
                indicator=lambda front: hypervolume(front, reference))
    outcome = macs.run()
    wall = time.perf_counter() - start
    members = sorted(outcome.archive.members, key=lambda m: m.objectives[0])
    front = np.array([resimulated_objectives(problem, m.z) for m in members]).reshape(-1, 2)
    dfet = dfet_problem(problem.shape)
    return MacsResult(
        problem=problem.name,
        seed=settings.seed,
        backend=backend.name,
        workers=backend.workers,
        status="converged" if len(front) else "failed",
        message="" if len(front) else "no feasible archive member",
        front=front,
        front_transcribed=np.array([m.objectives for m in members]).reshape(-1, 2),
        decisions=np.array([m.z[dfet.decision_slice] for m in members]),
        evaluations=outcome.evaluations,
        iterations=outcome.iterations,
        failed_searches=outcome.failed_searches,
        gd=generational_distance(front, reference) if len(front) else float("nan"),
        igd=inverted_generational_distance(front, reference) if len(front) else float("nan"),
        hv=hypervolume(front, reference) if len(front) else 0.0,
        wall_time_s=wall,
        settings=asdict(settings),
        history=outcome.history,
        trace=backend.traces[first_trace:],
    )
