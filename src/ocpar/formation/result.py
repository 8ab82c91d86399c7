"""The result of a formation run, as an object and as ``result.json``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ocpar.formation.couplings.potential import equidistance_error
from ocpar.formation.keep_out.obstacles import Clearance
from ocpar.formation.keep_out.separation import ClosestApproach
from ocpar.formation.problem import FormationProblem
from ocpar.formation.verify import Verification
from ocpar.models.labels import (
    Labels,
    control_labels,
    cost_unit,
    mass_unit,
    model_name,
    state_labels,
    time_unit,
)
from ocpar.ocp.dmoc import DmocShape
from ocpar.result_files import categories
from ocpar.results import (
    Array,
    RunResult,
    array,
    components,
    derived_units,
    text,
    time_axes,
)

#: Names of the position entries in the array file's ``q_component`` labels (others: q<i>),
#: unless the model names its entries (``state_names``, :mod:`ocpar.models.labels`).
AXES = ("x", "y", "z")


#: The ``configuration`` variable's description by the fleet's agents: DMOC agents
#: (``dmoc``), ODE agents (``ms``), both (``mixed``) or unknown (None)
NODE_PATHS = {
    "dmoc": "configuration q_k at the nodes (the DMOC node path)",
    "ms": "state x_k at the nodes (the multiple-shooting node path)",
    "mixed": "each agent's node path: a DMOC agent's configuration q_k, an ODE agent's "
             "state x_k (NaN-padded to the widest)",
    None: "each agent's node path at the nodes"}


@dataclass(frozen=True)
class Units:
    """The names and units of the fleet's quantities (its first agent's model's,
    :mod:`ocpar.models.labels`): ``state`` the configuration's entries (default x, y, z for
    the position entries, q<i> for the others), ``control`` the control's, and the units of
    ``time``, ``cost`` (the inner optimal cost) and ``mass`` (unit strings, '1' by
    default); ``node_path`` what a node of the paths is (:data:`NODE_PATHS`)."""

    state: Labels
    control: Labels
    time: str
    cost: str
    mass: str
    node_path: str = NODE_PATHS[None]

    @classmethod
    def of_fleet(cls, problem: FormationProblem) -> Units:
        """The names and units of ``problem``'s fleet: its widest model's (:meth:`of`), and
        the description of its node paths by its agents' kinds."""
        kinds = {"dmoc" if isinstance(s, DmocShape) else "ms" for s in problem.agents_by_shape()}
        units = cls.of(problem.widest_shape.model, problem.node_width,
                       problem.common_shape.model.nu, problem.position_indices)
        return dataclasses.replace(units, node_path=NODE_PATHS[
            kinds.pop() if len(kinds) == 1 else "mixed"])

    @classmethod
    def of(cls, model: object, nq: int, nu: int, positions: tuple[int, ...]) -> Units:
        """``model``'s names and units of its ``nq`` configuration and ``nu`` control
        entries, ``positions`` the configuration's position entries."""
        default = tuple(AXES[positions.index(i)] if i in positions and len(positions) <= 3
                        else f"q{i}" for i in range(nq))
        return cls(state_labels(model, nq, default), control_labels(model, nu),
                   time_unit(model), cost_unit(model), mass_unit(model))

    @property
    def velocity(self) -> Labels:
        """The velocities' names and units (the configuration's per time unit)."""
        return self.state.per(self.time)


