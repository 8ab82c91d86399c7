"""The inner-problem contract every transcription implements, and the one engine kernel.

A *shape* is a frozen, hashable dataclass holding everything that fixes an NLP's structure
(model, grid, solver options); its :meth:`Shape.build` makes the :class:`Transcription`, and
:func:`transcription` caches that once per shape per process. A task (:class:`OcpTask`)
is a shape plus numbers only: the parameter vector p (boundary data) and the guesses to try,
as arrays. :func:`solve_task` is the engine kernel of every transcription: it applies the
failure policy and returns an :class:`InnerSolution` (a subclass with the transcription's
payload), never raising on a solver failure. :func:`solve_tasks` is its batched form, the
kernel the schemes use: one call of the transcription's :meth:`BatchTranscription.solve_batch`
for a chunk's first attempts, the policy one task at a time for those that fail.

The failure policy: try the task's ``warm_start`` (with ``multipliers``; the transcription's
:meth:`Transcription.default_guess` if None), then the task's ``fallback``, then the
transcription's :meth:`Transcription.fallback_guesses`, until one succeeds; ``attempts``
counts the tries. A guess with non-finite entries is a failed attempt (status
:data:`INVALID_GUESS`) without calling the solver; non-finite parameters fail the task at
once (status :data:`INVALID_PARAMS`, one attempt). In :func:`solve_tasks` the batched
attempt from the task's first guess comes first and counts as an attempt; a task whose
batched attempt fails goes through the whole policy above (from its first guess again, with
the transcription's one-task solver, e.g. IPOPT).
"""

from __future__ import annotations

import os
import time
from collections.abc import Hashable, Iterator, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np

#: Status of an attempt from a guess that is not finite (no solver call).
INVALID_GUESS = "Invalid_Guess"
#: Status of a task whose parameters are not finite (no solver call).
INVALID_PARAMS = "Invalid_Parameters"


@dataclass
class InnerSolution:
    """Fields every transcription's solution has: optimal ``cost`` J* (NaN on failure), the
    solver's ``status``, ``success``, solver ``iterations``, ``attempts`` made by the failure
    policy (1 if the first guess succeeded) and ``solve_time_s`` of the last attempt (s)."""

    cost: float
    status: str
    success: bool
    iterations: int
    attempts: int
    solve_time_s: float


S = TypeVar("S", bound=InnerSolution)


@dataclass
class NlpCall:
    """One call of a CasADi ``nlpsol`` solver (:func:`call_nlpsol`): its outputs ``out``
    (None if CasADi raised, e.g. on NaN in the model), ``status``, ``success``,
    ``iterations`` and wall time ``solve_time_s`` (s)."""

    out: dict[str, Any] | None
    status: str
    success: bool
    iterations: int
    solve_time_s: float

    @property
    def common(self) -> dict[str, Any]:
        """The :class:`InnerSolution` fields of a solve that returned (one attempt)."""
        assert self.out is not None
        return {"cost": float(self.out["f"]), "status": self.status, "success": self.success,
                "iterations": self.iterations, "attempts": 1,
                "solve_time_s": self.solve_time_s}

    @property
    def cost_gradient(self) -> np.ndarray:
        """dJ*/dp from the parameters' multiplier (CasADi's lam_p is −dJ*/dp; checked against
        finite differences in the tests)."""
        assert self.out is not None
        return -np.asarray(self.out["lam_p"]).ravel()


def call_nlpsol(solver: Any, **arguments: Any) -> NlpCall:
    """Call ``solver(**arguments)`` and time it; an evaluation error becomes a failed call with
    status ``error: ...`` (first line of CasADi's message), never an exception."""
    start = time.perf_counter()
    try:
        out = solver(**arguments)
    except RuntimeError as exc:
        return NlpCall(None, f"error: {exc}".splitlines()[0], False, 0,
                       time.perf_counter() - start)
    elapsed = time.perf_counter() - start
    stats = solver.stats()
    return NlpCall(out, str(stats["return_status"]), bool(stats["success"]),
                   int(stats["iter_count"]), elapsed)


@runtime_checkable
class Transcription(Protocol[S]):
    """A parametric NLP of one shape, built once and solved many times.

    ``n_params`` is the length of p; a guess is a vector of the NLP's variables (see each
    transcription); ``multipliers`` are constraint multipliers λ_g of a neighbouring solve.
    """

    @property
    def n_params(self) -> int: ...

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> S:
        """Solve for parameters p from ``guess`` (default: :meth:`default_guess`); a failed
        solve is returned (``success`` False, its status), never raised."""
        ...

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> S:
        """A failed solution for p with ``status``: NaN cost and payload."""
        ...

    def default_guess(self, params: np.ndarray) -> np.ndarray:
        """The first guess when a task brings none."""
        ...

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """Guesses to try after the task's own (possibly none), made lazily."""
        ...

    def warm_start(self, solution: S) -> np.ndarray:
        """The guess that re-solves from ``solution``."""
        ...


@runtime_checkable
class BatchTranscription(Transcription[S], Protocol[S]):
    """A transcription that can also solve many tasks of its shape in one call."""

    def solve_batch(self, params: np.ndarray, guesses: list[np.ndarray | None],
                    multipliers: list[np.ndarray | None]) -> list[S] | None:
        """Solve k tasks at once: ``params`` (k, n_params), one guess and one multiplier
        vector per task (None: the defaults). Each solution's ``success`` is decided per
        task; None when this shape solves one task at a time (or the call failed)."""
        ...


