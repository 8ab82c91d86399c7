"""The formation reconfiguration problem: n agents, fixed starts, final formation on a curve.

Agent i is any Lagrangian mechanical system (:class:`~ocpar.models.MechanicalSystem`: L(q, q̇),
optionally time-dependent per DMOC interval, generalised force F(q, u), optional holonomic
constraints c(q) = 0), the same model for all agents, transcribed by DMOC with the problem's
``shape`` (N intervals over the horizon T). It starts in configuration ``starts[i]`` with
velocity ``start_velocities[i]`` and must end, after T, with its position (the first
d = ``curve.dim`` entries of its configuration) at z(φ_i) on the closed curve z, the rest of
its configuration equal to ``final_attitude`` and its velocity ``final_velocity``, minimising
∫|u|² dt. The angles φ are chosen by the outer problem subject to the coupling g(φ) = 0
(:mod:`ocpar.formation.potential`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.bsp.columns import Columns
from ocpar.formation.curve import Circle, Curve
from ocpar.formation.potential import relax
from ocpar.formation.separation import ClosestApproach, closest_approach
from ocpar.models import MechanicalSystem
from ocpar.ocp import DmocShape, OcpTask

#: Boundary configurations must satisfy the model's holonomic constraints to this tolerance.
CONSTRAINT_TOL = 1e-8


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

    ``name`` labels results; ``shape`` the DMOC shape (model, N, horizon T); ``curve`` the
    final formation's curve (:class:`~ocpar.formation.Circle`,
    :class:`~ocpar.formation.Ellipse`, :class:`~ocpar.formation.PlaneCurve`,
    :class:`~ocpar.formation.ParametricCurve`, or a user's :class:`~ocpar.formation.Curve`).
    Shapes, with n agents (n ≥ 2), nq the model's configuration size and d = ``curve.dim``
    ≤ nq: ``starts`` (n, nq); ``start_velocities`` (n, nq), default at rest;
    ``final_velocity`` (nq,) common to all or (n, nq) per agent, default at rest;
    ``final_attitude`` (nq − d,) the configuration entries after the position (none for
    point masses, e.g. a unit quaternion for rigid bodies). Units are the model's.
    """

    name: str
    shape: DmocShape
    curve: Curve
    starts: np.ndarray
    start_velocities: np.ndarray | None = None
    final_velocity: np.ndarray | None = None
    final_attitude: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.shape, DmocShape):
            raise ValueError(f"shape: must be a DmocShape, got {type(self.shape).__name__}")
        if not isinstance(self.shape.model, MechanicalSystem):
            raise ValueError("shape: its model is not a MechanicalSystem (needs nq, nu, "
                             "lagrangian, generalized_force)")
        if not isinstance(self.curve, Curve):
            raise ValueError(f"curve: must be a Curve (Circle, Ellipse, PlaneCurve, "
                             f"ParametricCurve), got {type(self.curve).__name__}")
        self._check_model()
        self.curve.check()  # built-in curves checked themselves; a user's subclass may not
        nq, d = self.shape.model.nq, self.curve.dim
        if d > nq:
            raise ValueError(f"curve: lies in {d}-D but the model's configuration has {nq} "
                             "entries")
        if np.ndim(np.asarray(self.starts, dtype=object)) != 2:
            raise ValueError(f"starts: must have shape (n, {nq}), one row per agent")
        n = len(self.starts)
        if n < 2:
            raise ValueError(f"starts: a formation needs at least 2 agents, got {n}")
        fields = {
            "starts": (self.starts, (n, nq)),
            "start_velocities": (np.zeros((n, nq)) if self.start_velocities is None
                                 else self.start_velocities, (n, nq)),
            "final_attitude": (np.zeros(0) if self.final_attitude is None and nq == d
                               else self.final_attitude, (nq - d,)),
        }
        final_velocity = np.zeros(nq) if self.final_velocity is None else self.final_velocity
        fields["final_velocity"] = (final_velocity, (n, nq) if np.ndim(final_velocity) == 2
                                    else (nq,))
        for name, (value, shape) in fields.items():
            if value is None:
                raise ValueError(f"{name}: required ({nq - d} configuration entries after the "
                                 f"{d} position entries)")
            object.__setattr__(self, name, _array(name, value, shape))
        self._check_holonomic_constraints()
        indices = self.position_indices
        if not indices or len(set(indices)) != len(indices) or not all(
                isinstance(i, (int, np.integer)) and 0 <= i < nq for i in indices):
            raise ValueError(f"shape: the model's position_indices must be distinct entries "
                             f"of its {nq} configuration entries, got {indices}")

    def _check_model(self) -> None:
        """The model's L(q, q̇) must be a scalar and F(q, u) a column (nq,) of CasADi
        expressions (checked on the first interval's Lagrangian)."""
        model = self.shape.model
        q, qdot, u = (ca.SX.sym(name, size) for name, size in
                      (("q", model.nq), ("qdot", model.nq), ("u", model.nu)))
        try:
            lagrangian = ca.SX(model.lagrangian(q, qdot, 0))
            force = ca.SX(model.generalized_force(q, u))
        except Exception as exc:  # a user's model: any failure means "does not evaluate"
            first = str(exc).splitlines()[0] if str(exc) else ""
            raise ValueError(f"shape: the model's lagrangian or generalized_force does not "
                             f"evaluate on CasADi symbols: {type(exc).__name__}: {first}"
                             ) from None
        if lagrangian.shape != (1, 1) or force.shape != (model.nq, 1):
            raise ValueError(f"shape: the model's lagrangian must be a scalar and its "
                             f"generalized_force a column of {model.nq}, got shapes "
                             f"{lagrangian.shape} and {force.shape}")

    def _check_holonomic_constraints(self) -> None:
        """Starts and final configurations (at a point of the curve) must satisfy c(q) = 0."""
        model = self.shape.model
        if not getattr(model, "n_constraints", 0):
            return
        q = ca.SX.sym("q", model.nq)
        c = ca.Function("c", [q], [model.constraints(q)])
        end = np.concatenate([self.curve.points(np.zeros(1))[0], self.final_attitude])
        for name, rows in (("starts", self.starts), ("final_attitude", end[None, :])):
            residual = np.abs(np.asarray(c(rows.T))).max()
            if not residual <= CONSTRAINT_TOL:
                raise ValueError(f"{name}: violates the model's holonomic constraints by "
                                 f"{residual:.1e}")

    @property
    def position_indices(self) -> tuple[int, ...]:
        """The configuration entries that are an agent's position in space: the model's
        ``position_indices`` if it has them, else the first ``curve.dim`` entries."""
        indices = getattr(self.shape.model, "position_indices", None)
        return tuple(range(self.curve.dim)) if indices is None else tuple(indices)

    def positions(self, trajectories: np.ndarray) -> np.ndarray:
        """The position part (n, N+1, p) of node paths ``trajectories`` (n, N+1, nq)."""
        return np.asarray(trajectories)[..., list(self.position_indices)]

    def closest_approach(self, trajectories: np.ndarray) -> ClosestApproach:
        """The closest approach of any two agents on node paths ``trajectories`` (n, N+1, nq),
        on their piecewise-linear positions over [0, T] (:mod:`ocpar.formation.separation`);
        distance and time NaN, pair (−1, −1) if a path is not finite (a failed run)."""
        positions = self.positions(trajectories)
        if not np.all(np.isfinite(positions)):
            return ClosestApproach(math.nan, (-1, -1), math.nan)
        return closest_approach(positions, self.shape.duration)

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

    def final_positions(self, phi: np.ndarray) -> np.ndarray:
        """Points z(φ) on the curve at angles φ (n,) rad: shape (n, d)."""
        return self.curve.points(phi)

    def final_position_derivatives(self, phi: np.ndarray) -> np.ndarray:
        """d(final configuration q_N)/dφ_i for each agent: shape (n, nq), z′(φ_i) in the
        position entries and zero beyond."""
        along = self.curve.tangents(phi)
        return np.hstack([along, np.zeros((len(along), len(self.final_attitude)))])

    def final_velocities(self, agents: np.ndarray) -> np.ndarray:
        """Final velocities (len(agents), nq) of the agents ``agents``."""
        velocity = self.final_velocity
        return velocity[agents] if velocity.ndim == 2 \
            else np.broadcast_to(velocity, (len(agents), len(velocity)))

    def boundary_params(self, i: int, phi_i: float) -> np.ndarray:
        """DMOC boundary data p = (q_0, q̇_0, q_N, q̇_N) of agent i ending at angle φ_i."""
        return self.boundary_params_rows(np.array([i]), np.array([phi_i]))[0]

    def boundary_params_rows(self, agents: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Boundary data (len(agents), 4 nq): row k for agent ``agents[k]`` ending at
        ``phi[k]`` (rad)."""
        agents = np.asarray(agents, dtype=np.intp)
        m = len(agents)
        return np.hstack([self.starts[agents], self.start_velocities[agents],
                          self.final_positions(phi),
                          np.broadcast_to(self.final_attitude, (m, len(self.final_attitude))),
                          self.final_velocities(agents)])

    def tasks_for(self, agents: np.ndarray, phi: np.ndarray,
                  warm_starts: np.ndarray | None = None) -> Columns:
        """Task k: agent ``agents[k]`` ending at angle ``phi[k]`` (rad), in columnar form (a
        :class:`~ocpar.bsp.columns.Columns` of :class:`~ocpar.ocp.OcpTask`: the shared
        shape, the (len(agents), 4 nq) boundary data of :meth:`boundary_params_rows`, and
        optional warm starts, one row per task, to retry from if a first attempt fails)."""
        params = self.boundary_params_rows(agents, phi)
        return Columns.of(OcpTask, len(params), shape=self.shape, params=params,
                          warm_start=None, multipliers=None, fallback=warm_starts)

    def tasks(self, phi: np.ndarray, warm_starts: np.ndarray | None = None) -> Columns:
        """One inner DMOC task per agent, agent i ending at φ_i (see :meth:`tasks_for`)."""
        return self.tasks_for(np.arange(self.agents), phi, warm_starts)

    def initial_phi(self) -> np.ndarray:
        """The documented initial guess for φ (rad).

        With the start positions projected into the curve's plane (coordinates along the
        axes of :meth:`~ocpar.formation.Curve.frame`, relative to its centre), the agents are
        ranked by their position along the counter-clockwise tangent at θ_c, the polar angle
        of the start centroid seen from the centre, and placed equidistantly in arc length,
        counter-clockwise in that order, centred on φ_c, the parameter of the curve's point
        seen at θ_c (:meth:`~ocpar.formation.Curve.parameter_at`): agent i a fraction
        (rank_i − (n−1)/2)/n of the curve's length on from φ_c
        (:meth:`~ocpar.formation.Curve.spread`). On a circle φ_c = θ_c and
        φ_i = θ_c + 2π (rank_i − (n−1)/2) / n, which satisfies g(φ) = 0. On any other curve
        these angles are then relaxed to the local minimum of the potential G they lead to
        (:func:`~ocpar.formation.potential.relax`): there g(φ) = 0 has isolated solutions
        only, so the guess is the formation itself, and the hierarchical and the monolithic
        mode start from the same feasible point. In the paper's example θ_c = −3π/4 and the
        tangent points along +x, so agents sorted by x go counter-clockwise. This ordering
        decides which local optimum is found (see :mod:`ocpar.formation.ordering` on a
        circle).
        """
        n = self.agents
        centre, axes = self.curve.frame()
        in_plane = (self.starts[:, : self.curve.dim] - centre) @ axes.T
        offset = in_plane.mean(axis=0)
        theta_c = float(np.arctan2(offset[1], offset[0]))
        tangent = np.array([-np.sin(theta_c), np.cos(theta_c)])
        rank = np.empty(n)
        rank[np.argsort(in_plane @ tangent, kind="stable")] = np.arange(n)
        guess = self.curve.spread(self.curve.parameter_at(theta_c), (rank - (n - 1) / 2) / n)
        return relax(guess, self.curve)