@dataclass
class Fleet:
    """What the array file says of the problem's agents: ``duration`` T (common to the
    fleet); ``position_indices`` the configuration's position entries;
    ``targets`` (n, d) the target points z(φ) at the returned φ (NaN where φ is not finite);
    ``model`` (n,) each agent's index into ``model_names`` (the models' class names, in order
    of first use); ``mass`` (n,) each agent's model's ``mass`` (NaN for a model without
    one); ``nq`` the configuration's entries; ``units`` the names and units of the fleet's
    quantities (:class:`Units`)."""

    duration: float
    position_indices: tuple[int, ...]
    targets: np.ndarray
    model: np.ndarray
    model_names: list[str]
    mass: np.ndarray
    nq: int
    units: Units | None = None

    @classmethod
    def of(cls, problem: FormationProblem, phi: np.ndarray) -> Fleet:
        """``problem``'s fleet at the returned parameters ``phi``: O(n), vectorised."""
        n, shape = problem.agents, problem.common_shape
        targets = np.full((n, problem.curve.dim), np.nan)
        phi = np.reshape(phi, problem.parameter_shape)
        finite = np.all(np.isfinite(phi.reshape(n, -1)), axis=1)
        if np.any(finite):
            targets[finite] = problem.final_positions(phi[finite])
        model, mass, names = np.zeros(n, np.int16), np.empty(n), []
        for shape_i, agents in problem.agents_by_shape().items():
            name = model_name(shape_i.model)
            if name not in names:
                names.append(name)
            model[agents] = names.index(name)
            mass[agents] = float(getattr(shape_i.model, "mass", math.nan))
        return cls(shape.duration, problem.position_indices, targets, model, names, mass,
                   problem.node_width, Units.of_fleet(problem))


