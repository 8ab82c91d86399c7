"""Agents whose end position an outer problem chooses, as resident agents
(:mod:`ocpar.bsp.resident`): each agent's inner solution stays on the worker that computed
it, and a superstep moves only what the outer step needs (the formation's outer objective,
:class:`~ocpar.formation.hierarchical.OuterObjective`).

An agent's shape is any transcription with the agent-shape interface: a
:class:`~ocpar.ocp.DmocShape` (p = (q_0, q̇_0, q_N, q̇_N), 4 nq numbers) or a
:class:`~ocpar.ocp.ms_endpoint.MsEndpointShape` (an ODE model by multiple shooting,
p = (x_0, x̄_N)): p begins with the start and end states of ``boundary_size`` entries each,
the end's position entries are ``end_position_entries(d)``, a solution has ``cost_gradient``
dJ*/dp, ``end_hessian`` (the end state's block), the path ``q`` and controls ``u``, and
``previous_guesses(q, u)`` re-solves from them. An agent's first task (an
:class:`AgentTask`) carries its shape (shared by a chunk's agents) and its boundary data p;
later tasks only its end position (d numbers), the rest of p being fixed; where the shapes
take the duration T as their last parameter (``free_duration``), a task may set it
(``duration``, shared by a superstep's agents: the coordinator sends one number per T, and
:func:`duration_terms` gives the solutions' derivatives in T). Back comes an
:class:`AgentOutcome` (J*, dJ*/d(end position), the end Hessian's position block, success,
status, attempts: 1 + d + d² numbers and three small ones). The agent's :class:`AgentState` (its
:class:`~ocpar.ocp.DmocSolution`: paths, controls, multipliers; and its boundary data) stays
on its worker: the solution is the next solve's fallback start (the failure policy of
:func:`~ocpar.ocp.solve_tasks`), or, for a shape with ellipsoid obstacles
(:attr:`~ocpar.ocp.DmocShape.resolves_from_previous`), its first guess: the agent re-solves
from its previous path and side, the other side tried only where it can be cheaper
(:meth:`~ocpar.ocp.DmocTranscription.start_guesses`); gathered by the
coordinator once, at the end. The solves are
those of sending everything out and back each superstep, bit for bit.

In the transcription layer (not the formation's package) so that a worker that has imported
:mod:`ocpar.ocp` (the Dask workers' preload) unpickles these tasks without importing a
scheme.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ocpar.bsp.columns import LISTED, SHARED, STACKED, Columns, to_columns
from ocpar.bsp.kernel import run_chunk
from ocpar.ocp.contract import OcpTask, Shape
from ocpar.ocp.dmoc import DmocSolution

#: The engine kernel the agents' solves go through (so that the kernel hook
#: :data:`~ocpar.bsp.kernel.WRAPPER_VARIABLE` applies to them as to any superstep's).
INNER_KERNEL = "ocpar.ocp:solve_tasks"


@dataclass(frozen=True)
class AgentTask:
    """One agent's inner solve in a superstep: its ``shape`` (module docstring); on its
    first task its boundary data ``params`` p (n_params,) and ``end`` None, later ``params``
    None and ``end`` its end position (d,) (the rest of p is kept from the first task);
    ``positions`` d, the target's dimension; ``duration`` T (the model's time unit) set as
    the last parameter of a shape with ``free_duration`` (None: the one p has)."""

    shape: Shape
    params: np.ndarray | None
    end: np.ndarray | None
    positions: int
    duration: float | None


@dataclass
class AgentState(DmocSolution):
    """What stays on an agent's worker: its latest solution (a DMOC or multiple-shooting
    one: the same fields), its boundary data ``params`` (n_params,) of that solve and the
    solution's constraint ``multipliers`` where its transcription returns them (an ODE
    agent's: its next solve starts from them with its path; None for DMOC)."""

    params: np.ndarray
    multipliers: np.ndarray | None


@dataclass
class AgentOutcome:
    """What the outer step needs of one agent's solve: ``cost`` J* (NaN on failure),
    ``end_gradient`` dJ*/d(end position) (d,), ``end_hessian`` the position block of the
    end state's d²J* (d, d), ``success``, the solver's ``status`` and the failure policy's
    ``attempts``."""

    cost: float
    end_gradient: np.ndarray
    end_hessian: np.ndarray
    success: bool
    status: str
    attempts: int


