"""Verification of a returned formation, independent of how it was found.

:func:`verify_formation` reads only what a run returns, the node paths (n, N+1, nq), the
interval controls (n, N, nu) and the parameters φ, and the problem's data. It checks:

* ``target``: each returned end position lies on the target: its parameters are *located*
  from the point itself (:meth:`~ocpar.formation.Curve.locate`: closed form on a circle,
  Newton on other curves with φ only as the hint; a surface's inverse chart), within
  :data:`TARGET_RTOL` of the target's size; onto slots, the distance to the assigned slot;
* ``coupling``: the coupling residual max_k |c_k| at the *located* parameters
  (:func:`coupling_residual`), ≤ :data:`COUPLING_TOL`; onto slots, no slot taken twice; the
  potential on a surface in space, chart-free: max_i |tangential ∇G_i| / max_i |∇G_i| at the
  end points (:func:`~ocpar.formation.couplings.potential.surface_criticality`);
* ``start``, ``attitude``: the paths start at the start configurations and end in the final
  attitude (the entries after the position);
* ``momentum``: the start and end velocities, through DMOC's boundary equations (the
  discrete Legendre transform, :mod:`ocpar.ocp.dmoc`): D2L(q_0, q̇_0) + D1L_d(q_0, q_1) +
  f⁻_0 = 0 and −D2L(q_N, q̇_N) + D2L_d(q_{N−1}, q_N) + f⁺_{N−1} = 0 on the returned nodes and
  controls with the problem's q̇_0, q̇_N (the holonomic reactions projected out), built
  here from the model's Lagrangian and force;
* ``dynamics``: DMOC's interior equations, the discrete Euler–Lagrange equations with forces
  D2L_d(q_{k−1}, q_k) + D1L_d(q_k, q_{k+1}) + f⁺_{k−1} + f⁻_k = 0 at every inner node
  k = 1 … N−1 (the holonomic reactions projected out, and c(q_k) = 0 there), on the returned
  nodes and controls, built here the same way;
* ``dynamics`` of an ODE agent (:class:`~ocpar.ocp.MsEndpointShape`): the shooting
  residuals, each returned interval's controls re-integrated from its returned start node by
  the shape's integrator (numpy code here, on the model's f), against the next node;
  ``start`` its start state, ``attitude`` the end entries its shape fixes other than the
  position; ``momentum`` does not apply (0);
* ``control_bounds``, ``path_constraints``: every bound and path constraint of each agent's
  shape at the points where DMOC imposes them: controls u_k; rows of ``q`` alone at the
  inner nodes, rows of ``v``/``u`` at (q_{k+½}, (q_{k+1} − q_k)/h, u_k);
* ``obstacles``: the clearance of the continuous paths from the problem's obstacles
  (:func:`~ocpar.formation.keep_out.obstacles.closest_obstacle`): a DMOC path's segments;
  an ODE agent's path re-integrated, each of its integrator's sub-steps by
  :data:`DENSE_SUBSTEPS` finer steps (:func:`checked_positions`), as a polyline;
* ``separation`` (with a required one): the closest approach of any two agents on the
  continuous paths (:func:`~ocpar.formation.keep_out.separation.closest_approach`, always
  measured; ODE agents' on the polyline through their nodes, :data:`DENSE_SUBSTEPS`, where
  no separation is required, else on the dense re-integration the obstacles' clearance is
  checked on).

A check that does not apply (no constraint, no obstacle) is not made. Near-collisions are
reported, not failed: a closest approach below :data:`NEAR_COLLISION_FRACTION` of the
formation's spacing without a required separation (the answer is the optimum without one).
Every check is vectorised over the agents (O(n), the closest approach O(n log n)).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.couplings.coupling import PotentialCoupling
from ocpar.formation.couplings.potential import (
    circle_coupling,
    surface_criticality,
    within_expansion,
)
from ocpar.formation.keep_out.obstacles import CLEARANCE_TOL, Clearance, closest_obstacle
from ocpar.formation.keep_out.separation import SEPARATION_RTOL, ClosestApproach, closest_pair
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import Surface
from ocpar.ocp import DmocShape, MsEndpointShape
from ocpar.ocp.columns_eval import evaluate_columns
from ocpar.ocp.constraints import CompiledConstraint
from ocpar.ocp.contract import Shape

#: An end position counts as on the target within this fraction of the target's size (a
#: curve's or surface's length scale, the slots' extent): the inner problems take q_N as data,
#: so a returned end point equals z(φ) to rounding (~1e-16); 1e-9 leaves room for the
#: located parameters' rounding on any curve.
TARGET_RTOL = 1e-9
#: The coupling holds where max_k |c_k| ≤ this at the located parameters: c is scaled
#: (ℓ²/n³ dG/dφ, O(1)), and this is the tolerance of the coupling's own projection
#: (:data:`~ocpar.formation.couplings.coupling.PROJECTION_TOL`); converged runs reach ~1e-12 or
#: less.
COUPLING_TOL = 1e-8
#: Start configuration and final attitude are every inner problem's data: equal to rounding,
#: relative to 1 + |q| (1e-9 leaves room for a model's unit-quaternion normalisation).
BOUNDARY_RTOL = 1e-9
#: DMOC's boundary momentum and interior equations hold to this, relative to 1 + the size of
#: their terms:
#: the inner solvers stop at a KKT residual of ~1e-10 (``kkt_tol``, IPOPT's tol 1e-12 scaled).
MOMENTUM_RTOL = 1e-7
#: Bounds and path rows hold to this, relative to max(1, |bound|): the solvers' accuracy
#: (IPOPT's tol 1e-12 scaled, ``kkt_tol`` 1e-10) with room for the constraint's scaling.
CONSTRAINT_RTOL = 1e-7
#: A closest approach below this fraction of the formation's spacing (the smallest distance
#: between two target points) is a near-collision: 1 %, i.e. two agents pass each other a
#: hundred times closer than the formation will keep them (the 10,000-mass circle's
#: 1.93e-6 against a spacing of 6.3e-3, 0.03 %, is one; crossing paths that miss each other
#: by a tenth of the spacing are not).
NEAR_COLLISION_FRACTION = 0.01

#: Up to this many agents the coupling residual is the direct O(n²) sum (~5 ms at 1000
#: agents); above it, on a circle, the O(n log n) expansion about equidistant angles
#: (:func:`~ocpar.formation.couplings.potential.circle_coupling`: ~0.03 s at 100,000 agents) where
#: it applies...
DIRECT_COUPLING_MAX_AGENTS = 1_000
#: ... and where it does not (angles far from equidistant ones), the direct sum up to this
#: many agents on a circle and NaN above (3 s at 10,000 agents, ~5 min at 100,000); the
#: equidistance error, zero exactly where c(φ) is, is reported too.
COUPLING_CHECK_MAX_AGENTS = 20_000

#: What each check says when it fails ({agent}, {value}, {tolerance}, {where}).
FAILURE_WORDS = {
    "target": "agent {agent}'s end point lies {value:.3g} (relative) off the target",
    "coupling": "the coupling residual at the located end points is {value:.3g}",
    "slots_shared": "{value:.0f} agent(s) share a slot with another",
    "start": "agent {agent}'s path does not start at its start configuration "
             "({value:.3g} relative)",
    "attitude": "agent {agent}'s path does not end in the final attitude ({value:.3g} "
                "relative)",
    "momentum": "agent {agent}'s path misses its boundary velocities: DMOC's boundary "
                "momentum residual {value:.3g} (relative)",
    "dynamics": "agent {agent}'s path breaks its dynamics: DMOC's interior equations' or "
                "the shooting residual {value:.3g} (relative)",
    "control_bounds": "agent {agent}'s controls break control_bounds by {value:.3g} "
                      "(relative)",
    "path_constraints": "agent {agent}'s path breaks {where} by {value:.3g} (relative)",
    "obstacles": "agent {agent}'s path enters {where} by {value:.3g}",
    "separation": "agents {where} come {value:.3g} closer than the required separation",
}


@dataclass(frozen=True)
class Check:
    """One check's worst ``value`` over the agents (a violation: ≥ 0, relative where the
    tolerance is), the ``agent`` where it occurs (−1: the formation as a whole), the
    ``tolerance`` it must not exceed and ``where`` (which constraint or obstacle, '' if
    none). NaN fails."""

    value: float
    agent: int
    tolerance: float
    where: str = ""

    @property
    def passed(self) -> bool:
        return bool(self.value <= self.tolerance)

    def to_dict(self) -> dict:
        return {"worst": self.value if math.isfinite(self.value) else None,
                "agent": self.agent if self.agent >= 0 else None,
                "tolerance": self.tolerance, "passed": self.passed,
                **({"where": self.where} if self.where else {})}


@dataclass(frozen=True)
class Verification:
    """What :func:`verify_formation` found: ``checks`` by name (module docstring);
    ``parameters`` the located parameters (the shape of φ); ``coupling_residual`` max_k
    |c_k| at them (onto slots: agents sharing a slot); ``closest`` the closest approach of
    any two agents; ``spacing`` the smallest distance between two target points (length
    unit; inf with one agent); ``obstacle_clearance`` (None without obstacles);
    ``near_collision`` (None, or where and how close, :data:`NEAR_COLLISION_FRACTION`);
    ``time_s`` how long the checks took (s); ``agent_violation`` (n,) per agent the largest
    relative residual of its own checks (start, attitude, momentum, dynamics, control bounds, path
    constraints; NaN for a path that is not finite)."""

    checks: dict[str, Check]
    parameters: np.ndarray
    coupling_residual: float
    closest: ClosestApproach
    spacing: float
    obstacle_clearance: Clearance | None
    near_collision: dict | None
    time_s: float
    agent_violation: np.ndarray

    @property
    def passed(self) -> bool:
        return all(check.passed for check in self.checks.values())

    @property
    def failures(self) -> list[str]:
        """One line per failed check."""
        return self.failures_except(())

    def failures_except(self, known: tuple[str, ...]) -> list[str]:
        """One line per failed check but those named in ``known``."""
        return [FAILURE_WORDS[name].format(agent=c.agent, value=c.value, where=c.where)
                + f" (tolerance {c.tolerance:.1e})"
                for name, c in self.checks.items() if not c.passed and name not in known]

    def failure_words(self, known: tuple[str, ...] = ()) -> str:
        """'<first failure> (and k more)' ('' if none failed), leaving out the checks named in
        ``known``."""
        failures = self.failures_except(known)
        if not failures:
            return ""
        more = f" (and {len(failures) - 1} more)" if len(failures) > 1 else ""
        return failures[0] + more

    def to_dict(self) -> dict:
        """The ``verification`` block of ``result.json`` (without :attr:`time_s`: the file's
        timings are its ``wall_time_s`` and ``trace``, and its other numbers do not depend on
        where or how fast it ran)."""
        return {"passed": self.passed, "failures": self.failures,
                "checks": {name: c.to_dict() for name, c in self.checks.items()},
                "spacing": self.spacing if math.isfinite(self.spacing) else None}


def coupling_residual(problem: FormationProblem, phi: np.ndarray) -> float:
    """max_k |c_k(φ)|: the scaled coupling as the outer problem imposes it
    (:meth:`~ocpar.formation.couplings.coupling.Coupling.residual`; the potential on a circle with
    more than :data:`DIRECT_COUPLING_MAX_AGENTS` agents near equidistant angles
    :func:`~ocpar.formation.couplings.potential.circle_coupling`); onto slots, how many agents
    share a
    slot with another (0: the assignment's coupling holds); NaN if φ is not finite, or on a
    circle with more than :data:`COUPLING_CHECK_MAX_AGENTS` agents far from equidistant."""
    if isinstance(problem.curve, Slots):   # the coupling: no slot taken twice
        return float(phi.size - np.unique(phi).size)
    if not np.all(np.isfinite(phi)):
        return float("nan")
    if problem.on_circle and problem.coupling == PotentialCoupling() \
            and phi.size > DIRECT_COUPLING_MAX_AGENTS:
        if within_expansion(phi):
            return float(np.max(np.abs(circle_coupling(phi))))
        if phi.size > COUPLING_CHECK_MAX_AGENTS:
            return float("nan")
    return float(np.max(np.abs(problem.coupling.residual(phi, problem.curve))))


def _worst(values: np.ndarray, tolerance: float, agents: np.ndarray | None = None,
           where: str = "") -> Check:
    """The largest of per-agent ``values`` (n,) (NaN first), as a :class:`Check`; ``agents``
    maps their positions to agent indices (default: the identity)."""
    values = np.asarray(values, float)
    if not values.size:
        return Check(0.0, -1, tolerance, where)
    k = int(np.argmax(np.where(np.isnan(values), np.inf, values)))
    agent = int(k if agents is None else agents[k])
    return Check(float(values[k]), agent, tolerance, where)


def _relative(gap: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """max over the last axis of |gap| / (1 + |reference|): (n,) from (n, m)."""
    if not gap.shape[-1]:
        return np.zeros(gap.shape[0])
    return np.max(np.abs(gap) / (1.0 + np.abs(reference)), axis=-1)


@lru_cache(maxsize=64)
def _boundary_terms(shape: DmocShape) -> ca.Function:
    """(q_0, q_1, q_{N−1}, q_N, u_0, u_{N−1}, q̇_0, q̇_N, h) ↦ the terms of DMOC's first
    equation, D2L(q_0, q̇_0), D1L_d(q_0, q_1), f⁻_0, and of its last, −D2L(q_N, q̇_N),
    D2L_d(q_{N−1}, q_N), f⁺_{N−1} (nq each, without the reactions), and the holonomic
    constraints' gradients ∇c(q_0)ᵀ, ∇c(q_N)ᵀ (nq × nc each, flattened), from the model's
    Lagrangian and force (:mod:`ocpar.ocp.dmoc`), h the step (an input: an agent's own
    T/N)."""
    model, n = shape.model, shape.intervals
    nq, nu, h = model.nq, model.nu, ca.SX.sym("h")
    last = n - 1 if getattr(model, "time_dependent", False) else 0
    q0, q1, qm, qn, v0, vn = (ca.SX.sym(name, nq) for name in ("q0", "q1", "qm", "qn",
                                                                "v0", "vn"))
    u0, um = ca.SX.sym("u0", nu), ca.SX.sym("um", nu)

    def discrete_lagrangian(a: ca.SX, b: ca.SX, k: int) -> ca.SX:
        return h * model.lagrangian((a + b) / 2, (b - a) / h, k)

    terms = [ca.gradient(model.lagrangian(q0, v0, 0), v0),
             ca.gradient(discrete_lagrangian(q0, q1, 0), q0),
             0.5 * h * model.generalized_force((q0 + q1) / 2, u0),
             -ca.gradient(model.lagrangian(qn, vn, last), vn),
             ca.gradient(discrete_lagrangian(qm, qn, last), qn),
             0.5 * h * model.generalized_force((qm + qn) / 2, um)]
    nc = getattr(model, "n_constraints", 0)
    grads = ([ca.vec(ca.jacobian(model.constraints(q), q).T) for q in (q0, qn)] if nc
             else [ca.SX(0, 1), ca.SX(0, 1)])
    return ca.Function("boundary", [q0, q1, qm, qn, u0, um, v0, vn, h], [*terms, *grads])


@lru_cache(maxsize=64)
def _interior_terms(shape: DmocShape, k: int) -> ca.Function:
    """(q_{k−1}, q_k, q_{k+1}, u_{k−1}, u_k, h) ↦ the terms of DMOC's k-th interior equation,
    D2L_d(q_{k−1}, q_k), D1L_d(q_k, q_{k+1}), f⁺_{k−1}, f⁻_k (nq each, without the
    reactions), the holonomic constraints' gradient ∇c(q_k)ᵀ (nq × nc, flattened) and c(q_k)
    (nc), from the model's Lagrangian and force (:mod:`ocpar.ocp.dmoc`); ``k`` names the
    intervals' Lagrangians of a time-dependent model (0 otherwise: one for all); h the step."""
    model, h = shape.model, ca.SX.sym("h")
    qa, qb, qc = (ca.SX.sym(name, model.nq) for name in ("qa", "qb", "qc"))
    ua, ub = ca.SX.sym("ua", model.nu), ca.SX.sym("ub", model.nu)

    def discrete_lagrangian(a: ca.SX, b: ca.SX, interval: int) -> ca.SX:
        return h * model.lagrangian((a + b) / 2, (b - a) / h, interval)

    before = k - 1 if getattr(model, "time_dependent", False) else 0
    terms = [ca.gradient(discrete_lagrangian(qa, qb, before), qb),
             ca.gradient(discrete_lagrangian(qb, qc, k), qb),
             0.5 * h * model.generalized_force((qa + qb) / 2, ua),
             0.5 * h * model.generalized_force((qb + qc) / 2, ub)]
    nc = getattr(model, "n_constraints", 0)
    holonomic = ([ca.vec(ca.jacobian(model.constraints(qb), qb).T), model.constraints(qb)]
                 if nc else [ca.SX(0, 1), ca.SX(0, 1)])
    return ca.Function("interior", [qa, qb, qc, ua, ub, h], [*terms, *holonomic])


def _equation_residuals(terms: list[np.ndarray], grad: np.ndarray) -> np.ndarray:
    """Per row (m,) the relative residual |r| / (1 + Σ |terms|) of one DMOC equation whose
    ``terms`` are (m, nq) each, r their sum with its part in the range of ∇c(q)ᵀ (``grad``
    (m, nq nc) flattened column-major, nc ≥ 0: the holonomic reactions, free multipliers)
    removed by least squares; a row with a non-finite entry gives NaN."""
    m, nq = terms[0].shape
    r = sum(terms[1:], terms[0])
    if grad.size:   # least-squares reactions λ: r − G (GᵀG)⁻¹ Gᵀ r, G = ∇cᵀ (nq, nc)
        g = grad.reshape(m, -1, nq).transpose(0, 2, 1)
        ok = np.all(np.isfinite(g), axis=(1, 2)) & np.all(np.isfinite(r), axis=1)
        r = np.where(ok[:, None], r, np.nan)   # a failed path's NaN stays NaN
        g, gt = g[ok], g[ok].transpose(0, 2, 1)
        r[ok] -= (g @ np.linalg.solve(gt @ g, gt @ r[ok][..., None]))[..., 0]
    size = sum(np.sqrt(np.einsum("ij,ij->i", t, t)) for t in terms)
    return np.sqrt(np.einsum("ij,ij->i", r, r)) / (1.0 + size)


def _dynamics_residuals(shape: DmocShape, q: np.ndarray, u: np.ndarray, steps: np.ndarray
                        ) -> np.ndarray:
    """Per agent (m,) the largest residual of DMOC's interior equations (the discrete
    Euler–Lagrange equations with forces at the inner nodes k = 1 … N−1, relative as in
    :func:`_equation_residuals`) and of the holonomic constraints |c(q_k)| there, on node
    paths ``q`` (m, N+1, nq) and controls ``u`` (m, N, nu) with steps h ``steps`` (m,); 0
    with one interval."""
    varying = getattr(shape.model, "time_dependent", False)
    worst = np.zeros(len(q))
    for k in range(1, shape.intervals):   # node by node: m rows at a time (memory)
        out = evaluate_columns(_interior_terms(shape, k if varying else 0), q[:, k - 1],
                               q[:, k], q[:, k + 1], u[:, k - 1], u[:, k], steps)
        residual = _equation_residuals(out[0:4], out[4])
        if out[5].size:
            residual = np.maximum(residual, np.max(np.abs(out[5]), axis=1))
        worst = np.maximum(worst, residual)
    return worst


def _momentum_residuals(shape: DmocShape, q: np.ndarray, u: np.ndarray, v0: np.ndarray,
                        vn: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Per agent (m,) the larger relative residual of DMOC's two boundary equations on node
    paths ``q`` (m, N+1, nq) and controls ``u`` (m, N, nu) with boundary velocities ``v0``,
    ``vn`` (m, nq), steps h ``steps`` (m,): |r| / (1 + Σ |terms|), r the sum of the terms
    with its part in the range of ∇c(q)ᵀ (the holonomic reactions, free multipliers)
    removed."""
    out = evaluate_columns(_boundary_terms(shape), q[:, 0], q[:, 1], q[:, -2], q[:, -1],
                           u[:, 0], u[:, -1], v0, vn, steps)
    return np.maximum(_equation_residuals(out[0:3], out[6]),
                      _equation_residuals(out[3:6], out[7]))


@dataclass
class AgentChecks:
    """The checks that read one agent's own path (module docstring: ``start``,
    ``attitude``, ``momentum``, ``dynamics``, the shape's ``control_bounds`` and
    ``path_constraints``) as relative residuals per agent, for m agents in order: ``start``,
    ``attitude`` (None without attitude entries), ``momentum`` and ``dynamics`` (m,); per
    shape with control bounds its agents' worst ``bounds`` (m_s,), per shape with path
    constraints each constraint's worst ``path`` (m_s, C), the agents of each shape
    ``agents`` (their indices, m_s); and ``violation`` (m,), each agent's largest. Made where
    the paths are (:func:`agent_checks`: the coordinator's, or each worker's block of agents,
    :mod:`ocpar.formation.finish`)."""

    start: np.ndarray
    attitude: np.ndarray | None
    momentum: np.ndarray
    dynamics: np.ndarray
    bounds: dict[Shape, np.ndarray]
    path: dict[Shape, np.ndarray]
    agents: dict[Shape, np.ndarray]
    violation: np.ndarray


def _rows_by_shape(shapes: list[Shape]) -> dict[Shape, np.ndarray]:
    """The rows (ascending) of each distinct shape of ``shapes``, in order of first use; one
    shape object repeated (a fleet of one shape) without hashing it once per row."""
    if shapes and all(shape is shapes[0] for shape in shapes):
        return {shapes[0]: np.arange(len(shapes))}
    groups: dict[Shape, list[int]] = {}
    for row, shape in enumerate(shapes):
        groups.setdefault(shape, []).append(row)
    return {shape: np.array(rows) for shape, rows in groups.items()}


def agent_checks(shapes: list[Shape], q: np.ndarray, u: np.ndarray, params: np.ndarray,
                 positions: int, first: int = 0, durations: np.ndarray | None = None
                 ) -> AgentChecks:
    """The :class:`AgentChecks` of m agents with indices ``first`` … ``first`` + m − 1: each
    one's shape (``shapes``, m), node paths ``q`` (m, N+1, nq; a fleet of DMOC and ODE
    agents: padded to its widest, each agent's first entries read), controls ``u`` (m, N, nu),
    its boundary data ``params`` (m, n_params: DMOC's (q_0, q̇_0, q_N, q̇_N), an ODE agent's
    (x_0, x̄_N)), ``positions`` d; ``durations`` (m,) each agent's T where it chose its own
    (default: its shape's). Each agent's numbers are its own: any block of agents
    gives the rows of the whole fleet's."""
    m = len(q)
    groups = _rows_by_shape(shapes)
    start, attitude = np.empty(m), np.zeros(m)
    momentum, dynamics = np.empty(m), np.empty(m)
    has_attitude = False
    bounds, path, agents = {}, {}, {}
    for shape, members in groups.items():
        rows = members
        agents[shape] = rows + first
        qs, us, ps = q[rows][..., :shape.node_size], u[rows], params[rows]
        own_durations = (np.full(len(rows), shape.duration) if durations is None
                         else np.asarray(durations, float)[rows])
        if isinstance(shape, MsEndpointShape):
            own = _ode_checks(shape, qs, us, ps, positions, own_durations)
        else:
            own = _dmoc_checks(shape, qs, us, ps, positions, own_durations / shape.intervals)
        start[rows], momentum[rows], dynamics[rows] = own.start, own.momentum, own.dynamics
        if own.attitude is not None:
            attitude[rows], has_attitude = own.attitude, True
        if shape.control_bounds is not None:
            lo, hi = np.array(shape.control_bounds).T
            gap = np.maximum(np.maximum(lo - us, us - hi), 0.0)
            scale = np.maximum(1.0, np.where(np.isfinite([lo, hi]), np.abs([lo, hi]), 0.0)
                               .max(axis=0))
            bounds[shape] = np.max(gap / scale, axis=(1, 2))
        worst_path = []
        for constraint in shape.path_constraints:
            values = {k: v.reshape(-1, v.shape[-1]) for k, v in own.points(constraint).items()}
            finite = [abs(b) for b in constraint.lower + constraint.upper if math.isfinite(b)]
            gap = constraint.violation(values).reshape(len(rows), -1) / max([1.0, *finite])
            worst_path.append(np.max(gap, axis=1) if gap.size else np.zeros(len(rows)))
        if worst_path:
            path[shape] = np.column_stack(worst_path)
    violation = np.maximum(np.maximum(start, attitude), np.maximum(momentum, dynamics))
    for shape, rows in agents.items():   # raised to each agent's worst bound and constraint
        local = rows - first
        for worst in ([bounds[shape]] if shape in bounds else []) + (
                list(path[shape].T) if shape in path else []):
            violation[local] = np.maximum(violation[local], worst)
    return AgentChecks(start, attitude if has_attitude else None, momentum, dynamics, bounds,
                       path, agents, violation)


@dataclass
class _OwnChecks:
    """One shape's agents' residuals (m,) (``attitude`` None without such entries) and
    ``points``: the arguments (by name) at which its transcription imposes a path
    constraint."""

    start: np.ndarray
    attitude: np.ndarray | None
    momentum: np.ndarray
    dynamics: np.ndarray
    points: Callable[[CompiledConstraint], dict[str, np.ndarray]]


def _dmoc_checks(shape: DmocShape, q: np.ndarray, u: np.ndarray, params: np.ndarray,
                 positions: int, steps: np.ndarray) -> _OwnChecks:
    """DMOC agents' checks (module docstring), each agent's step h ``steps`` (m,)."""
    nq, h = shape.model.nq, steps[:, None, None]
    starts, v0 = params[:, :nq], params[:, nq:2 * nq]
    final_attitude, vn = params[:, 2 * nq + positions:3 * nq], params[:, 3 * nq:4 * nq]
    attitude = (_relative(q[:, -1, positions:] - final_attitude, final_attitude)
                if final_attitude.shape[1] else None)

    def points(constraint: CompiledConstraint) -> dict[str, np.ndarray]:
        if constraint.depends_on("v", "u"):
            return {"q": (q[:, :-1] + q[:, 1:]) / 2, "v": (q[:, 1:] - q[:, :-1]) / h, "u": u}
        return {"q": q[:, 1:-1]}

    return _OwnChecks(_relative(q[:, 0] - starts, starts), attitude,
                      _momentum_residuals(shape, q, u, v0, vn, steps),
                      _dynamics_residuals(shape, q, u, steps), points)


def _ode_checks(shape: MsEndpointShape, x: np.ndarray, u: np.ndarray, params: np.ndarray,
                positions: int, durations: np.ndarray) -> _OwnChecks:
    """ODE agents' checks: ``start`` the start state, ``attitude`` the end entries the shape
    fixes other than the position, ``dynamics`` the shooting residuals (:func:`_shooting`,
    each agent over its horizon T ``durations`` (m,)),
    ``momentum`` 0 (DMOC's boundary velocities: an ODE agent's are entries of its states)."""
    nx = shape.model.nx
    starts, ends = params[:, :nx], params[:, nx:2 * nx]
    fixed = [i for i in range(nx) if i not in shape.free_end and i not in
             shape.position_indices]
    attitude = (_relative(x[:, -1, fixed] - ends[:, fixed], ends[:, fixed]) if fixed
                else None)

    def points(constraint: CompiledConstraint) -> dict[str, np.ndarray]:
        if constraint.depends_on("u"):
            return {"x": x[:, :-1], "u": u}
        return {"x": x[:, 1:]}

    return _OwnChecks(_relative(x[:, 0] - starts, starts), attitude, np.zeros(len(x)),
                      _shooting(shape, x, u, durations), points)


@lru_cache(maxsize=32)
def _rhs(model: object) -> ca.Function:
    """f(x, u) of an ODE model, built here from the model."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)  # type: ignore[attr-defined]
    return ca.Function("f", [x, u], [model.rhs(x, u)])  # type: ignore[attr-defined]


#: The verification's re-integration of an ODE agent for its obstacle clearance: each of the
#: integrator's sub-steps (``MsEndpointShape.steps`` per interval) re-integrated from its
#: start by this many steps of the same integrator (:func:`checked_positions`). The closest
#: approach is measured on it only where a separation is required: on 8 × as many intervals
#: it cost 10 × (0.47 s against 0.04 s for 200 unicycles, more than their solve), for a
#: difference of 1e-3 (0.6608 against 0.6599 for 8 unicycles); without, ODE agents' closest
#: approach is that of the nodes' polyline.
DENSE_SUBSTEPS = 8


def _advance(shape: MsEndpointShape, state: np.ndarray, control: np.ndarray,
             step: float | np.ndarray) -> np.ndarray:
    """One step of ``step`` (a number, or one per row (k, 1)) of the shape's integrator
    (classical RK4 or Euler) from states (k, nx) under controls (k, nu), in numpy on the
    model's f (not the transcription's expressions)."""
    f = _rhs(shape.model)

    def rate(at: np.ndarray) -> np.ndarray:
        return evaluate_columns(f, at, control)[0]

    if shape.integrator == "euler":
        return state + step * rate(state)
    k1 = rate(state)
    k2 = rate(state + step / 2 * k1)
    k3 = rate(state + step / 2 * k2)
    k4 = rate(state + step * k3)
    return state + step / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _sub_steps(shape: MsEndpointShape, x: np.ndarray, u: np.ndarray,
               durations: np.ndarray | None = None) -> np.ndarray:
    """The integrator's states (m, N, steps + 1, nx) of each interval, re-integrated from its
    returned start node x_j (m, N+1, nx) under its control (m, N, nu): ``steps`` steps of
    h/``steps``, h = T/N with each agent's T ``durations`` (m,; default the shape's)."""
    m, n, nx = x.shape[0], shape.intervals, shape.model.nx
    horizon = np.full(m, shape.duration) if durations is None else np.asarray(durations, float)
    step = np.repeat(horizon / n / shape.steps, n)[:, None]
    state, control = x[:, :-1].reshape(-1, nx), u.reshape(-1, u.shape[-1])
    states = [state]
    for _ in range(shape.steps):
        states.append(_advance(shape, states[-1], control, step))
    return np.stack(states, axis=1).reshape(m, n, shape.steps + 1, nx)


def _shooting(shape: MsEndpointShape, x: np.ndarray, u: np.ndarray, durations: np.ndarray
              ) -> np.ndarray:
    """Per agent (m,) the largest relative shooting residual |x_{k+1} − Φ(x_k, u_k)| /
    (1 + |x_{k+1}|) over the intervals: the returned controls re-integrated from each
    returned node by the shape's integrator with each agent's T ``durations`` (m,)
    (:func:`_sub_steps`)."""
    m, nx = x.shape[0], shape.model.nx
    state = _sub_steps(shape, x, u, durations)[:, :, -1].reshape(-1, nx)
    reached = x[:, 1:].reshape(-1, nx)
    gap = np.max(np.abs(reached - state) / (1 + np.abs(reached)), axis=1)
    return np.max(gap.reshape(m, shape.intervals), axis=1)


def _dense_path(shape: MsEndpointShape, x: np.ndarray, u: np.ndarray, refine: int,
                durations: np.ndarray | None = None) -> np.ndarray:
    """The states (m, N steps refine + 1, nx) of ODE agents' paths x (m, N+1, nx) under
    controls u (m, N, nu), each over its horizon T ``durations`` (m,; default the shape's):
    each of the integrator's sub-steps (:func:`_sub_steps`) re-integrated from its start by
    ``refine`` steps of the same integrator, up to the next sub-step's start (the next node
    after an interval's last): the points of the transcription's keep-out polyline are among
    them."""
    m, n, nx, steps = x.shape[0], shape.intervals, shape.model.nx, shape.steps
    horizon = np.full(m, shape.duration) if durations is None else np.asarray(durations, float)
    state = _sub_steps(shape, x, u, horizon)[:, :, :-1].reshape(-1, nx)   # each sub-step's start
    control = np.repeat(u, steps, axis=1).reshape(-1, u.shape[-1])
    step = np.repeat(horizon / n / steps / refine, n * steps)[:, None]
    fine = [state]
    for _ in range(refine - 1):
        fine.append(_advance(shape, fine[-1], control, step))
    points = np.stack(fine, axis=1).reshape(m, n * steps * refine, nx)
    return np.concatenate([points, x[:, -1:]], axis=1)


def checked_positions(problem: FormationProblem, trajectories: np.ndarray,
                      controls: np.ndarray, nodes: np.ndarray | None = None,
                      durations: np.ndarray | None = None, separation: bool = False
                      ) -> np.ndarray:
    """The positions (n, P, d) the obstacle clearance (and, with ``separation`` required,
    the closest approach) is checked on: the nodes (P = N+1;
    :meth:`~ocpar.formation.FormationProblem.positions`) where no agent is an ODE agent or
    there is neither an obstacle nor a required separation (a DMOC path is linear between
    nodes); else every agent on a
    common dense grid of S = :data:`DENSE_SUBSTEPS` · lcm(ODE shapes' ``steps``) points per
    interval (P = N S + 1): an ODE agent's path re-integrated (:func:`_dense_path`), a DMOC
    agent's nodes joined linearly. ``nodes``: the nodes' positions where they are at hand
    (the paths of a run whose workers wrote them are not gathered); ``durations`` (n,) each
    agent's horizon T where it chose its own (default: its shape's)."""
    if not (problem.obstacles or separation) or not problem.ode_agents:
        return problem.positions(trajectories) if nodes is None else nodes
    q, u = np.asarray(trajectories, float), np.asarray(controls, float)
    groups = problem.agents_by_shape()
    sub = math.lcm(*(s.steps for s in groups if isinstance(s, MsEndpointShape)))
    refine = DENSE_SUBSTEPS * sub
    n, nodes = q.shape[:2]
    entries = list(problem.position_indices)
    dense = np.empty((n, (nodes - 1) * refine + 1, len(entries)))
    for shape, agents in groups.items():
        if isinstance(shape, MsEndpointShape):
            path = _dense_path(shape, q[agents][..., :shape.node_size], u[agents],
                               refine // shape.steps,
                               None if durations is None else np.asarray(durations)[agents])
            dense[agents] = path[..., entries]
        else:
            nodes_at = problem.positions(q[agents])
            s = np.arange(refine)[None, None, :, None] / refine
            inner = nodes_at[:, :-1, None] + s * (nodes_at[:, 1:, None] - nodes_at[:, :-1, None])
            dense[agents] = np.concatenate(
                [inner.reshape(len(agents), -1, len(entries)), nodes_at[:, -1:]], axis=1)
    return dense


def _constraint_checks(problem: FormationProblem, checks: AgentChecks) -> dict[str, Check]:
    """``control_bounds`` and ``path_constraints`` checks of each agent's shape, where any
    agent has them (module docstring), from the agents' ``checks``."""
    bounds, path = [], []
    for shape in problem.agents_by_shape():
        if shape not in checks.agents:
            continue
        agents = checks.agents[shape]
        if shape in checks.bounds:
            bounds.append(_worst(checks.bounds[shape], CONSTRAINT_RTOL, agents))
        for c, constraint in enumerate(shape.path_constraints):
            path.append(_worst(checks.path[shape][:, c], CONSTRAINT_RTOL, agents,
                               f"path constraint {constraint.name!r}"))
    # per name the worst over shapes and constraints: a failed one first, NaN first
    return {name: max(found, key=lambda c: (not c.passed, math.inf if math.isnan(c.value)
                                            else c.value))
            for name, found in (("control_bounds", bounds), ("path_constraints", path))
            if found}


def _target_size(problem: FormationProblem) -> float:
    """The target's size (length unit): a curve's or surface's length scale, the slots'
    largest distance from their centroid (at least 1e-300)."""
    if isinstance(problem.curve, Slots):
        points = problem.curve.points
        return max(float(np.max(np.abs(points - points.mean(axis=0)))), 1e-300)
    return float(problem.curve.length_scale)


def _locate(problem: FormationProblem, ends: np.ndarray, phi: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """The parameters of the end positions ``ends`` (n, d) on the target (the shape of φ)
    and their distances from it (n,), length unit: a curve's or slots' own ``locate`` (φ the
    hint); a surface's inverse chart (:meth:`~ocpar.formation.targets.surface.Surface.locate`, no
    hint), NaN for a failed path's NaN point."""
    if not isinstance(problem.curve, Surface):
        located, distance = problem.curve.locate(ends, np.reshape(phi, problem.parameter_shape))
        return np.reshape(located, problem.parameter_shape), distance
    located = np.full(problem.parameter_shape, np.nan)
    finite = np.all(np.isfinite(ends), axis=1)
    if np.any(finite):
        located[finite] = problem.curve.locate(ends[finite])
    return located, np.linalg.norm(problem.curve.points(located) - ends, axis=1)


def verify_formation(problem: FormationProblem, trajectories: np.ndarray,
                     controls: np.ndarray, phi: np.ndarray,
                     min_separation: float | None = None,
                     backend: Backend | None = None) -> Verification:
    """Check a returned formation from its node paths ``trajectories`` (n, N+1, nq), interval
    controls ``controls`` (n, N, nu) and parameters ``phi`` (the shape of φ; used only as the
    hint where the end points are located, and onto slots as the assignment) against
    ``problem`` (module docstring); ``min_separation`` D (length unit) if the run required
    one (then the closest approach must be ≥ D (1 − :data:`SEPARATION_RTOL`)). With a
    ``backend``, the closest approach's intervals are searched on its workers (the same
    figures). :func:`agent_checks`, then :func:`verify_checked`."""
    start = time.perf_counter()
    q, u = np.asarray(trajectories, float), np.asarray(controls, float)
    n = problem.agents
    checks = agent_checks(list(problem.shapes), q, u,
                          problem.boundary_params_rows(np.arange(n), phi), problem.curve.dim)
    return verify_checked(problem, problem.positions(q), q[:, -1, :problem.curve.dim], phi,
                          checks, min_separation, backend, time.perf_counter() - start,
                          checked_positions(problem, q, u,
                                            separation=min_separation is not None))


def verify_checked(problem: FormationProblem, positions: np.ndarray, ends: np.ndarray,
                   phi: np.ndarray, checks: AgentChecks, min_separation: float | None = None,
                   backend: Backend | None = None, spent_s: float = 0.0,
                   clearance_positions: np.ndarray | None = None) -> Verification:
    """:func:`verify_formation` given the agents' own checks ``checks`` (made where their
    paths are, :func:`agent_checks`), their positions (n, N+1, p) on the nodes
    (:meth:`~ocpar.formation.FormationProblem.positions`) and their end points ``ends``
    (n, d: the first d entries of q_N, which the target fixes): the target and coupling at
    the end points, the obstacles, the closest approach (its intervals on the ``backend``'s
    workers, if one is given), the near-collision rule. ``spent_s``: time already spent on
    the checks (s), counted in the verification's. ``clearance_positions`` (n, P, d): the
    positions the obstacle clearance and a required separation are checked on
    (:func:`checked_positions`; None: the nodes' ``positions``)."""
    start = time.perf_counter() - spent_s
    positions, ends = np.asarray(positions, float), np.asarray(ends, float)
    found: dict[str, Check] = {}

    located, distance = _locate(problem, ends, phi)
    found["target"] = _worst(distance / _target_size(problem), TARGET_RTOL)
    if isinstance(problem.curve, Surface) and problem.coupling == PotentialCoupling():
        residual = surface_criticality(problem.curve, ends)[0]   # in space, chart-free
    else:
        residual = coupling_residual(problem, located)
    if isinstance(problem.curve, Slots):
        found["slots_shared"] = Check(residual, -1, 0.0)
    else:
        found["coupling"] = Check(residual, -1, COUPLING_TOL)

    found["start"] = _worst(checks.start, BOUNDARY_RTOL)
    if checks.attitude is not None:
        found["attitude"] = _worst(checks.attitude, BOUNDARY_RTOL)
    found["momentum"] = _worst(checks.momentum, MOMENTUM_RTOL)
    found["dynamics"] = _worst(checks.dynamics, MOMENTUM_RTOL)
    found |= _constraint_checks(problem, checks)

    clearance = None
    if problem.obstacles:
        clearance = closest_obstacle(
            positions if clearance_positions is None else clearance_positions,
            problem.obstacles, problem.common_shape.duration)
        where = (f"obstacles[{clearance.obstacle}] "
                 f"({problem.obstacles[clearance.obstacle].name})"
                 if clearance.obstacle >= 0 else "an obstacle")
        found["obstacles"] = Check(-clearance.distance, clearance.agent,
                                   CLEARANCE_TOL * min(o.scale for o in problem.obstacles),
                                   where)
    closest = problem.closest_approach_of(
        positions if min_separation is None or clearance_positions is None
        else clearance_positions, backend)
    if min_separation is not None:
        found["separation"] = Check(min_separation - closest.distance, closest.agents[0],
                                    min_separation * SEPARATION_RTOL,
                                    f"{closest.agents[0]} and {closest.agents[1]}")
    spacing = formation_spacing(problem, positions[:, -1], located)
    near = near_collision(closest, spacing) if min_separation is None else None
    return Verification(found, located, residual, closest, spacing, clearance, near,
                        time.perf_counter() - start, checks.violation)


def formation_spacing(problem: FormationProblem, targets: np.ndarray, located: np.ndarray
                      ) -> float:
    """The smallest distance between two of the end points ``targets`` (n, d), length unit
    (inf with one agent, NaN if a point is not finite): on a circle, of neighbours in the
    order of their angles ``located`` (n,) (the chord grows with the angle between two
    points: O(n log n), no tree), else :func:`~ocpar.formation.keep_out.separation.closest_pair`."""
    if len(targets) < 2:
        return math.inf
    if not np.all(np.isfinite(targets)):
        return math.nan
    if not (problem.on_circle and np.all(np.isfinite(located))):
        return closest_pair(targets)[0]
    ring = targets[np.argsort(np.mod(located, 2 * np.pi), kind="stable")]
    return float(np.linalg.norm(ring - np.roll(ring, -1, axis=0), axis=1).min())


def near_collision(closest: ClosestApproach, spacing: float) -> dict | None:
    """Where and how close the ``closest`` approach is, if below
    :data:`NEAR_COLLISION_FRACTION` of the formation's ``spacing`` (else None)."""
    if not closest.distance < NEAR_COLLISION_FRACTION * spacing:
        return None
    return {"distance": closest.distance, "agents": list(closest.agents),
            "time": closest.time, "spacing": spacing, "fraction": closest.distance / spacing,
            "rule": f"closest approach below {100 * NEAR_COLLISION_FRACTION:g} % of the "
                    f"formation's spacing (the smallest distance between two target points)"}


def near_collision_words(near: dict) -> str:
    """The status line's words on a near-collision (:class:`Verification`)."""
    i, j = near["agents"]
    return (f"near-collision: agents {i} and {j} come within {near['distance']:.3g} at "
            f"t = {near['time']:.3g}, {100 * near['fraction']:.2g} % of the formation's spacing "
            f"{near['spacing']:.3g} (below {100 * NEAR_COLLISION_FRACTION:g} %); this is the "
            f"optimum without a separation requirement: --min-separation D keeps every "
            f"pair D apart")