@dataclass
class FormationResult(RunResult):
    """Outcome of :func:`ocpar.formation.solve_formation`.

    ``phi`` (n,) final angles (rad); ``agent_costs`` (n,) inner optimal costs Ĵ_i;
    ``trajectories`` (n, N+1, nq) DMOC node paths; ``controls`` (n, N, nu) their interval
    controls (``result.json`` carries each agent's ``peak_thrust`` max_k |u_k|, force
    unit); ``cost_parts`` the total cost split by
    control groups where the model names them (e.g. ``translational_cost``,
    ``rotational_cost``); ``outer_iterations`` the outer solver's iterations (None where it
    stopped on a failed inner solve, unknown); ``coupling_residual``
    max_k |c_k(φ)|, the scaled coupling c = (ℓ²/n³) dG/dφ as the outer problem imposes it
    (:mod:`ocpar.formation.couplings.potential`), at the parameters located from the returned end
    points (``verification``: :class:`~ocpar.formation.verify.Verification`, whose checks
    decide whether the run may say ``converged``; ``result.json`` carries it and
    ``near_collision``); ``on_circle`` whether the curve is a circle (the
    equidistance error is NaN otherwise); ``separation`` the closest approach of any two
    agents on the continuous paths (:meth:`FormationProblem.closest_approach
    <ocpar.formation.FormationProblem.closest_approach>`); with a required minimum
    separation (:mod:`ocpar.formation.keep_out.rounds`): ``required_separation`` D,
    ``separation_rounds`` the keep-out rounds run and ``unconstrained_cost`` the total cost
    before them (NaN/None/0 without); with obstacles (:mod:`ocpar.formation.keep_out.obstacles`, in
    every inner problem): ``obstacle_clearance`` the smallest clearance of any agent from
    any obstacle on the returned continuous paths (which agent, obstacle, when) and
    ``obstacle_sides`` on which side each agent passes each obstacle
    (:func:`~ocpar.formation.keep_out.obstacles.passing_sides`: per agent, per obstacle ``left`` or
    ``right`` in 2-D, a unit vector in 3-D, None for a half-space); ``feasible_set``
    ``continuous`` on a circle (a common rotation), ``discrete`` elsewhere (the potential's
    isolated critical points), with ``critical_sets`` the candidates searched by
    ``--ordering optimal`` (:meth:`~ocpar.formation.couplings.critical_sets.CriticalSet.to_dict`,
    cheapest first; None when none were); ``ordering`` on a circle with ``--ordering
    optimal`` (None otherwise): the assignment (slot index per agent), ``offset`` (rad),
    what its optimality rests on (``bound``: ``convex``, ``quadratic`` or None: none
    claimed), ``proven``, the relative ``gap`` and ``lower_bound`` it proved (null where
    none is claimed), the search's ``search_supersteps`` and ``search_inner_solves``, all the
    ordering's ``inner_solves`` and why the search stopped (``message``;
    :mod:`~ocpar.formation.ordering_bound`); ``final_time`` with a free or minimum final
    time (None for a fixed one): T and how it was found (:mod:`ocpar.formation.final_time`:
    ``free``: the weight w, the objective Σ J_i + w T, dF/dT + w at T, the bound T stopped
    at, the ``method`` (``joint``: T and the shift by joint Newton steps, each iteration a
    superstep at (θ, T); ``sequence``: a formation solve per T), the iterations;
    ``minimum``: the ``bracket`` [T_lo, T_hi], ``proven``, the rotation,
    phase 1's total slack at ``phase_one_T``; ``free_per_agent``: the weight, the largest
    T_i) and ``durations`` (n,) each agent's own T_i (None but there; the array file's
    ``duration``); ``fleet`` (:class:`Fleet`) and per agent the inner
    solver's ``solver_status`` and ``solver_iterations`` (n,) of its last solve at the
    returned φ (with a required separation: of the solve before the rounds; a monolithic
    run: the one NLP's) for the array file (:meth:`arrays`); ``positions`` (n, N+1, p) the
    position entries of the node paths. Where the workers wrote their agents' part of the
    array file themselves (``parts``, the files' names, :mod:`ocpar.formation.finish`), the
    per-agent arrays (``agent_costs``, ``trajectories``, ``controls``, ``solver_status``,
    ``solver_iterations``) are None: they are in those files, and ``positions`` is here.
    The common fields are :class:`ocpar.results.RunResult`'s.
    """

    scheme: ClassVar[str] = "formation"
    #: NaN in Python and null in ``result.json`` unless converged (with the cost parts,
    #: :meth:`headline_keys`, :meth:`headline_attributes`; the last iterate's in
    #: ``last_iterate``).
    headline_fields: ClassVar[tuple[str, ...]] = ("total_cost", "unconstrained_cost")
    statuses: ClassVar[tuple[str, ...]] = (*RunResult.statuses, "separation_not_met",
                                           "obstacles_not_cleared")

    agents: int
    mode: str
    total_cost: float
    phi: np.ndarray
    agent_costs: np.ndarray | None
    trajectories: np.ndarray | None
    outer_iterations: int | None
    separation: ClosestApproach
    cost_parts: dict[str, float] = field(default_factory=dict)
    coupling_residual: float = math.nan
    on_circle: bool = True
    required_separation: float | None = None
    separation_rounds: int = 0
    unconstrained_cost: float = math.nan
    controls: np.ndarray | None = None
    obstacle_clearance: Clearance | None = None
    obstacle_sides: list[list[str | list[float] | None]] | None = None
    feasible_set: str = "continuous"
    critical_sets: list[dict] | None = None
    ordering: dict | None = None
    final_time: dict | None = None
    durations: np.ndarray | None = None
    verification: Verification | None = None
    fleet: Fleet | None = None
    solver_status: list[str] | None = None
    solver_iterations: np.ndarray | None = None
    positions: np.ndarray | None = None
    parts: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.positions is None and self.trajectories is not None and self.fleet is not None:
            self.positions = np.asarray(self.trajectories)[..., list(
                self.fleet.position_indices)]

    def headline_keys(self) -> tuple[str, ...]:
        """:attr:`headline_fields` and the cost parts' keys."""
        return self.headline_fields + tuple(self.cost_parts)

    def headline_attributes(self) -> tuple[str, ...]:
        """:attr:`headline_fields` and ``cost_parts`` (each part NaN unless converged)."""
        return (*self.headline_fields, "cost_parts")

    def headline_title(self) -> str:
        """The total cost, for the plot's title (:meth:`~ocpar.results.RunResult.title`)."""
        return f"total cost {self.total_cost:.6e}"

    @property
    def peak_thrust(self) -> np.ndarray:
        """max_k |u_k| per agent (n,), force unit (NaN without controls)."""
        if self.controls is None:
            return np.full(self.agents, np.nan)
        return np.max(np.linalg.norm(np.asarray(self.controls, float), axis=2), axis=1)

    @property
    def equidistance_error(self) -> float:
        """max |gap − 2π/n| between neighbours on the circle (rad); NaN off a circle."""
        return equidistance_error(self.phi) if self.on_circle else math.nan

    def scheme_fields(self) -> dict:
        """Formation's fields of ``result.json`` (the figures and the final angles; the
        paths and per-agent data are in the array file, :meth:`arrays`)."""
        return {
            "agents": self.agents,
            "mode": self.mode,
            "total_cost": _finite_or_none(self.total_cost),
            **{name: _finite_or_none(value) for name, value in self.cost_parts.items()},
            "phi": np.asarray(self.phi, float).tolist(),
            "equidistance_error": _finite_or_none(self.equidistance_error),
            "coupling_residual": _finite_or_none(self.coupling_residual),
            "outer_iterations": self.outer_iterations,
            "min_separation": _finite_or_none(self.separation.distance),
            "closest_pair": (list(self.separation.agents)
                             if math.isfinite(self.separation.distance) else None),
            "closest_time": _finite_or_none(self.separation.time),
            "required_separation": self.required_separation,
            "separation_rounds": self.separation_rounds,
            "unconstrained_cost": _finite_or_none(self.unconstrained_cost),
            **self._obstacle_fields(),
            "feasible_set": self.feasible_set,
            "critical_sets": self.critical_sets,
            "ordering": self.ordering,
            **({"final_time": self.final_time} if self.final_time is not None else {}),
            **self._verification_fields(),
        }

    def arrays(self) -> dict[str, Array]:
        """The array file's variables (:meth:`~ocpar.results.RunResult.dataset`): on the
        dimensions agent, time (the N+1 nodes), interval_time (the N intervals, by their
        start), q_component (named by the model, default x, y, z for the position entries,
        q<i> for the others), u_component, axis (d): the coordinates ``time``,
        ``interval_time``, ``q_component`` and ``u_component``
        (with their ``*_units``); ``configuration`` (the node paths), ``velocity``
        (q_{k+1} − q_k)/h on each interval (DMOC's path is linear between nodes: one
        velocity per interval; the boundary ones are the problem's data), ``control``,
        ``cost``, ``peak_thrust``, ``phi``, ``target`` z(φ), ``model`` (an index into
        ``model_name``), ``mass``, ``solver_status`` (an index into ``solver_status_name``),
        ``solver_iterations``, ``constraint_violation`` and, with obstacles,
        ``obstacle_side``. Units: the model's (:class:`Units`; '1' for the nondimensional
        paper examples). Where the workers wrote their agents' variables (:attr:`parts`),
        the run's own ones only (:func:`run_arrays`)."""
        fleet = self.fleet
        duration = math.nan if fleet is None else fleet.duration
        positions = () if fleet is None else fleet.position_indices
        nodes = (self.trajectories if self.trajectories is not None else self.positions).shape[1]
        units = self.units()
        out = run_arrays(nodes, duration, units, [] if fleet is None else fleet.model_names,
                         positions)
        if self.parts:
            return out
        return out | agent_arrays(AgentRecords(
            first=0, q=np.asarray(self.trajectories, float), u=self.controls,
            cost=np.asarray(self.agent_costs, float), phi=np.asarray(self.phi, float),
            target=None if fleet is None else fleet.targets,
            model=None if fleet is None else fleet.model,
            mass=None if fleet is None else fleet.mass,
            status=self.solver_status, iterations=self.solver_iterations,
            violation=None if self.verification is None
            else self.verification.agent_violation, sides=self.obstacle_sides),
            duration if self.durations is None else self.durations, positions,
            self.on_circle, units)

    def units(self) -> Units:
        """The names and units of the fleet's quantities (:class:`Units`: the fleet's, else
        the defaults for the arrays' shapes)."""
        if self.fleet is not None and self.fleet.units is not None:
            return self.fleet.units
        nq = self.fleet.nq if self.fleet is not None else np.shape(self.trajectories)[2]
        nu = 0 if self.controls is None else np.shape(self.controls)[2]
        return Units.of(None, nq, nu, () if self.fleet is None else self.fleet.position_indices)

    def _verification_fields(self) -> dict:
        """``verification`` (:meth:`~ocpar.formation.verify.Verification.to_dict`) and
        ``near_collision`` (None unless there is one); none without a verification."""
        v = self.verification
        if v is None:
            return {}
        return {"verification": v.to_dict(), "near_collision": v.near_collision}

    def _obstacle_fields(self) -> dict:
        """``min_obstacle_clearance`` and where it occurs (none without obstacles; the sides
        are in the array file)."""
        c = self.obstacle_clearance
        if c is None:
            return {}
        return {"min_obstacle_clearance": _finite_or_none(c.distance),
                "obstacle_agent": c.agent if c.agent >= 0 else None,
                "obstacle_index": c.obstacle if c.obstacle >= 0 else None,
                "obstacle_time": _finite_or_none(c.time)}

    def _required_summary(self) -> str:
        """The summary's words on a required separation ('' without one)."""
        if self.required_separation is None:
            return ""
        if not self.converged:
            return f"   required {self.required_separation:g}: {self.separation_rounds} round(s)"
        increase = self.total_cost / self.unconstrained_cost - 1
        return (f"   required {self.required_separation:g}: {self.separation_rounds} round(s), "
                f"cost {increase * 100:+.3g}% over the unconstrained {self.unconstrained_cost:.6e}")

    def _obstacle_summary(self) -> str:
        """The summary's line on obstacles ('' without any)."""
        c = self.obstacle_clearance
        if c is None:
            return ""
        if c.agent < 0:
            return "min obstacle clearance — (no finite paths; obstacles in the inner problems)\n"
        return (f"min obstacle clearance {c.distance:.6g} (agent {c.agent}, obstacle "
                f"{c.obstacle} at t = {c.time:.6g}; obstacles in the inner problems)\n")

    def _separation_summary(self) -> str:
        """The summary's words on the closest approach ('—' where there is none: fewer than
        two agents, or no finite paths)."""
        c = self.separation
        if c.agents[0] < 0:
            return "min separation —"
        return (f"min separation {c.distance:.6g} (agents {c.agents[0]} and {c.agents[1]} "
                f"at t = {c.time:.6g})")

    def _final_time_summary(self) -> str:
        """The summary's line on a free or minimum final time ('' for a fixed one)."""
        t = self.final_time
        if t is None:
            return ""
        if t["mode"] == "minimum":
            low, high = t["bracket"]
            slack = t["phase_one_slack"]
            return (f"minimum final time T {high:.12g} (none reachable below {low:.12g}; "
                    f"phase 1's slack at T (1 - tol) "
                    f"{'none' if slack is None else format(slack, '.3e')})\n")
        if t["mode"] == "free_per_agent":
            return (f"free final time per agent: T_i up to {t['T']} (w {t['time_weight']:g}; "
                    f"the array file's duration)\n")
        objective = "" if t["objective"] is None else f", sum J + w T {t['objective']:.12e}"
        return f"free final time T {t['T']:.12g} (w {t['time_weight']:g}{objective})\n"

    def summary(self) -> str:
        """A few lines for people: the headline numbers of the run."""
        equidistance = (f"equidistance error {_shown(self.equidistance_error, '.1e')} rad   "
                        if self.on_circle else "")
        parts = "".join(f"{name.replace('_', ' ')} {value:.6e}   "
                        for name, value in self.cost_parts.items())
        cost = (f"total cost {self.total_cost:.12e}   {parts}" if self.converged
                else f"total cost — {self.not_reached()}\n")
        return (
            f"status {self.status} ({self.message})\n"
            f"{cost}"
            f"{equidistance}coupling residual {_shown(self.coupling_residual, '.1e')}\n"
            f"{self._separation_summary()}{self._required_summary()}\n"
            f"{self._obstacle_summary()}"
            f"{self._final_time_summary()}"
            f"outer iterations {_count(self.outer_iterations)}   supersteps {self.supersteps}   "
            f"inner solves {self.inner_solves} (failed {self.failed_solves}, retries "
            f"{self.retries})\n"
            f"wall time {self.wall_time_s:.2f} s on {self.workers} {self.backend} worker(s), "
            f"mode {self.mode}"
        )