def solve_agents(tasks: Columns, states: Columns | None) -> tuple[Columns, Columns]:
    """Resident kernel: the agents' solves from ``tasks`` (Columns of :class:`AgentTask`),
    each falling back to its previous solution (``states``: Columns of :class:`AgentState`;
    None on the first task: no fallback). Returns their :class:`AgentOutcome` and their new
    :class:`AgentState` (the new states)."""
    kinds = _kinds(tasks)
    if kinds is not None:   # DMOC and ODE agents: each kind on its own, joined in order
        parts = [solve_agents(tasks.take(rows), None if states is None else states.take(rows))
                 for rows in kinds]
        order = np.empty(len(tasks), np.intp)
        order[np.concatenate(kinds)] = np.arange(len(tasks))
        return tuple(Columns.concat([part[j] for part in parts]).take(order)  # type: ignore
                     for j in range(2))
    k = len(tasks)
    d = int(tasks.column("positions")[0])  # the curve's dimension: every agent's
    shape = _first_shape(tasks)   # a fleet's shapes of one kind share their layout
    entries = shape.end_position_entries(d)
    ends = shape.boundary_size + entries   # the end position's entries of p
    fallback: tuple[str, object] = (SHARED, None)
    warm: tuple[str, object] = (SHARED, None)
    multipliers: tuple[str, object] = (SHARED, None)
    if states is None:
        params = np.array(tasks.column("params"), float)
    else:
        previous = shape.previous_guesses(np.asarray(states.column("q")),
                                          np.asarray(states.column("u")))
        fallback = (STACKED, previous)
        params = np.array(states.column("params"), float)
        params[:, ends] = tasks.column("end")
        warm, fallback = _from_previous(tasks, previous, fallback)
        multipliers = _warm_multipliers(warm, states)
    duration = tasks.fields["duration"][1]   # shared by the superstep's agents
    if duration is not None:
        if not shape.free_duration:
            raise ValueError("a task's duration needs shapes with free_duration")
        params[:, -1] = duration
    inner = Columns(cls=OcpTask, length=k, fields={
        "shape": tasks.fields["shape"], "params": (STACKED, params),
        "warm_start": warm, "multipliers": multipliers, "fallback": fallback})
    solutions = to_columns(run_chunk(INNER_KERNEL, inner).results)
    assert isinstance(solutions, Columns)
    gradient = np.asarray(solutions.column("cost_gradient"))[:, ends]
    hessian = np.asarray(solutions.column("end_hessian"))[:, entries[:, None], entries]
    outcome = Columns(cls=AgentOutcome, length=k, fields={
        "cost": solutions.fields["cost"],
        "end_gradient": (STACKED, np.ascontiguousarray(gradient)),
        "end_hessian": (STACKED, np.ascontiguousarray(hessian)),
        "success": solutions.fields["success"],
        "status": solutions.fields["status"],
        "attempts": solutions.fields["attempts"],
    })
    states = Columns(cls=AgentState, length=k, fields={"multipliers": (SHARED, None)}
                     | solutions.fields | {"params": (STACKED, params)})
    return outcome, states


def duration_terms(tasks: Columns, states: Columns) -> tuple[np.ndarray, ...]:
    """dJ*/dT (k,), d²J*/dT² (k,) and d²J*/(d end position dT) (k, d) of the agents'
    solutions ``states`` (Columns of :class:`AgentState`) to ``tasks`` (Columns of
    :class:`AgentTask`), whose shapes take T as their last parameter: the last entry of
    ``cost_gradient`` (the envelope theorem) and the last column of ``end_hessian`` (the
    KKT system, :mod:`ocpar.ocp.sensitivity`); NaN for a failed solve."""
    k, d = len(tasks), int(tasks.column("positions")[0])
    slope, curvature, cross = np.empty(k), np.empty(k), np.empty((k, d))
    for rows in _kinds(tasks) or [np.arange(k)]:   # each kind its own end_hessian's size
        entries = _first_shape(tasks.take(rows)).end_position_entries(d)
        part = states.take(rows)
        hessian = np.asarray(part.column("end_hessian"), float)
        slope[rows] = np.asarray(part.column("cost_gradient"), float)[:, -1]
        curvature[rows] = hessian[:, -1, -1]
        cross[rows] = hessian[:, entries, -1]
    return slope, curvature, cross


