"""A free final time through the inner-problem contract: the sums an outer problem needs of
its agents' J*(T) and their derivatives in T, reduced on the workers over fixed units.

A transcription offers a free duration when T is the last entry of its parameters p
(``DmocShape.free_duration``, ``MsEndpointShape.free_duration``); its solution's
``cost_gradient`` then ends with dJ*/dT (the parameters' multiplier, the envelope theorem)
and its ``end_hessian`` is the block of d²J*/dp² over (the end position's entries, T), T's
row and column last (from the KKT system,
:mod:`ocpar.ocp.sensitivity`). Any transcription that meets this serves :func:`duration_sums`.

The engine kernel :func:`duration_sums` solves one unit of agents (one :class:`DurationUnit`:
columns of :class:`~ocpar.ocp.OcpTask` with T in p) and returns their sums in agent order;
the coordinator adds the units' sums in unit order: the numbers do not depend on which
worker solved which unit, nor on how many workers there are.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from ocpar.bsp.columns import Columns
from ocpar.ocp.contract import solve_tasks, transcription

#: a shape dataclass with the fields ``duration`` (T) and ``free_duration``
S = TypeVar("S")
#: its transcription
T = TypeVar("T")


@dataclass(frozen=True)
class DurationUnit:
    """One unit of agents' inner solves: ``tasks`` (Columns of
    :class:`~ocpar.ocp.OcpTask`, T the last parameter of each)."""

    tasks: Columns


@dataclass
class DurationSums:
    """Sums over a unit (or, added, over all agents) of J* (``cost``), dJ*/dT
    (``gradient``, cost unit per time unit) and d²J*/dT² (``curvature``); ``solves`` made,
    ``failed`` of them (their terms are left out, the sums then no answer), and the first
    failure's solver status (``first_failure``, "" if none)."""

    cost: float
    gradient: float
    curvature: float
    solves: int
    failed: int
    first_failure: str = ""

    def __add__(self, other: DurationSums) -> DurationSums:
        return DurationSums(self.cost + other.cost, self.gradient + other.gradient,
                            self.curvature + other.curvature, self.solves + other.solves,
                            self.failed + other.failed,
                            self.first_failure or other.first_failure)


def check_time_fields(free_duration: bool, time_bounds: object, time_weight: float
                      ) -> tuple[float, float] | None:
    """A shape's ``time_bounds`` as (T_min, T_max) (0 < T_min ≤ T_max < ∞), None where none
    are given, after checking ``time_weight`` (finite, ≥ 0, only with bounds) and that T is
    not both a parameter (``free_duration``) and a variable; ValueError naming the field."""
    if not (math.isfinite(time_weight) and time_weight >= 0):
        raise ValueError(f"time_weight: must be a finite number >= 0, got {time_weight!r}")
    if time_bounds is None:
        if time_weight:
            raise ValueError("time_weight: needs time_bounds (T a variable of the task)")
        return None
    try:
        low, high = (float(b) for b in time_bounds)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError("time_bounds: must be (T_min, T_max)") from None
    if not 0 < low <= high < math.inf:
        raise ValueError(f"time_bounds: needs 0 < T_min <= T_max < inf, got {time_bounds}")
    if free_duration:
        raise ValueError("time_bounds: not with free_duration (T a variable of the task, or "
                         "its parameter)")
    return low, high


def over_duration(shape: S, duration: float) -> S:
    """``shape`` over the horizon ``duration`` (the model's time unit)."""
    return dataclasses.replace(shape, duration=float(duration))  # type: ignore[type-var]


def build_at_unit_duration(shape: Any, transcribe: Callable[[Any], T]) -> T:
    """``transcribe(shape)``; with a free duration (T a parameter) the process-wide
    transcription of ``shape`` at ``duration`` 1, which serves every T
    (:func:`~ocpar.ocp.transcription`)."""
    if shape.free_duration and shape.duration != 1.0:
        return transcription(over_duration(shape, 1.0))  # type: ignore[return-value]
    return transcribe(shape)


def duration_sums(unit: DurationUnit) -> DurationSums:
    """Engine kernel: solve ``unit``'s tasks (:func:`~ocpar.ocp.solve_tasks`) and sum their
    J*, dJ*/dT and d²J*/dT² in task order (module docstring)."""
    solutions = solve_tasks(unit.tasks)
    assert isinstance(solutions, Columns)
    ok = np.asarray(solutions.column("success"), bool)
    cost = np.asarray(solutions.column("cost"), float)[ok]
    gradient = np.asarray(solutions.column("cost_gradient"), float)[ok, -1]
    curvature = np.asarray(solutions.column("end_hessian"), float)[ok, -1, -1]
    statuses = solutions.column("status")
    first = next((str(statuses[i]) for i in np.flatnonzero(~ok).tolist()), "")
    return DurationSums(float(np.sum(cost)), float(np.sum(gradient)),
                        float(np.sum(curvature)), len(ok), int(np.sum(~ok)), first)


__all__ = ["DurationSums", "DurationUnit", "build_at_unit_duration", "check_time_fields",
           "duration_sums", "over_duration"]