def run_arrays(nodes: int, duration: float, units: Units, model_names: list[str],
               positions: tuple[int, ...] = ()) -> dict[str, Array]:
    """The array file's variables that are the run's, not an agent's: the coordinates
    ``time`` of the ``nodes`` nodes over ``duration``, ``interval_time``
    (:func:`~ocpar.results.time_axes`), ``q_component`` and ``u_component`` (names and
    units, ``units``), ``velocity_units`` (where the velocity's entries differ in unit,
    :func:`~ocpar.results.derived_units`), ``axis`` (the names of the configuration's
    ``positions`` entries, where known) and ``model_name`` (where the agents' models are
    known)."""
    out = (time_axes(np.linspace(0.0, duration, nodes), units.time)
           | components("q_component", units.state, "configuration entry")
           | derived_units("velocity", "q_component", units.velocity)
           | components("u_component", units.control, "control entry"))
    if positions:
        out["axis"] = array("axis", text(units.state.names[i] for i in positions), "1",
                            "position entry (the target's and the obstacles' axes)")
    if model_names:
        out["model_name"] = array("models", text(model_names), "1",
                                  "the agents' model classes")
    return out


@dataclass
class AgentRecords:
    """What the array file holds of m consecutive agents, the first ``first``: node paths
    ``q`` (m, N+1, nq), controls ``u`` (m, N, nu) (None: none), ``cost`` (m,), ``phi`` (m,)
    or (m, 2), ``target`` (m, d), ``model`` (m,) indices into the run's model names,
    ``mass`` (m,), the inner solver's ``status`` (m strings) and ``iterations`` (m,), the
    verification's ``violation`` (m,) and the ``sides`` each passes its obstacles on (None
    where not known)."""

    first: int
    q: np.ndarray
    u: np.ndarray | None
    cost: np.ndarray
    phi: np.ndarray
    target: np.ndarray | None = None
    model: np.ndarray | None = None
    mass: np.ndarray | None = None
    status: list[str] | None = None
    iterations: np.ndarray | None = None
    violation: np.ndarray | None = None
    sides: list[list[str | list[float] | None]] | None = None