def _kinds(tasks: Columns) -> list[np.ndarray] | None:
    """The rows of each kind of shape (class) among ``tasks``, in order of first use; None
    where there is one kind (the states of a fleet mixing them have paths of different
    sizes: Columns keep them as a list)."""
    kind, shapes = tasks.fields["shape"]
    if kind == SHARED:
        return None
    classes = [type(shape) for shape in shapes]
    if len(set(classes)) == 1:
        return None
    groups: dict[type, list[int]] = {}
    for row, cls in enumerate(classes):
        groups.setdefault(cls, []).append(row)
    return [np.asarray(rows) for rows in groups.values()]


def _first_shape(tasks: Columns) -> Shape:
    """The shape of the first of ``tasks`` (Columns of :class:`AgentTask`)."""
    kind, shapes = tasks.fields["shape"]
    return shapes if kind == SHARED else shapes[0]


def _from_previous(tasks: Columns, previous: np.ndarray, fallback: tuple[str, object]
                   ) -> tuple[tuple[str, object], tuple[str, object]]:
    """The inner tasks' ``warm_start`` and ``fallback`` columns: an agent whose shape
    :attr:`~ocpar.ocp.DmocShape.resolves_from_previous` (obstacles; every ODE agent) starts
    from its previous
    solution ``previous`` (k, nw) where that is finite (no fallback: it is that solution);
    the others from the default guess with ``previous`` as their fallback, as of old."""
    kind, shapes = tasks.fields["shape"]
    if kind == SHARED:
        resolves = np.full(len(tasks), shapes.resolves_from_previous)
    else:   # once per distinct shape (a fleet shares a few)
        flags: dict[int, bool] = {}
        resolves = np.fromiter((flags.setdefault(id(shape), shape.resolves_from_previous)
                                for shape in shapes), bool, count=len(tasks))
    if not resolves.any():
        return (SHARED, None), fallback
    warm = resolves & np.all(np.isfinite(previous), axis=1)
    if warm.all():
        return (STACKED, previous), (SHARED, None)
    return ((LISTED, [p if w else None for p, w in zip(previous, warm, strict=True)]),
            (LISTED, [None if w else p for p, w in zip(previous, warm, strict=True)]))


def _warm_multipliers(warm: tuple[str, object], states: Columns) -> tuple[str, object]:
    """The inner tasks' ``multipliers`` column: the previous solution's (``states``) where an
    agent starts from its previous solution (``warm``, :func:`_from_previous`), else None."""
    kind, guesses = warm
    if kind == SHARED:
        return SHARED, None
    multipliers = states.column("multipliers")
    if kind == STACKED and isinstance(multipliers, np.ndarray):
        return STACKED, multipliers
    return LISTED, [lam if guess is not None else None
                    for guess, lam in zip(guesses, multipliers, strict=True)]  # type: ignore


def agent_tasks(shapes: Shape | Sequence[Shape], positions: int,
                params: np.ndarray | None = None, end: np.ndarray | None = None,
                duration: float | None = None) -> Columns:
    """Columns of :class:`AgentTask`, one per agent: their first tasks given their boundary
    data ``params`` (n, n_params), later ones given their end positions ``end`` (n, d =
    ``positions``) instead. ``shapes``: one shape for all, or one per agent; ``duration``
    the common T of shapes with ``free_duration`` (None: p's)."""
    rows = params if params is not None else end
    if rows is None or (params is None) == (end is None):
        raise ValueError("agent_tasks needs either params or end")
    shape_column = ((LISTED, list(shapes)) if isinstance(shapes, tuple | list)
                    else (SHARED, shapes))
    return Columns(cls=AgentTask, length=len(rows), fields={
        "shape": shape_column,
        "params": (SHARED, None) if params is None else (STACKED, params),
        "end": (SHARED, None) if end is None else (STACKED, end),
        "positions": (SHARED, positions),
        "duration": (SHARED, None if duration is None else float(duration))})


__all__ = ["INNER_KERNEL", "AgentOutcome", "AgentState", "AgentTask", "agent_tasks",
           "duration_terms", "solve_agents"]