class Shape(Hashable, Protocol):
    """A frozen, hashable dataclass fixing an NLP's structure (the solver-cache key)."""

    def build(self) -> Transcription[Any]:
        """Build the transcription of this shape (costly: done once per process)."""
        ...


@dataclass(frozen=True)
class OcpTask:
    """One inner solve: ``shape`` and numbers only. ``params`` p (n_params,); ``warm_start``
    the first guess (None: the transcription's default) with optional constraint
    ``multipliers``; ``fallback`` a second guess if the first attempt fails. Optional arrays,
    not a tuple of them, so that a batch packs into one stacked array per field
    (:mod:`ocpar.bsp.columns`)."""

    shape: Shape
    params: np.ndarray
    warm_start: np.ndarray | None = None
    multipliers: np.ndarray | None = None
    fallback: np.ndarray | None = None


@lru_cache(maxsize=128)
def transcription(shape: Shape) -> Transcription[Any]:
    """The process-wide transcription of ``shape``: built once, then reused."""
    return shape.build()


def check_params(params: np.ndarray, n_params: int, name: str) -> np.ndarray:
    """p as a float vector of length ``n_params``; ValueError naming the transcription
    otherwise."""
    params = np.asarray(params, float)
    if params.shape != (n_params,):
        raise ValueError(f"{name} params must have length {n_params}, got shape {params.shape}")
    return params


def _guesses(nlp: Transcription[Any], task: OcpTask, params: np.ndarray
             ) -> Iterator[tuple[np.ndarray | None, np.ndarray | None]]:
    yield task.warm_start, task.multipliers
    if task.fallback is not None:
        yield task.fallback, None
    for guess in nlp.fallback_guesses(params):
        yield guess, None


def solve_task(task: OcpTask) -> InnerSolution:
    """Engine kernel of every transcription: solve ``task`` with this process's cached
    transcription of ``task.shape`` under the failure policy (module docstring)."""
    nlp = transcription(task.shape)
    params = check_params(task.params, nlp.n_params, type(nlp).__name__)
    if not np.all(np.isfinite(params)):
        return nlp.failure(params, INVALID_PARAMS, 0.0)
    return _apply_policy(nlp, task, params, attempts_before=0)


def solve_tasks(tasks: Sequence[OcpTask]) -> list[InnerSolution]:
    """Batched engine kernel (:mod:`ocpar.bsp.kernel`): the solutions of ``tasks``, in order,
    as :func:`solve_task` would give them, but each shape's tasks first solved together by
    :meth:`BatchTranscription.solve_batch` (module docstring). A task's solution does not
    depend on which other tasks share its chunk."""
    solutions: list[InnerSolution | None] = [None] * len(tasks)
    by_shape: dict[Shape, list[int]] = {}
    for index, task in enumerate(tasks):
        by_shape.setdefault(task.shape, []).append(index)
    for shape, indices in by_shape.items():
        nlp = transcription(shape)
        batch, params = _batchable(nlp, [tasks[i] for i in indices])
        batch = [indices[k] for k in batch]
        first = nlp.solve_batch(params, [tasks[i].warm_start for i in batch],  # type: ignore
                                [tasks[i].multipliers for i in batch]) if batch else None
        for i, solution in zip(batch if first is not None else [], first or [], strict=True):
            solutions[i] = solution
        for i in indices:
            solution = solutions[i]
            if solution is None:
                solutions[i] = solve_task(tasks[i])
            elif not solution.success:
                params = np.asarray(tasks[i].params, float)
                solutions[i] = _apply_policy(nlp, tasks[i], params, attempts_before=1)
    return solutions  # type: ignore[return-value]


#: Marks :func:`solve_tasks` as a batched kernel: the engine calls it once per chunk.
solve_tasks.batched = True  # type: ignore[attr-defined]


def _batchable(nlp: Transcription[Any], tasks: list[OcpTask]) -> tuple[list[int], np.ndarray]:
    """The positions of the ``tasks`` (one shape) whose first attempt can join a batch, and
    their parameters (k, n_params): all, if the transcription batches and their numbers are
    finite; the others are left to :func:`solve_task`, which reports them."""
    if not isinstance(nlp, BatchTranscription):
        return [], np.zeros((0, nlp.n_params))
    params = np.array([np.asarray(t.params, float).ravel() for t in tasks]
                      if len({np.size(t.params) for t in tasks}) == 1 else [])
    if params.shape != (len(tasks), nlp.n_params):
        return [], np.zeros((0, nlp.n_params))
    finite = np.all(np.isfinite(params), axis=1)
    finite &= [t.warm_start is None or bool(np.all(np.isfinite(t.warm_start))) for t in tasks]
    chosen = np.flatnonzero(finite)
    return chosen.tolist(), params[chosen]


def _apply_policy(nlp: Transcription[Any], task: OcpTask, params: np.ndarray,
                  attempts_before: int) -> InnerSolution:
    """The failure policy for ``task`` after ``attempts_before`` failed attempts."""
    solution = None
    for attempt, (guess, multipliers) in enumerate(_guesses(nlp, task, params),
                                                   start=attempts_before + 1):
        if guess is not None and not np.all(np.isfinite(guess)):
            solution = nlp.failure(params, INVALID_GUESS, 0.0)
        else:
            solution = nlp.solve(params, guess, multipliers)
        solution.attempts = attempt
        if solution.success:
            break
    return solution


def cache_report(_task: object = None) -> dict:
    """Engine kernel for diagnostics: this process's id and its transcription-cache counters
    (``builds`` = transcriptions built, ``hits`` = reuses)."""
    info = transcription.cache_info()
    return {"pid": os.getpid(), "builds": info.misses, "hits": info.hits, "cached": info.currsize}