def agent_arrays(records: AgentRecords, duration: float | np.ndarray,
                 positions: tuple[int, ...], on_circle: bool, units: Units
                 ) -> dict[str, Array]:
    """The array file's variables of the agents of ``records`` (their ``agent`` coordinate,
    configuration, velocity, cost, phi, control, peak_thrust, target, model, mass,
    solver_status with its own ``solver_status_name``, solver_iterations,
    constraint_violation, obstacle_side: :meth:`FormationResult.arrays`), in ``units``. Any
    block of agents gives its rows of the whole fleet's variables; the solver statuses'
    names are the block's own (:func:`ocpar.result_files.load` joins them). ``duration``:
    the fleet's T, or each agent's (m,) where each chose its own (then also a ``duration``
    variable)."""
    q = records.q
    m, nodes, _ = q.shape
    h = np.reshape(duration, (-1, 1, 1)) / (nodes - 1)
    position = Labels(*(tuple(units.state.names[i] for i in positions),
                        tuple(units.state.units[i] for i in positions))) if positions else None
    out = {
        "agent": array("agent", np.arange(records.first, records.first + m), "1",
                       "agent index"),
        "configuration": array("agent time q_component", q, units.state,
                               units.node_path),
        "velocity": array("agent interval_time q_component", np.diff(q, axis=1) / h,
                          units.velocity, "velocity (q_{k+1} - q_k)/h on each interval",
                          entry_units="velocity_units"),
        "cost": array("agent", records.cost, units.cost, "inner optimal cost J_i"),
        **({"duration": array("agent", np.asarray(duration, float), units.time,
                              "the agent's horizon T_i (its own final time)")}
           if np.ndim(duration) else {}),
        "phi": array("agent" if np.ndim(records.phi) == 1 else "agent parameter",
                     records.phi, "rad" if on_circle else "1",
                     "final parameter on the target (angle on a curve, slot index, "
                     "surface parameters)"),
    }
    if records.u is not None:
        u = np.asarray(records.u, float)
        out["control"] = array("agent interval_time u_component", u, units.control,
                               "control u_k on each interval (constant on it)")
        out["peak_thrust"] = array("agent", np.max(np.linalg.norm(u, axis=2), axis=1),
                                   units.control.unit or "1", "max_k |u_k|"
                                   + ("" if units.control.unit else
                                      " (over entries of different units)"))
    if records.target is not None:
        out |= {
            "target": array("agent axis", records.target,
                            "1" if position is None else position.unit or "1",
                            "target point z(phi) at the returned parameters"),
            "model": array("agent", records.model, "1", "index into model_name",
                           categories="model_name"),
            "mass": array("agent", records.mass, units.mass,
                          "the agent's model's mass (NaN: a model without one)"),
        }
    if records.status is not None:
        codes, names = categories(records.status)
        out |= {
            "solver_status": array("agent", codes, "1",
                                   "index into solver_status_name: the inner solver's "
                                   "return status", categories="solver_status_name"),
            "solver_status_name": array("status", text(names), "1",
                                        "inner solver return statuses"),
            "solver_iterations": array("agent", np.asarray(records.iterations, np.int32),
                                       "1", "inner solver iterations"),
        }
    if records.violation is not None:
        out["constraint_violation"] = array(
            "agent", records.violation, "1",
            "largest relative residual of the agent's boundary, momentum, dynamics, "
            "control-bound and path-constraint checks (ocpar.formation.verify)")
    if records.sides is not None:
        out["obstacle_side"] = _obstacle_sides(records.sides, positions)
    return out


