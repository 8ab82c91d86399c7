"""The formation reconfiguration problem: n agents, fixed starts, final formation on a curve.

Agent i is any controlled ODE (:class:`~ocpar.models.OdeModel` naming its
``position_indices``, transcribed by multiple shooting, :class:`~ocpar.ocp.MsEndpointShape`:
it starts in the state ``starts[i]`` and ends with its position on the target, the other
end entries ``final_state`` or free) or any Lagrangian mechanical system
(:class:`~ocpar.models.MechanicalSystem`: L(q, q̇),
optionally time-dependent per DMOC interval, generalised force F(q, u), optional holonomic
constraints c(q) = 0), transcribed by DMOC with the problem's ``shape`` (N intervals over
the horizon T): one shape for all agents, or one per agent (a mixed fleet: each agent its own
model, mass, thrust limits, cost or path constraints, on a common N, T and configuration
and control sizes). It starts in configuration ``starts[i]`` with
velocity ``start_velocities[i]`` and must end, after T, with its position (the first
d = ``curve.dim`` entries of its configuration) at z(φ_i) on the closed curve z, the rest of
its configuration equal to ``final_attitude`` and its velocity ``final_velocity``, minimising
∫|u|² dt. The angles φ are chosen by the outer problem subject to the coupling g(φ) = 0
(:mod:`ocpar.formation.couplings.coupling`: the paper's potential by default).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ocpar.bsp import Backend
from ocpar.bsp.columns import LISTED, Columns
from ocpar.formation.couplings.coupling import Coupling, PotentialCoupling
from ocpar.formation.keep_out.obstacles import Obstacle, check_obstacles
from ocpar.formation.keep_out.separation import ClosestApproach, closest_approach
from ocpar.formation.targets.curve import Circle, Curve
from ocpar.formation.targets.slots import Slots, nearest_assignment
from ocpar.formation.targets.surface import PARAMETERS, Surface, fibonacci_directions
from ocpar.models import MechanicalSystem
from ocpar.models.labels import check_labels
from ocpar.ocp import DmocShape, MsEndpointShape, OcpTask
from ocpar.ocp.constraints import check_smooth
from ocpar.ocp.reach import Reach, rest_to_rest_reach

#: Boundary configurations must satisfy the model's holonomic constraints to this tolerance.
CONSTRAINT_TOL = 1e-8
#: Points of the curve sampled (uniform in φ) to find each start's nearest target
#: (:meth:`FormationProblem._check_thrust_reach`), and agents per block of that search.
REACH_SAMPLES, REACH_BLOCK = 2048, 256
#: A start moved for obstacles (:meth:`FormationProblem.clear_start`) has every target at
#: least this · the obstacle's scale clear of it (scaled: |A (r − c)| ≥ 1 + this) ...
START_MARGIN = 0.1
#: ... at the smallest of this many shifts of the formation's family (2π/this apart) that
#: does.
START_SHIFTS = 4096


def _one(shape: object) -> bool:
    """Whether ``shape`` is one shape for all agents (not one per agent)."""
    return not isinstance(shape, tuple | list)


def _array_allowing_nan(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float array of ``shape`` (NaN allowed), or ValueError naming the
    field."""
    try:
        array = np.array(value, float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be an array of numbers with shape {shape}") from None
    if array.shape != shape:
        raise ValueError(f"{name}: must have shape {shape}, got {array.shape}")
    return array


def _array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float array of ``shape``, or ValueError naming the field."""
    try:
        array = np.asarray(value, float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be an array of numbers with shape {shape}") from None
    if array.shape != shape:
        raise ValueError(f"{name}: must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: must be finite")
    return array


@dataclass(frozen=True)
class FormationProblem:
    """A formation problem; checked when built (one ValueError naming the field).

    ``name`` labels results; ``shape`` the DMOC shape (model, N, horizon T), or a sequence of
    one per agent (a mixed fleet; same N, T, configuration and control sizes and position
    entries; agents with equal shapes share one compiled solver per process); ``curve`` the
    final formation's curve (:class:`~ocpar.formation.Circle`,
    :class:`~ocpar.formation.Ellipse`, :class:`~ocpar.formation.PlaneCurve`,
    :class:`~ocpar.formation.ParametricCurve`, or a user's :class:`~ocpar.formation.Curve`),
    or :class:`~ocpar.formation.Slots`, m ≥ n given points of which the agents take n (then
    φ_i is agent i's slot index and only the assignment is free:
    :mod:`ocpar.formation.targets.slots`).
    Shapes, with n agents (n ≥ 2), nq the model's configuration size and d = ``curve.dim``
    ≤ nq: ``starts`` (n, nq); ``start_velocities`` (n, nq), default at rest;
    ``final_velocity`` (nq,) common to all or (n, nq) per agent, default at rest;
    ``final_attitude`` (nq − d,) the configuration entries after the position (none for
    point masses, e.g. a unit quaternion for rigid bodies). Units are the model's.
    ODE agents (``shape`` an :class:`~ocpar.ocp.MsEndpointShape`, or one per agent): nq is
    the state's nx, ``starts`` (n, nx) the start states; ``final_state`` the end state's
    entries other than the position (nx − d,), in state order, common or (n, nx − d) per
    agent (default 0), an entry the shape leaves free (``free_end``) ignored (NaN allowed
    there); ``start_velocities``, ``final_velocity`` and ``final_attitude`` are DMOC's and
    stay None. A fleet of both kinds (one shape per agent): its DMOC agents at rest at both
    ends with all of their configuration the position, ``starts`` (n, W) each agent's start
    in its first entries (W the widest agent's; NaN beyond), boundary data of one length
    (:meth:`_check_mixed_boundary`).
    ``obstacles``: static :class:`~ocpar.formation.keep_out.obstacles.Ellipsoid` (or ``Sphere``) and
    :class:`~ocpar.formation.keep_out.obstacles.HalfSpace` obstacles in position space that every
    path keeps clear of at all times (:mod:`ocpar.formation.keep_out.obstacles`; an ODE agent's
    on the polyline through its integrator's sub-step states, :mod:`ocpar.ocp.ms_endpoint`); the
    starts must be clear of them. ``coupling``: what the final angles satisfy on a curve
    (:mod:`ocpar.formation.couplings.coupling`): the paper's potential (default),
    :class:`~ocpar.formation.couplings.coupling.EqualArcLength` or a user's
    :class:`~ocpar.formation.couplings.coupling.UserCoupling`; onto slots only the default.
    """

    name: str
    shape: DmocShape | MsEndpointShape | tuple[DmocShape | MsEndpointShape, ...]
    curve: Curve | Surface | Slots
    starts: np.ndarray
    start_velocities: np.ndarray | None = None
    final_velocity: np.ndarray | None = None
    final_attitude: np.ndarray | None = None
    obstacles: tuple[Obstacle, ...] = ()
    coupling: Coupling = field(default_factory=PotentialCoupling)
    final_state: np.ndarray | None = None

    def __post_init__(self) -> None:
        self._check_shapes()
        if not isinstance(self.curve, Curve | Surface | Slots):
            raise ValueError(f"curve: must be a Curve (Circle, Ellipse, PlaneCurve, "
                             f"ParametricCurve), a Surface (Sphere, Ellipsoid, "
                             f"ParametricSurface) or Slots, got {type(self.curve).__name__}")
        if isinstance(self.curve, Curve):
            self.curve.check()  # built-in curves checked themselves; a user's subclass may not
        nq, d = self.node_width, self.curve.dim
        if d > nq:
            raise ValueError(f"curve: lies in {d}-D but the model's configuration has {nq} "
                             "entries")
        if np.ndim(np.asarray(self.starts, dtype=object)) != 2:
            raise ValueError(f"starts: must have shape (n, {nq}), one row per agent")
        n = len(self.starts)
        if n < 2:
            raise ValueError(f"starts: a formation needs at least 2 agents, got {n}")
        if isinstance(self.curve, Slots) and self.curve.count < n:
            raise ValueError(f"curve: {self.curve.count} slots for {n} agents: a formation "
                             "needs at least one slot per agent")
        if not isinstance(self.coupling, Coupling):
            raise ValueError(f"coupling: must be a Coupling (PotentialCoupling, EqualArcLength, "
                             f"UserCoupling), got {type(self.coupling).__name__}")
        if isinstance(self.curve, Slots) and self.coupling != PotentialCoupling():
            raise ValueError("coupling: onto slots the coupling is the assignment (no slot "
                             "taken twice); leave coupling at its default")
        if isinstance(self.curve, Curve | Surface):
            self.coupling.check(self.curve, n * self.parameters)
        fields = {"starts": (self.starts, (n, nq))}
        if self.mixed_kinds:
            self._check_mixed_boundary(n, d)
            fields = {}
        elif self.ode_agents:
            self._check_ode_boundary(n, nq, d)
        else:
            if self.final_state is not None:
                raise ValueError("final_state: ODE agents' field; DMOC agents end with "
                                 "final_attitude and final_velocity")
            fields |= {
                "start_velocities": (np.zeros((n, nq)) if self.start_velocities is None
                                     else self.start_velocities, (n, nq)),
                "final_attitude": (np.zeros(0) if self.final_attitude is None and nq == d
                                   else self.final_attitude, (nq - d,))}
            final_velocity = (np.zeros(nq) if self.final_velocity is None
                              else self.final_velocity)
            fields["final_velocity"] = (final_velocity, (n, nq) if np.ndim(final_velocity) == 2
                                        else (nq,))
        for name, (value, shape) in fields.items():
            if value is None:
                raise ValueError(f"{name}: required ({nq - d} configuration entries after the "
                                 f"{d} position entries)")
            object.__setattr__(self, name, _array(name, value, shape))
        if isinstance(self.shape, tuple) and len(self.shape) != n:
            raise ValueError(f"shape: a mixed fleet needs one shape per agent: "
                             f"{len(self.shape)} shapes for {n} agents")
        self._check_holonomic_constraints()
        indices = self.position_indices
        if not indices or len(set(indices)) != len(indices) or not all(
                isinstance(i, (int, np.integer)) and 0 <= i < nq for i in indices):
            raise ValueError(f"shape: the model's position_indices must be distinct entries "
                             f"of its {nq} configuration entries, got {indices}")
        object.__setattr__(self, "obstacles", check_obstacles(self.obstacles, len(indices)))
        self._attach_obstacles()
        self.check_clear("starts", self.starts)
        self._check_path_constraints()
        self._check_thrust_reach()

    @property
    def ode_agents(self) -> bool:
        """Whether any agent is an ODE agent (:class:`~ocpar.ocp.MsEndpointShape`)."""
        return bool(self.ode_mask.any())

    @property
    def ode_mask(self) -> np.ndarray:
        """(n,) whether each agent is an ODE agent."""
        shapes = self.shape if isinstance(self.shape, tuple) else (self.shape,)
        ode = np.array([isinstance(s, MsEndpointShape) for s in shapes])
        return ode if isinstance(self.shape, tuple) else np.full(len(self.starts), ode[0])

    @property
    def mixed_kinds(self) -> bool:
        """Whether the fleet mixes DMOC and ODE agents."""
        shapes = self.shape if isinstance(self.shape, tuple) else (self.shape,)
        return len({type(s) for s in shapes}) > 1

    @property
    def node_width(self) -> int:
        """Entries of a node of the fleet's paths: the largest agent's (a mixed fleet's
        narrower paths are padded with NaN in the fleet-wide arrays)."""
        shapes = self.shape if isinstance(self.shape, tuple) else (self.shape,)
        return max(s.node_size for s in set(shapes))

    @property
    def widest_shape(self) -> DmocShape | MsEndpointShape:
        """The first shape of :attr:`node_width` entries (its model names the entries)."""
        shapes = self.shape if isinstance(self.shape, tuple) else (self.shape,)
        return next(s for s in shapes if s.node_size == self.node_width)

    def _check_mixed_boundary(self, n: int, d: int) -> None:
        """A fleet of DMOC and ODE agents: its DMOC agents at rest at both ends, all of their
        configuration the position (nq = d); ``starts`` (n, W) each row its agent's start
        (q_0 or x_0) in its first entries, the rest ignored (NaN); ``final_state`` the ODE
        agents' (:meth:`_check_ode_boundary`); every agent's boundary data of one length."""
        for name in ("start_velocities", "final_velocity", "final_attitude"):
            if getattr(self, name) is not None:
                raise ValueError(f"{name}: a fleet of DMOC and ODE agents takes its DMOC agents "
                                 f"at rest with no attitude entries; leave {name} out")
        sizes = {}
        for shape in set(self.shapes):
            if isinstance(shape, DmocShape) and shape.node_size != d:
                raise ValueError(f"shape: in a fleet of DMOC and ODE agents the DMOC agents' "
                                 f"configuration is their position ({d} entries), got "
                                 f"{shape.node_size}")
            sizes.setdefault(type(shape), set()).add(shape.node_size)
            sizes.setdefault("params", set()).add(shape.n_params)
        if any(len(v) > 1 for v in sizes.values()):
            raise ValueError("shape: a fleet of DMOC and ODE agents needs one state size per "
                             "kind and boundary data of one length (e.g. planar point masses, "
                             "p = (q_0, q̇_0, q_N, q̇_N), and unicycles, p = (x_0, x̄_N))")
        width = self.node_width
        starts = _array_allowing_nan("starts", self.starts, (n, width))
        for shape, agents in self.agents_by_shape().items():
            if not np.all(np.isfinite(starts[agents, :shape.node_size])):
                raise ValueError(f"starts: agent {agents[0]}'s first {shape.node_size} entries "
                                 f"(its start) must be finite")
            starts[agents, shape.node_size:] = np.nan
        object.__setattr__(self, "starts", starts)
        self._check_ode_boundary(n, next(s for s in self.shapes
                                         if isinstance(s, MsEndpointShape)).node_size, d)

    def _check_ode_boundary(self, n: int, nx: int, d: int) -> None:
        """ODE agents' boundary data: no DMOC fields; ``final_state`` (nx − d,) or
        (n, nx − d), finite except at the shape's free end entries (stored with 0 there;
        in a mixed fleet a DMOC agent's row is not read, 0 too)."""
        for name in ("start_velocities", "final_velocity", "final_attitude"):
            if getattr(self, name) is not None:
                raise ValueError(f"{name}: DMOC agents' field; an ODE agent's start is its "
                                 f"whole state (starts) and its end is given by final_state")
        value = np.zeros(nx - d) if self.final_state is None else self.final_state
        try:
            value = np.array(value, float)
        except (TypeError, ValueError):
            raise ValueError(f"final_state: must be numbers, shape ({nx - d},) or "
                             f"({n}, {nx - d})") from None
        if value.shape not in ((nx - d,), (n, nx - d)):
            raise ValueError(f"final_state: must have shape ({nx - d},) or ({n}, {nx - d}) "
                             f"(the end state's entries other than the position), got "
                             f"{value.shape}")
        rest = [i for i in range(nx) if i not in self.position_indices]
        for shape, agents in self.agents_by_shape().items():
            if not isinstance(shape, MsEndpointShape):
                if value.ndim == 2:
                    value[agents] = 0.0   # a DMOC agent's row: not read
                continue
            free = np.flatnonzero(np.isin(rest, shape.free_end))
            if value.ndim == 2:
                value[np.ix_(agents, free)] = 0.0
            else:
                value[free] = 0.0
        if not np.all(np.isfinite(value)):
            raise ValueError("final_state: must be finite at every end entry the shape fixes "
                             "(NaN only at its free_end entries)")
        object.__setattr__(self, "final_state", value)

    @property
    def end_position_params(self) -> np.ndarray:
        """The entries (d,) of an agent's boundary data p that are its end position (what
        the target fixes): DMOC's first d of q_N, an ODE agent's position entries of x̄_N."""
        shape = self.common_shape
        return shape.boundary_size + shape.end_position_entries(self.curve.dim)

    def end_states(self, agents: np.ndarray) -> np.ndarray:
        """ODE agents' end states (len(agents), nx) without their positions (0 there, and at
        free entries): ``final_state`` in the non-position entries."""
        nx = next(s for s in self.shapes if isinstance(s, MsEndpointShape)).node_size
        rest = [i for i in range(nx) if i not in self.position_indices]
        ends = np.zeros((len(agents), nx))
        value = self.final_state
        ends[:, rest] = value[agents] if value.ndim == 2 else value
        return ends

    def reach_sets(self) -> list[tuple[Reach, np.ndarray]]:
        """Each distinct shape's exact rest-to-rest reach set
        (:func:`~ocpar.ocp.reach.rest_to_rest_reach`: box- or norm-limited point masses) with
        its agents that start and end at rest (indices, ascending); shapes without an exact
        set, or without such agents, are left out."""
        cached = self.__dict__.get("_reach_sets")
        if cached is not None:
            return cached
        sets = []
        for shape, agents in self.agents_by_shape().items():
            reach = rest_to_rest_reach(shape)
            if reach is None:
                continue
            rest = agents if self.mixed_kinds else agents[   # (a mixed fleet's: at rest)
                ~np.any(self.start_velocities[agents], axis=1)
                & ~np.any(self.final_velocities(agents), axis=1)]
            if len(rest):
                sets.append((reach, rest))
        object.__setattr__(self, "_reach_sets", sets)   # once per problem (a frozen one)
        return sets

    def limit_label(self, agent: int, reach: Reach) -> str:
        """The field that bounds ``agent``'s reach, for messages (``shape[3].control_bounds``)."""
        where = "shape" if _one(self.shape) else f"shape[{agent}]"
        return f"{where}.{reach.limit}"

    def _check_thrust_reach(self) -> None:
        """Point masses at rest at both ends under box or norm thrust limits reach exactly
        the displacements of their DMOC reach set (:mod:`ocpar.ocp.reach`). An agent from
        whose start no point of the curve is within it has no feasible formation at all:
        ValueError naming its limit. The curve is sampled at :data:`REACH_SAMPLES` points
        and each gap shortened by their largest spacing, so that the check never refuses a
        reachable curve. Surfaces are not checked (no such bound on their sampling); the
        formation as a whole is checked by :func:`ocpar.formation.feasibility.feasible_window`."""
        try:
            sets = self.reach_sets()
        except ValueError as exc:
            raise ValueError(f"shape: {exc}") from None
        if not sets or isinstance(self.curve, Surface):   # no sampling bound on a surface
            return
        if isinstance(self.curve, Slots):
            phi, closed = np.arange(self.curve.count), False
        else:
            phi, closed = np.arange(REACH_SAMPLES) * 2 * np.pi / REACH_SAMPLES, True
        targets = self.final_positions(phi)
        spacing = float(np.max(np.linalg.norm(targets - np.roll(targets, 1, axis=0), axis=1))
                        ) if closed else 0.0
        starts = self.positions(self.starts)
        for reach, rest in sets:
            for block in np.array_split(rest, max(1, -(-len(rest) // REACH_BLOCK))):
                need = reach.need(targets[None] - starts[block][:, None], spacing).min(axis=1)
                if np.any(need > 1):
                    k = int(np.argmax(need))
                    i = int(block[k])
                    raise ValueError(
                        f"{self.limit_label(i, reach)}: agent {i} (mass "
                        f"{self.shapes[i].model.mass:g}) cannot reach any point of the curve "
                        f"from rest to rest in T = {self.shapes[i].duration:g}: the nearest "
                        f"needs {need[k]:.4g} times the thrust its limit allows")

    def _attach_obstacles(self) -> None:
        """Every agent's shape gets the problem's obstacles on its position entries (its
        inner problem imposes them, :mod:`ocpar.ocp.obstacles`; a shape's own are replaced,
        so that ``dataclasses.replace(problem, obstacles=...)`` changes them all), each with
        its own solver (``auto``: ``sqpmethod``; its batch solves without the obstacles
        first, :meth:`~ocpar.ocp.dmoc.DmocTranscription.solve_batch`)."""
        indices = self.position_indices if self.obstacles else ()
        shapes = (self.shape,) if _one(self.shape) else self.shape
        if all((shape.obstacles, shape.obstacle_positions) == (self.obstacles, indices)
               for shape in shapes):
            return   # attached already, or none
        attached = {shape: dataclasses.replace(
            shape, obstacles=self.obstacles, obstacle_positions=indices)
            for shape in set(shapes)}
        object.__setattr__(self, "shape", attached[self.shape] if _one(self.shape)
                           else tuple(attached[shape] for shape in self.shape))

    def _check_path_constraints(self) -> None:
        """Each agent's path constraints and running cost must be finite, with their
        Jacobians, at its start (q_0, q̇_0, u = 0: the inner solves start from zero
        controls), and the constraints of q alone met there (the nodes next to the start
        must meet them); one evaluation per distinct shape. ODE agents' constraints are of
        ``x`` (their start state) and ``u``."""
        for shape, agents in self.agents_by_shape().items():
            size = shape.node_size
            point = ({"x": self.starts[agents, :size]} if isinstance(shape, MsEndpointShape)
                     else {"q": self.starts[agents, :size],
                           "v": (np.zeros((len(agents), size)) if self.mixed_kinds
                                 else self.start_velocities[agents])}) | {
                "u": np.zeros((len(agents), shape.model.nu))}
            where = [f"agent {i}'s start" for i in agents]
            prefix = f"shape{'' if _one(self.shape) else f'[{agents[0]}]'}"
            if getattr(shape, "running_cost", None) is not None:
                check_smooth(shape.running_cost, point, f"{prefix}.running_cost", where)
            for j, constraint in enumerate(shape.path_constraints):
                label = f"{prefix}.path_constraints[{j}] ({constraint.name})"
                check_smooth(constraint, point, label, where)
                excess = constraint.violation(point)
                if not constraint.depends_on("v", "u") and np.max(excess) > CONSTRAINT_TOL:
                    # (an ODE agent's constraint of x alone is imposed from x_1 on: its start
                    # must meet it as a DMOC agent's nodes next to the start must)
                    k = int(np.argmax(excess))
                    raise ValueError(f"starts: agent {agents[k]} breaks {label} by "
                                     f"{excess[k]:.3g}")

    def agents_by_shape(self) -> dict[DmocShape | MsEndpointShape, np.ndarray]:
        """The agents (indices, ascending) of each distinct shape, in order of first use."""
        if _one(self.shape):
            return {self.shape: np.arange(self.agents)}
        groups: dict[DmocShape, list[int]] = {}
        for i, shape in enumerate(self.shape):
            groups.setdefault(shape, []).append(i)
        return {shape: np.array(agents) for shape, agents in groups.items()}

    def check_clear(self, name: str, configurations: np.ndarray) -> None:
        """ValueError naming ``name`` if a position of ``configurations`` (m, nq) lies in an
        obstacle."""
        points = self.positions(configurations)
        for o, obstacle in enumerate(self.obstacles):
            gap, _ = obstacle.clearance(points, points)
            if np.any(gap < 0):
                i = int(np.argmin(gap))
                raise ValueError(f"{name}: agent {i} lies inside obstacles[{o}] "
                                 f"({obstacle.name}) by {-gap[i]:.3g}")

    def clear_start(self, phi0: np.ndarray) -> np.ndarray:
        """A start for the outer problem whose targets clear the obstacles: ``phi0`` (flat)
        if every target of it does by :data:`START_MARGIN`; else, where the coupling's
        solutions through it form a family (a circle's rotation, equal arc length's shift,
        :meth:`~ocpar.formation.couplings.coupling.Coupling.family`), the member with the smallest
        shift |θ| (of :data:`START_SHIFTS`) whose targets do (by the margin if one does,
        else just); else ``phi0`` if its targets are inside none. ValueError (one line,
        naming ``obstacles``) only when no member can avoid them."""
        phi0 = np.asarray(phi0, float).ravel()
        if not self.obstacles or self._targets_clear(phi0[None], START_MARGIN)[0]:
            return phi0
        family = (None if isinstance(self.curve, Slots | Surface)
                  else self.coupling.family(phi0, self.curve))
        if family is not None:
            k = np.arange(1, START_SHIFTS // 2 + 1)
            shifts = 2 * np.pi / START_SHIFTS * np.concatenate([[0], np.column_stack(
                [k, -k]).ravel()])
            members = np.array([family.angles(theta)[0] for theta in shifts])
            for margin in (START_MARGIN, 0.0):
                clear = np.flatnonzero(self._targets_clear(members, margin))
                if len(clear):
                    return members[clear[0]]
        nq = self.common_shape.model.nq
        where = "" if family is None else "; no shift of the formation avoids the obstacles"
        self.check_clear(f"final positions (at the initial angles{where})",
                         self.boundary_params_rows(np.arange(self.agents), phi0)[:, 2 * nq:3 * nq])
        if family is not None:
            raise ValueError("final positions: every shift of the formation puts one inside an "
                             "obstacle")
        return phi0

    def _targets_clear(self, phis: np.ndarray, margin: float) -> np.ndarray:
        """Whether every target z(φ) of each row of ``phis`` (m, n k) clears every obstacle
        by ``margin`` · its scale: (m,)."""
        points = self.final_positions(phis.reshape(-1, *self.parameter_shape[1:]))
        ok = np.ones(len(points), bool)
        for obstacle in self.obstacles:
            gap, _ = obstacle.clearance(points, points)
            ok &= gap >= margin * obstacle.scale
        return ok.reshape(len(phis), -1).all(axis=1)

    def _check_shapes(self) -> None:
        """``shape`` must be a DmocShape of a MechanicalSystem, an MsEndpointShape, or a
        non-empty sequence of one kind of them agreeing on N, T, nq (an ODE's nx), nu and the
        position entries (then stored as a tuple)."""
        shapes = (self.shape,) if _one(self.shape) else self.shape
        if isinstance(shapes, str) or not isinstance(shapes, tuple | list) or not shapes:
            raise ValueError(f"shape: must be a DmocShape, an MsEndpointShape or one per "
                             f"agent, got {type(self.shape).__name__}")
        checked: set[DmocShape | MsEndpointShape] = set()
        first = shapes[0]
        for i, shape in enumerate(shapes):
            label = "shape" if _one(self.shape) else f"shape[{i}]"
            if isinstance(shape, DmocShape | MsEndpointShape) and shape in checked:
                continue
            if not isinstance(shape, DmocShape | MsEndpointShape):
                raise ValueError(f"{label}: must be a DmocShape or an MsEndpointShape, got "
                                 f"{type(shape).__name__}")
            if isinstance(shape, DmocShape) and not isinstance(shape.model, MechanicalSystem):
                raise ValueError(f"{label}: its model is not a MechanicalSystem (needs nq, nu, "
                                 "lagrangian, generalized_force)")
            for what, value in (("intervals", lambda s: s.intervals),
                                ("duration", lambda s: s.duration),
                                ("free_duration", lambda s: getattr(s, "free_duration", False)),
                                ("model.nu", lambda s: s.model.nu),
                                ("model.position_indices",
                                 lambda s: getattr(s.model, "position_indices", None))):
                if value(shape) != value(first):
                    raise ValueError(f"{label}: {what} {value(shape)} differs from shape[0]'s "
                                     f"{value(first)}; a fleet shares N, T, nu and the "
                                     f"position entries")
            if isinstance(shape, DmocShape):
                self._check_model(shape.model, label)
            checked.add(shape)
        if not _one(self.shape):
            object.__setattr__(self, "shape", tuple(shapes))

    @property
    def shapes(self) -> tuple[DmocShape | MsEndpointShape, ...]:
        """Each agent's shape (n,)."""
        if _one(self.shape):
            return (self.shape,) * self.agents
        return self.shape

    @property
    def common_shape(self) -> DmocShape | MsEndpointShape:
        """The first agent's shape: its N, T, nq, nu and position entries are every agent's."""
        return self.shape if _one(self.shape) else self.shape[0]

    def with_shapes(self, change: Callable[[DmocShape], DmocShape]) -> FormationProblem:
        """This problem with ``change`` applied to every agent's shape (e.g. another solver,
        keep-out slots)."""
        shape = (change(self.shape) if _one(self.shape)
                 else tuple(change(s) for s in self.shape))
        return dataclasses.replace(self, shape=shape)

    def _check_model(self, model: MechanicalSystem, label: str) -> None:
        """The model's L(q, q̇) must be a scalar and F(q, u) a column (nq,) of CasADi
        expressions (checked on the first interval's Lagrangian)."""
        q, qdot, u = (ca.SX.sym(name, size) for name, size in
                      (("q", model.nq), ("qdot", model.nq), ("u", model.nu)))
        try:
            lagrangian = ca.SX(model.lagrangian(q, qdot, 0))
            force = ca.SX(model.generalized_force(q, u))
        except Exception as exc:  # a user's model: any failure means "does not evaluate"
            first = str(exc).splitlines()[0] if str(exc) else ""
            raise ValueError(f"{label}: the model's lagrangian or generalized_force does not "
                             f"evaluate on CasADi symbols: {type(exc).__name__}: {first}"
                             ) from None
        if lagrangian.shape != (1, 1) or force.shape != (model.nq, 1):
            raise ValueError(f"{label}: the model's lagrangian must be a scalar and its "
                             f"generalized_force a column of {model.nq}, got shapes "
                             f"{lagrangian.shape} and {force.shape}")
        check_labels(model, model.nq, model.nu, label)

    def _check_holonomic_constraints(self) -> None:
        """Starts and final configurations (at a point of the curve) must satisfy each
        agent's model's c(q) = 0."""
        if self.ode_agents:   # (c(q) = 0 is a mechanical system's)
            return
        end = np.concatenate([self.final_positions(np.zeros(self.parameters))[0],
                              self.final_attitude])
        for shape, agents in self.agents_by_shape().items():
            model = shape.model
            if not getattr(model, "n_constraints", 0):
                continue
            q = ca.SX.sym("q", model.nq)
            c = ca.Function("c", [q], [model.constraints(q)])
            for name, rows in (("starts", self.starts[agents]), ("final_attitude", end[None])):
                residual = np.abs(np.asarray(c(rows.T))).max()
                if not residual <= CONSTRAINT_TOL:
                    raise ValueError(f"{name}: violates the model's holonomic constraints by "
                                     f"{residual:.1e}")

    @property
    def position_indices(self) -> tuple[int, ...]:
        """The configuration entries that are an agent's position in space: the model's
        ``position_indices`` if it has them, else the first ``curve.dim`` entries."""
        indices = getattr(self.common_shape.model, "position_indices", None)
        return tuple(range(self.curve.dim)) if indices is None else tuple(indices)

    def positions(self, trajectories: np.ndarray) -> np.ndarray:
        """The position part (n, N+1, p) of node paths ``trajectories`` (n, N+1, nq)."""
        return np.asarray(trajectories)[..., list(self.position_indices)]

    def closest_approach(self, trajectories: np.ndarray, backend: Backend | None = None
                         ) -> ClosestApproach:
        """The closest approach of any two agents on node paths ``trajectories`` (n, N+1, nq),
        on their piecewise-linear positions over [0, T]
        (:mod:`ocpar.formation.keep_out.separation`; its intervals on the ``backend``'s
        workers if one is given); distance and time NaN, pair (−1, −1) if a path is not
        finite (a failed run)."""
        return self.closest_approach_of(self.positions(trajectories), backend)

    def closest_approach_of(self, positions: np.ndarray, backend: Backend | None = None
                            ) -> ClosestApproach:
        """:meth:`closest_approach` of the agents' positions (n, N+1, d) on the nodes."""
        if not np.all(np.isfinite(positions)):
            return ClosestApproach(math.nan, (-1, -1), math.nan)
        return closest_approach(positions, self.common_shape.duration, backend)

    @property
    def agents(self) -> int:
        return len(self.starts)

    @property
    def on_circle(self) -> bool:
        """True if the curve is a :class:`~ocpar.formation.Circle` (the shortcuts apply)."""
        return isinstance(self.curve, Circle)

    def require_circle(self, what: str) -> None:
        """Raise ValueError unless :attr:`on_circle`: ``what`` relies on the circle's
        equidistant slots and common rotation."""
        if not self.on_circle:
            raise ValueError(f"{what} only applies to a formation on a Circle (equidistant "
                             f"slots, a free common rotation); {self.name!r} ends on a "
                             f"{type(self.curve).__name__}")

    @property
    def parameters(self) -> int:
        """k, each agent's parameters on the target: 2 on a surface, else 1 (an angle on a
        curve, a slot index onto slots)."""
        return PARAMETERS if isinstance(self.curve, Surface) else 1

    @property
    def parameter_shape(self) -> tuple[int, ...]:
        """The shape of φ: (n,), or (n, 2) on a surface."""
        return (self.agents,) if self.parameters == 1 else (self.agents, self.parameters)

    def final_positions(self, phi: np.ndarray) -> np.ndarray:
        """Points z(φ) on the curve at angles φ (n,) rad, on a surface at parameters φ
        (n, 2) (or flat, 2n), or the slots φ (n,): shape (n, d)."""
        if isinstance(self.curve, Slots):
            return self.curve.at(phi)
        if isinstance(self.curve, Surface):
            return self.curve.points(np.reshape(phi, (-1, PARAMETERS)))
        return self.curve.points(phi)

    def final_position_derivatives(self, phi: np.ndarray) -> np.ndarray:
        """d(final configuration q_N)/dφ_i for each agent: shape (n, nq), z′(φ_i) in the
        position entries and zero beyond."""
        if isinstance(self.curve, Slots):
            raise ValueError("slots have no parameters to differentiate in")
        along = self.curve.tangents(phi)
        return np.hstack([along, np.zeros((len(along),
                                           self.common_shape.node_size - along.shape[1]))])

    def final_velocities(self, agents: np.ndarray) -> np.ndarray:
        """Final velocities (len(agents), nq) of the agents ``agents``."""
        velocity = self.final_velocity
        return velocity[agents] if velocity.ndim == 2 \
            else np.broadcast_to(velocity, (len(agents), len(velocity)))

    def boundary_params(self, i: int, phi_i: float) -> np.ndarray:
        """DMOC boundary data p = (q_0, q̇_0, q_N, q̇_N) of agent i ending at angle φ_i."""
        return self.boundary_params_rows(np.array([i]), np.array([phi_i]))[0]

    def boundary_params_rows(self, agents: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Boundary data (len(agents), n_params): row k for agent ``agents[k]`` ending at
        ``phi[k]`` (rad): DMOC's (q_0, q̇_0, q_N, q̇_N), with T (the shapes' ``duration``)
        appended where their duration is free (``DmocShape.free_duration``); an ODE agent's
        (x_0, x̄_N), T likewise."""
        agents = np.asarray(agents, dtype=np.intp)
        m = len(agents)
        if self.mixed_kinds:   # DMOC agents at rest, all configuration the position
            ode = self.ode_mask[agents]
            shape = self.common_shape
            rows = np.full((m, shape.n_params), shape.duration)   # T last where it is free
            width = shape.n_params - int(shape.free_duration)
            targets = self.final_positions(phi)
            if ode.any():
                ends = self.end_states(agents[ode])
                ends[:, list(self.position_indices)] = targets[ode]
                nx = ends.shape[1]
                rows[ode, :width] = np.hstack([self.starts[agents[ode], :nx], ends])
            if (~ode).any():
                d = self.curve.dim
                zero = np.zeros(((~ode).sum(), d))
                rows[~ode, :width] = np.hstack([self.starts[agents[~ode], :d], zero,
                                                targets[~ode], zero])
            return rows
        if self.ode_agents:
            ends = self.end_states(agents)
            ends[:, list(self.position_indices)] = self.final_positions(phi)
            shape = self.common_shape
            return np.hstack([self.starts[agents], ends,
                              np.full((m, int(shape.free_duration)), shape.duration)])
        shape = self.common_shape
        return np.hstack([self.starts[agents], self.start_velocities[agents],
                          self.final_positions(phi),
                          np.broadcast_to(self.final_attitude, (m, len(self.final_attitude))),
                          self.final_velocities(agents),
                          np.full((m, int(shape.free_duration)), shape.duration)])

    def tasks_for(self, agents: np.ndarray, phi: np.ndarray,
                  warm_starts: np.ndarray | None = None) -> Columns:
        """Task k: agent ``agents[k]`` ending at angle ``phi[k]`` (rad), in columnar form (a
        :class:`~ocpar.bsp.columns.Columns` of :class:`~ocpar.ocp.OcpTask`: the shared
        shape, the (len(agents), 4 nq) boundary data of :meth:`boundary_params_rows`, and
        optional warm starts, one row per task, to retry from if a first attempt fails)."""
        params = self.boundary_params_rows(agents, phi)
        return self.task_columns(agents, params, fallback=warm_starts)

    def task_columns(self, agents: np.ndarray, params: np.ndarray,
                     warm_start: np.ndarray | None = None,
                     fallback: np.ndarray | None = None) -> Columns:
        """Columnar :class:`~ocpar.ocp.OcpTask` rows for ``agents`` with parameters
        ``params`` (len(agents), n_params) and optional warm starts and fallbacks (one row
        per task), each on its agent's shape (one shared column unless the fleet is
        mixed)."""
        columns = Columns.of(OcpTask, len(params), shape=self.common_shape, params=params,
                             warm_start=warm_start, multipliers=None, fallback=fallback)
        if not _one(self.shape):
            shapes = self.shape
            columns.fields["shape"] = (LISTED, [shapes[i] for i in np.asarray(agents).tolist()])
        return columns

    def tasks(self, phi: np.ndarray, warm_starts: np.ndarray | None = None) -> Columns:
        """One inner DMOC task per agent, agent i ending at φ_i (see :meth:`tasks_for`)."""
        return self.tasks_for(np.arange(self.agents), phi, warm_starts)

    def initial_phi(self) -> np.ndarray:
        """The documented initial guess for φ (rad); onto slots, the slot indices minimising
        Σ_i |start position_i − slot|² (:func:`~ocpar.formation.targets.slots.nearest_assignment`);
        on a surface (n, 2), see :meth:`_initial_on_surface`.

        With the start positions projected into the curve's plane (coordinates along the
        axes of :meth:`~ocpar.formation.Curve.frame`, relative to its centre), the agents are
        ranked by their position along the counter-clockwise tangent at θ_c, the polar angle
        of the start centroid seen from the centre, and placed equidistantly in arc length,
        counter-clockwise in that order, centred on φ_c, the parameter of the curve's point
        seen at θ_c (:meth:`~ocpar.formation.Curve.parameter_at`): agent i a fraction
        (rank_i − (n−1)/2)/n of the curve's length on from φ_c
        (:meth:`~ocpar.formation.Curve.spread`). On a circle φ_c = θ_c and
        φ_i = θ_c + 2π (rank_i − (n−1)/2) / n, which satisfies g(φ) = 0. On any other curve
        these angles are then projected onto the coupling
        (:meth:`~ocpar.formation.couplings.coupling.Coupling.project`; for the potential the local
        minimum of G they lead to, :func:`~ocpar.formation.couplings.potential.relax`: g(φ) = 0 has
        isolated solutions there, so the guess is the formation itself), and the hierarchical
        and the monolithic mode start from the same feasible point. In the paper's example
        θ_c = −3π/4 and the tangent points along +x, so agents sorted by x go
        counter-clockwise. This ordering decides which local optimum is found (see
        :mod:`ocpar.formation.ordering` on a circle).
        """
        if isinstance(self.curve, Slots):   # CAPT's assignment, by distance
            return nearest_assignment(self.positions(self.starts), self.curve).astype(float)
        if isinstance(self.curve, Surface):
            return self._initial_on_surface()
        n = self.agents
        centre, axes = self.curve.frame()
        in_plane = (self.starts[:, : self.curve.dim] - centre) @ axes.T
        offset = in_plane.mean(axis=0)
        theta_c = float(np.arctan2(offset[1], offset[0]))
        tangent = np.array([-np.sin(theta_c), np.cos(theta_c)])
        rank = np.empty(n)
        rank[np.argsort(in_plane @ tangent, kind="stable")] = np.arange(n)
        guess = self.curve.spread(self.curve.parameter_at(theta_c), (rank - (n - 1) / 2) / n)
        return self.coupling.project(guess, self.curve)

    def _initial_on_surface(self) -> np.ndarray:
        """On a surface (n, 2): the points seen from its centre along n evenly spread
        directions (:func:`~ocpar.formation.targets.surface.fibonacci_directions`), each agent
        taking
        one by CAPT's assignment (Σ_i |start_i − point|² minimal), then projected onto the
        coupling (for the potential, relaxed to the local minimum of G it leads to)."""
        n = self.agents
        candidates = self.curve.parameters_toward(fibonacci_directions(n))
        slots = Slots(self.curve.points(candidates))
        chosen = nearest_assignment(self.positions(self.starts), slots)
        guess = candidates[chosen].ravel()
        return self.coupling.project(guess, self.curve).reshape(n, PARAMETERS)
