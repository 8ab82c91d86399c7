"""A formation run's answer, finished where its paths are: each worker checks its own agents
and, on a large run, writes their part of the array file itself.

Once the outer solver has its φ, the agents' solutions (paths, controls) are on the workers
(:mod:`ocpar.ocp.endpoint_agents`). :func:`finish` applies :func:`finish_agents` to them
there (:meth:`ocpar.bsp.ResidentSet.apply`: not a superstep of the solve): each worker

* checks its agents' own paths (:func:`~ocpar.formation.verify.agent_checks`: start,
  attitude, boundary momentum, interior dynamics, control bounds, path constraints),
* on a run that writes its agents in parts (:func:`writes_parts`), writes their variables of
  the array file (:func:`~ocpar.formation.result.agent_arrays`) as ``result.agents-K.nc``
  (K its first agent) into the run's output directory, which :func:`ocpar.load` joins;
  otherwise it sends them (paths, controls, solver status) back,
* and sends back, per agent, what the checks of the formation as a whole need: the
  positions on the nodes (the closest approach, searched interval by interval on the workers
  again, and the obstacles), the end point (the target and the coupling), the cost and the
  control groups' cost parts.

So the coordinator gathers neither a path's controls nor its multipliers and writes no
agent's variables on a run in parts; the verdicts are those of
:func:`~ocpar.formation.verify.verify_formation` on the gathered paths (the same functions on
each agent's own numbers).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import LISTED, SHARED, STACKED, Columns
from ocpar.bsp.resident import ResidentSet
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import AgentRecords, Units, agent_arrays
from ocpar.formation.verify import AgentChecks, agent_checks
from ocpar.models.labels import model_name
from ocpar.ocp.contract import Shape

#: A run writes its agents' variables in parts from this many agents on (with more than one
#: worker, where they share the output directory's file system): below, the coordinator
#: gathers them and writes one file (13 MB at 50,000 point masses: one download).
PARTS_MIN_AGENTS = 50_000
#: The name of the part of the array file that starts at agent K.
PART_NAME = "result.agents-{first:0{width}d}.nc"


@dataclass(frozen=True)
class FinishTask:
    """One agent's finish: its ``shape``, index ``agent`` and returned parameters ``phi``;
    shared by all agents: the position entries ``positions`` and target dimension ``dim``,
    the horizon ``duration``, whether the target is a circle (``on_circle``, the units of
    φ), the fleet's ``model_names``, the control groups ``cost_groups`` (name → columns)
    whose cost parts the run reports, and ``directory`` the part file goes to (None: sent
    back instead) with its name's digit ``width``, and the fleet's names and ``units``
    (:class:`~ocpar.formation.result.Units`)."""

    shape: Shape
    agent: int
    phi: np.ndarray
    positions: tuple[int, ...]
    dim: int
    duration: float
    on_circle: bool
    model_names: tuple[str, ...]
    cost_groups: dict
    directory: str | None
    width: int
    units: Units


@dataclass
class AgentFinish:
    """What an agent's finish sends back: its own checks' residuals (``start``, ``attitude``
    (NaN without attitude entries), ``momentum``, ``dynamics``, ``bounds`` (NaN without
    control bounds), ``path`` (one per path constraint of its shape), ``violation``), its
    ``positions`` (N+1, p) and ``end`` (d,), its ``cost`` and ``cost_parts`` (h Σ|u|² per
    control group, before the factor h); and, where its worker wrote no part, its paths
    ``q``, controls ``u``, solver ``status`` and ``iterations`` (None where written); its
    horizon ``duration`` T (the model's time unit: the one it chose where T is its own)."""

    start: float
    attitude: float
    momentum: float
    dynamics: float
    bounds: float
    path: np.ndarray
    violation: float
    positions: np.ndarray
    end: np.ndarray
    cost: float
    cost_parts: np.ndarray
    q: np.ndarray | None
    u: np.ndarray | None
    status: str | None
    iterations: int | None
    written: float
    duration: float


def finish_agents(tasks: Columns, states: Columns) -> Columns:
    """The function :meth:`~ocpar.bsp.ResidentSet.apply` applies on a worker: the
    :class:`AgentFinish` of its agents (``tasks``: Columns of :class:`FinishTask`;
    ``states``: their :class:`~ocpar.ocp.endpoint_agents.AgentState` s), its part of the
    array file written where ``directory`` says."""
    k = len(tasks)
    q, u = padded_paths(states.column("q")), np.asarray(states.column("u"), float)
    params = np.asarray(states.column("params"), float)
    shape_kind, shape_data = tasks.fields["shape"]
    shapes = [shape_data] * k if shape_kind == SHARED else list(shape_data)
    first = int(np.asarray(tasks.column("agent"))[0])
    positions, dim, duration, on_circle, model_names, cost_groups, directory, width, units = (
        tasks.fields[name][1] for name in ("positions", "dim", "duration", "on_circle",
                                           "model_names", "cost_groups", "directory",
                                           "width", "units"))
    checks = agent_checks(shapes, q, u, params, dim, first,
                          np.asarray(states.column("duration"), float))
    of_shape: dict[int, np.ndarray] = {}   # once per distinct shape (a fleet shares a few)
    ends = np.array([of_shape.setdefault(id(shape), shape.boundary_size
                                         + shape.end_position_entries(dim))
                     for shape in (shapes if shape_kind != SHARED else shapes[:1])])
    entries = ends - np.array([shape.boundary_size for shape in shapes[:len(ends)]])[:, None]
    if shape_kind == SHARED:
        ends, entries = np.tile(ends, (k, 1)), np.tile(entries, (k, 1))
    cost = np.asarray(states.column("cost"), float)
    squares = (np.column_stack([np.sum(u[..., a:b] ** 2, axis=(1, 2))
                                for a, b in cost_groups.values()])
               if cost_groups else np.zeros((k, 0)))
    written = 0.0
    if directory is not None:
        start = time.perf_counter()
        write_part(Path(directory), first, width, AgentRecords(
            first=first, q=q, u=u, cost=cost, phi=np.asarray(tasks.column("phi"), float),
            target=np.take_along_axis(params, ends, axis=1),
            model=np.array([model_names.index(model_name(s.model)) for s in shapes],
                           np.int16),
            mass=np.array([float(getattr(s.model, "mass", math.nan)) for s in shapes]),
            status=list(states.column("status")),
            iterations=np.asarray(states.column("iterations")),
            violation=checks.violation), duration, positions, on_circle, units)
        written = time.perf_counter() - start
    rows = {
        "start": (STACKED, checks.start),
        "attitude": (STACKED, np.full(k, math.nan) if checks.attitude is None
                     else checks.attitude),
        "momentum": (STACKED, checks.momentum),
        "dynamics": (STACKED, checks.dynamics),
        "bounds": (STACKED, _per_agent(checks.bounds, checks.agents, first, k)),
        "path": _paths(checks, first, k),
        "violation": (STACKED, checks.violation),
        "positions": (STACKED, np.ascontiguousarray(q[..., list(positions)])),
        "end": (STACKED, np.take_along_axis(q[:, -1], entries, axis=1)),
        "cost": (STACKED, cost),
        "cost_parts": (STACKED, squares),
        "written": (STACKED, np.full(k, written)),
        "duration": (STACKED, np.asarray(states.column("duration"), float)),
    }
    if directory is None:
        rows |= {"q": (STACKED, q), "u": (STACKED, u),
                 "status": states.fields["status"], "iterations": states.fields["iterations"]}
    else:
        rows |= {name: (SHARED, None) for name in ("q", "u", "status", "iterations")}
    return Columns(cls=AgentFinish, length=k, fields=rows)


def _per_agent(values: dict[Shape, np.ndarray], agents: dict[Shape, np.ndarray],
               first: int, k: int) -> np.ndarray:
    """Per-shape values of ``k`` agents (the first ``first``) as one value per agent, NaN
    for an agent whose shape has none."""
    out = np.full(k, math.nan)
    for shape, rows in agents.items():
        if shape in values:
            out[rows - first] = values[shape]
    return out


def _paths(checks: AgentChecks, first: int, k: int) -> tuple[str, object]:
    """The column of each agent's path-constraint residuals (one per constraint of its
    shape): stacked where the agents share one shape."""
    if len(checks.agents) == 1:
        (shape,) = checks.agents
        return STACKED, checks.path.get(shape, np.zeros((k, 0)))
    out = [np.zeros(0)] * k
    for shape, rows in checks.agents.items():
        if shape in checks.path:
            for row, values in zip(rows - first, checks.path[shape], strict=True):
                out[row] = values
    return LISTED, out


def write_part(directory: Path, first: int, width: int, records: AgentRecords,
               duration: float, positions: tuple[int, ...], on_circle: bool,
               units: Units) -> Path:
    """Write the array file's variables of the agents of ``records`` into ``directory`` as
    the part that starts at agent ``first`` (:data:`PART_NAME`), in ``units``."""
    from ocpar.result_files import write_netcdf

    path = directory / PART_NAME.format(first=first, width=width)
    write_netcdf(agent_arrays(records, duration, positions, on_circle, units), {}, path)
    return path


def writes_parts(problem: FormationProblem, backend: Backend, output: Path | None) -> bool:
    """Whether a run writes its agents' variables in parts, each worker its own: with an
    ``output`` directory, at least :data:`PARTS_MIN_AGENTS` agents, more than one worker,
    workers that share the directory's file system
    (:attr:`~ocpar.bsp.Backend.shares_files`), no obstacles (their sides are the
    coordinator's) and agents of one kind (DMOC or ODE: one size of path)."""
    return (output is not None and problem.agents >= PARTS_MIN_AGENTS and backend.workers > 1
            and backend.shares_files and not problem.obstacles and not problem.mixed_kinds)


@dataclass
class Finished:
    """What :func:`finish` gathered: the agents' own ``checks`` (joined in agent order), their
    ``positions`` (n, N+1, p) and ``ends`` (n, d), ``costs`` (n,), the cost parts' per-agent
    sums ``squares`` (n, groups), the part files' names (``parts``; empty where the agents
    were sent back) or else the paths ``q`` (n, N+1, nq), controls ``u``, solver
    ``status`` and ``iterations``, the longest time a worker spent writing its part
    (``written_s``) and each agent's horizon T ``durations`` (n,)."""

    checks: AgentChecks
    positions: np.ndarray
    ends: np.ndarray
    costs: np.ndarray
    squares: np.ndarray
    parts: list[str]
    q: np.ndarray | None
    u: np.ndarray | None
    status: list[str] | None
    iterations: np.ndarray | None
    written_s: float
    durations: np.ndarray


def finish(problem: FormationProblem, agents: ResidentSet, phi: np.ndarray,
           output: Path | None) -> Finished:
    """Finish the resident ``agents`` at their returned parameters ``phi`` (module
    docstring): their part files written into ``output`` where
    :func:`writes_parts` says (``output`` None: all sent back)."""
    n, shape = problem.agents, problem.common_shape
    groups = cost_groups(problem)
    directory = None
    if output is not None:
        Path(output).mkdir(parents=True, exist_ok=True)
        directory = str(Path(output).resolve())
    tasks = Columns(cls=FinishTask, length=n, fields={
        "shape": ((SHARED, problem.shape) if not isinstance(problem.shape, tuple)
                  else (LISTED, list(problem.shape))),
        "agent": (STACKED, np.arange(n)),
        "phi": (STACKED, np.reshape(phi, problem.parameter_shape)),
        "positions": (SHARED, problem.position_indices), "dim": (SHARED, problem.curve.dim),
        "duration": (SHARED, shape.duration), "on_circle": (SHARED, problem.on_circle),
        "model_names": (SHARED, tuple(dict.fromkeys(
            model_name(s.model) for s in problem.agents_by_shape()))),
        "cost_groups": (SHARED, groups), "directory": (SHARED, directory),
        "width": (SHARED, len(str(n - 1))),
        "units": (SHARED, Units.of_fleet(problem))})
    rows = agents.apply(finish_agents, tasks)
    paths = rows.column("path")
    by_shape = problem.agents_by_shape()
    bounds = np.asarray(rows.column("bounds"))
    attitude = np.asarray(rows.column("attitude"))
    checks = AgentChecks(
        start=np.asarray(rows.column("start")),
        attitude=None if np.all(np.isnan(attitude)) else attitude,
        momentum=np.asarray(rows.column("momentum")),
        dynamics=np.asarray(rows.column("dynamics")),
        bounds={s: bounds[a] for s, a in by_shape.items() if s.control_bounds is not None},
        path={s: np.array([paths[i] for i in a]).reshape(len(a), -1)
              for s, a in by_shape.items() if s.path_constraints},
        agents=by_shape, violation=np.asarray(rows.column("violation")))
    written = directory is not None
    parts = ([PART_NAME.format(first=b.start, width=len(str(n - 1)))
              for b in agents.blocks if len(b)] if written else [])
    return Finished(
        checks=checks, positions=np.asarray(rows.column("positions")),
        ends=np.asarray(rows.column("end")), costs=np.asarray(rows.column("cost")),
        squares=np.asarray(rows.column("cost_parts")), parts=parts,
        q=None if written else padded_paths(rows.column("q"), problem.node_width),
        u=None if written else np.asarray(rows.column("u")),
        status=None if written else list(rows.column("status")),
        iterations=None if written else np.asarray(rows.column("iterations")),
        written_s=float(np.max(rows.column("written"))),
        durations=np.asarray(rows.column("duration"), float))


def padded_paths(paths: list[np.ndarray] | np.ndarray, width: int | None = None
                 ) -> np.ndarray:
    """Node paths (k, N+1, width) from ``paths`` (a column of them): as they are where they
    share their size, else each padded with NaN to ``width`` (default: the widest; a fleet
    of DMOC and ODE agents)."""
    if isinstance(paths, np.ndarray) and (width is None or paths.shape[-1] == width):
        return np.asarray(paths, float)
    rows = [np.asarray(p, float) for p in paths]
    width = max(p.shape[-1] for p in rows) if width is None else width
    out = np.full((len(rows), rows[0].shape[0], width), np.nan)
    for out_row, row in zip(out, rows, strict=True):
        out_row[:, :row.shape[-1]] = row
    return out


def cost_groups(problem: FormationProblem) -> dict[str, tuple[int, int]]:
    """The model's named control groups (name → (first, last + 1) control columns) whose
    cost parts h Σ|u|² the run reports; none where an agent has a running cost of its own."""
    if any(getattr(shape, "running_cost", None) is not None
           for shape in problem.agents_by_shape()):
        return {}
    return dict(getattr(problem.common_shape.model, "cost_parts", {}))
