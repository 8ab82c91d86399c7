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

from ocpar.bsp.columns import LISTED, SHARED, STACKED, Columns, to_columns

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

    def solve_batch(self, params: np.ndarray, guesses: np.ndarray | Sequence[np.ndarray | None],
                    multipliers: np.ndarray | Sequence[np.ndarray | None]) -> Columns | None:
        """Solve k tasks at once: ``params`` (k, n_params), one guess and one multiplier
        vector per task (None: the defaults; an array (k, ...) when every task has one). The
        k solutions come as :class:`~ocpar.bsp.columns.Columns` of the transcription's
        solution class; each one's ``success`` is decided per task; None when this shape
        solves one task at a time (or the call failed)."""
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


def solve_tasks(tasks: Sequence[OcpTask] | Columns) -> list[InnerSolution] | Columns:
    """Batched, columnar engine kernel (:mod:`ocpar.bsp.kernel`): the solutions of ``tasks``,
    in order, as :func:`solve_task` would give them, but each shape's tasks first solved
    together by :meth:`BatchTranscription.solve_batch` (module docstring). Tasks given as
    :class:`~ocpar.bsp.columns.Columns` give Columns of solutions, a list gives a list. A
    task's solution does not depend on which other tasks share its chunk."""
    if isinstance(tasks, Columns):
        return _solve_columns(tasks)
    packed = to_columns(list(tasks))
    return _solve_columns(packed).items() if isinstance(packed, Columns) else []


#: Marks :func:`solve_tasks` as a batched kernel that takes and gives columns: the engine
#: calls it once per chunk, with the chunk as it arrived.
solve_tasks.batched = True  # type: ignore[attr-defined]
solve_tasks.columnar = True  # type: ignore[attr-defined]


def _solve_columns(tasks: Columns) -> Columns:
    kind, shapes = tasks.fields["shape"]
    if kind == SHARED:
        return _solve_shape(transcription(shapes), tasks)
    groups: dict[Shape, list[int]] = {}
    for index, shape in enumerate(tasks.column("shape")):
        groups.setdefault(shape, []).append(index)
    parts = [_solve_shape(transcription(shape), tasks.take(indices))
             for shape, indices in groups.items()]
    return _in_order(parts, [np.asarray(i) for i in groups.values()])


def _in_order(parts: list[Columns], positions: list[np.ndarray]) -> Columns:
    """``parts`` joined, row r of part k going to position ``positions[k][r]``."""
    if len(parts) == 1:
        return parts[0]
    order = np.concatenate(positions)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    return Columns.concat(parts).take(inverse)


def _solve_shape(nlp: Transcription[Any], tasks: Columns) -> Columns:
    """The solutions of ``tasks`` of one shape: the batchable ones in one batched call, the
    others and the batch's failures through the one-task policy."""
    chosen, params = _batchable(nlp, tasks)
    first = nlp.solve_batch(params, _rows(tasks, "warm_start", chosen),  # type: ignore
                            _rows(tasks, "multipliers", chosen)) if len(chosen) else None
    if first is None:
        chosen = good = np.zeros(0, dtype=np.intp)
    else:
        succeeded = np.asarray(first.column("success"), bool)
        good = chosen[succeeded]
    if len(good) == len(tasks):
        return first  # type: ignore[return-value]
    redo = np.setdiff1d(np.arange(len(tasks)), good)
    batched = set(chosen.tolist())
    again = [_apply_policy(nlp, task, np.asarray(task.params, float), attempts_before=1)
             if i in batched else solve_task(task)
             for i, task in zip(redo.tolist(), tasks.take(redo).items(), strict=True)]
    parts, positions = [to_columns(again)], [redo]
    if len(good):
        parts.insert(0, first.take(np.flatnonzero(succeeded)))  # type: ignore[union-attr]
        positions.insert(0, good)
    return _in_order(parts, positions)  # type: ignore[arg-type]


@lru_cache(maxsize=128)
def _batches(nlp: Transcription[Any]) -> bool:
    """Whether ``nlp`` (one of :func:`transcription`'s, cached as they are) is a
    :class:`BatchTranscription`: the protocol's structural check costs ~0.1 ms, once per
    chunk, 1–2 % of a small pursuit superstep."""
    return isinstance(nlp, BatchTranscription)


def _batchable(nlp: Transcription[Any], tasks: Columns) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``tasks`` (one shape) whose first attempt can join a batch, and their
    parameters (k, n_params): all, if the transcription batches and their numbers are
    finite; the others are left to :func:`solve_task`, which reports them."""
    none = np.zeros(0, dtype=np.intp), np.zeros((0, nlp.n_params))
    kind, params = tasks.fields["params"]
    if not _batches(nlp):
        return none
    if kind == SHARED:  # one task, or tasks sharing one array
        params = np.tile(np.ravel(params), (len(tasks), 1))
    elif kind == LISTED:  # e.g. taken from a chunk of several shapes
        if len({np.size(p) for p in params}) != 1:
            return none
        params = np.array([np.ravel(p) for p in params])
    params = np.asarray(params).reshape(len(tasks), -1)
    if params.shape[1] != nlp.n_params or not np.issubdtype(params.dtype, np.number):
        return none
    params = params.astype(float, copy=False)
    finite = np.all(np.isfinite(params), axis=1)
    kind, guesses = tasks.fields["warm_start"]
    if kind == STACKED and np.issubdtype(guesses.dtype, np.number):
        finite &= np.all(np.isfinite(guesses.reshape(len(tasks), -1)), axis=1)
    elif kind != SHARED or guesses is not None:
        finite &= [g is None or bool(np.all(np.isfinite(g))) for g in tasks.column("warm_start")]
    chosen = np.flatnonzero(finite)
    return chosen, params[chosen]


def _rows(tasks: Columns, name: str, rows: np.ndarray) -> np.ndarray | list[Any]:
    """Column ``name`` at ``rows``: an array (k, ...) where it is stacked, else a list."""
    kind, data = tasks.fields[name]
    if kind == SHARED:
        return [data] * len(rows)
    if kind == LISTED:
        return [data[i] for i in rows.tolist()]
    return data[rows]


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


@dataclass(frozen=True)
class PrepareTask:
    """What one worker is about to solve in batches: ``counts`` tasks of each shape
    (:func:`prepare_solvers`)."""

    counts: tuple[tuple[Shape, int], ...]


def prepare_solvers(task: PrepareTask) -> int:
    """Engine kernel: build this process's transcription of each shape of ``task`` and what
    solving its count of tasks in one batch takes (a transcription's ``prepare``, where it
    has one): the build a worker's first superstep would otherwise do, done once, apart from
    the solve. Returns this process's id."""
    for shape, count in task.counts:
        prepare = getattr(transcription(shape), "prepare", None)
        if prepare is not None:
            prepare(count)
    return os.getpid()


def cache_report(_task: object = None) -> dict:
    """Engine kernel for diagnostics: this process's id and its transcription-cache counters
    (``builds`` = transcriptions built, ``hits`` = reuses)."""
    info = transcription.cache_info()
    return {"pid": os.getpid(), "builds": info.misses, "hits": info.hits, "cached": info.currsize}