def _obstacle_sides(sides: list[list[str | list[float] | None]],
                    positions: tuple[int, ...]) -> Array:
    """``obstacle_sides`` (per agent, per obstacle) as an array: in 2-D (agent, obstacle)
    +1 left, −1 right, 0 none (a half-space, a failed path); else (agent, obstacle, axis) the
    unit vector from the centre to the closest point, NaN for none."""
    n, m = len(sides), len(sides[0]) if sides else 0
    if len(positions) == 2:
        codes = {"left": 1, "right": -1, None: 0}
        values = np.array([[codes[s] for s in row] for row in sides], np.int8).reshape(n, m)
        return array("agent obstacle", values, "1", "side the agent passes each obstacle on",
                     flag_values=[1, -1, 0], flag_meanings="left right none")
    values = np.full((n, m, len(positions)), np.nan)
    for i, row in enumerate(sides):
        for j, side in enumerate(row):
            if side is not None:
                values[i, j] = side
    return array("agent obstacle axis", values, "1",
                 "unit vector from the obstacle's centre to the agent's closest point "
                 "(scaled space); NaN: none")


def _count(n: int | None) -> str:
    """A count for the summary: '—' where it is not known (None)."""
    return "—" if n is None else str(n)


def _shown(x: float, spec: str) -> str:
    """A figure for the summary in format ``spec``: '—' where it is not finite."""
    return format(x, spec) if math.isfinite(x) else "—"


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
