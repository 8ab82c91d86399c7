"""The public definition of a multi-objective optimal control problem for MACS.

    min over u(·), t_f of (J_1, …, J_m),   J_i = φ_i(x(t_f), t_f) + ∫_0^{t_f} L_i(x, u) dt
    s.t.  ẋ = f(x, u),  x(0) = x_0,  x_k(t_f) = x_k^f for the fixed components k,
          u_lo ≤ u ≤ u_hi,  t_lo ≤ t_f ≤ t_hi,  the model's state bounds,
          lower ≤ c(x, u) ≤ upper  (path constraints, at the DFET's quadrature points),

with m ≥ 2, t_0 = 0 and every objective minimised; transcribed by DFET (N elements, states of
order l, controls of order l_u). A :class:`MacsProblem` is checked when it is built: a wrong
dimension, a non-finite number, an expression that does not evaluate or bounds that exclude
the boundary data raise one ``ValueError`` naming the field.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ocpar.models.labels import check_labels
from ocpar.models.ode import OdeModel
from ocpar.ocp import DfetShape
from ocpar.ocp.constraints import (
    CompiledConstraint,
    PathConstraint,
    check_smooth,
    compile_constraints,
    nonfinite,
)

#: φ(x_f (nx,), t_f) or L(x (nx,), u (nu,)): a scalar CasADi expression of CasADi symbols.
Term = Callable[[ca.SX, ca.SX], ca.SX]


@dataclass(frozen=True)
class Objective:
    """J = ``mayer``(x(t_f), t_f) + ∫_0^{t_f} ``running``(x(t), u(t)) dt, minimised; either
    term may be None, not both. Terms are Python callables built from CasADi operations (or
    ``casadi.Function``); ``name`` labels the objective in plots (default ``J<i>``) and
    results; ``unit`` is its unit in the array file (a string a unit library parses, '1'
    nondimensional)."""

    mayer: Term | None = None
    running: Term | None = None
    name: str = ""
    unit: str = "1"


@dataclass(frozen=True, eq=False)
class MacsProblem:
    """A multi-objective optimal control problem (see the module docstring).

    ``model``: any ODE model with ``nx``, ``nu``, ``rhs(x, u)`` (CasADi) and
    ``state_bounds()`` (a hashable value object, e.g. a frozen dataclass);
    ``objectives``: m ≥ 2 :class:`Objective`; ``initial_state`` x_0 (nx,);
    ``final_time`` (lo, hi) bounds on t_f > 0, lo == hi for a fixed t_f;
    ``control_bounds`` one finite (lo, hi) per control; ``final_state`` {index: value} of the
    fixed components of x(t_f); ``periodic_controls`` one flag per control (or one for all):
    the control is an angle whose bounds span one period, so a node on one bound equals the
    other bound; ``elements``, ``order``, ``control_order`` (default ``order``) of the DFET;
    ``reference_front`` (k, m) a known Pareto front, for GD/IGD (None: not known);
    ``path_constraints`` :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``x`` and ``u``
    (a speed limit, a nonlinear control constraint), imposed at every element's quadrature
    points (:meth:`~ocpar.ocp.dfet.DfetTranscription.path_rows`); those of ``x`` alone must
    hold at the initial state.

    Equal problems (same data, same objective expressions) compare and hash equal, also after
    pickling, so workers build their solvers once per problem.
    """

    name: str
    model: OdeModel
    objectives: Sequence[Objective]
    initial_state: Sequence[float]
    final_time: tuple[float, float]
    control_bounds: Sequence[tuple[float, float]]
    final_state: Mapping[int, float] = field(default_factory=dict)
    periodic_controls: bool | Sequence[bool] = False
    elements: int = 8
    order: int = 4
    control_order: int | None = None
    reference_front: np.ndarray | None = None
    path_constraints: Sequence[PathConstraint | CompiledConstraint] = ()
    #: (model, SHA-256 of everything else): what equality and hashing compare
    _key: tuple = field(init=False, repr=False)

    def __post_init__(self) -> None:
        checked = _check(self)
        for name, value in checked.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "_key", (self.model, _digest(self)))

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MacsProblem) and self._key == other._key

    def __hash__(self) -> int:
        return hash(self._key)

    @property
    def n_objectives(self) -> int:
        """m, the number of objectives."""
        return len(self.objectives)

    @property
    def objective_names(self) -> list[str]:
        """Each objective's ``name``, or ``J<i>`` (1-based)."""
        return [o.name or f"J{i + 1}" for i, o in enumerate(self.objectives)]

    @property
    def objective_units(self) -> list[str]:
        """Each objective's ``unit``."""
        return [o.unit for o in self.objectives]

    @property
    def shape(self) -> DfetShape:
        """The DFET transcription's shape (the solver-cache key)."""
        final = sorted(self.final_state.items())
        return DfetShape(self.model, self.elements, self.order, self.control_order,
                         tuple(self.control_bounds), self.final_time, tuple(self.initial_state),
                         tuple(i for i, _ in final), tuple(v for _, v in final))


def _fail(field_name: str, message: str) -> ValueError:
    return ValueError(f"MacsProblem.{field_name}: {message}")


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _numbers(value, field_name: str, size: int | None = None) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in np.ravel(np.asarray(value, dtype=float)))
    except (TypeError, ValueError):
        raise _fail(field_name, f"expected numbers, got {value!r}") from None
    if size is not None and len(out) != size:
        raise _fail(field_name, f"expected {size} numbers, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise _fail(field_name, f"must be finite, got {out}")
    return out


def _integer(value, field_name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise _fail(field_name, f"must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _compile(term: Term, field_name: str, first: ca.SX, second: ca.SX,
             sample: tuple[np.ndarray, np.ndarray]) -> ca.Function:
    """``term`` as a CasADi function of (first, second) → scalar, evaluated once at
    ``sample`` to check that it gives a finite number with a finite gradient."""
    if not callable(term):
        raise _fail(field_name, f"must be callable, got {term!r}")
    try:
        expr = ca.SX(term(first, second))
    except Exception as exc:  # any failure of user code becomes one line
        raise _fail(field_name, f"does not evaluate on CasADi symbols: {_first_line(exc)}") \
            from None
    if expr.shape != (1, 1):
        raise _fail(field_name, f"must be a scalar, got shape {expr.shape}")
    function = ca.Function(field_name.replace(".", "_").replace("[", "").replace("]", ""),
                           [first, second], [expr])
    value = float(function(*sample))
    if not math.isfinite(value):
        raise _fail(field_name, f"is not finite at the boundary data ({value})")
    if nonfinite(function, [np.asarray(a, float)[None] for a in sample]) is not None:
        raise _fail(field_name, "is not differentiable at the boundary data, where the "
                    "solves start")
    return function


def _check(problem: MacsProblem) -> dict:
    """Every field checked and normalised (tuples, CasADi functions); raises ValueError."""
    out: dict = {}
    if not isinstance(problem.name, str) or not problem.name:
        raise _fail("name", f"must be a non-empty string, got {problem.name!r}")
    model = problem.model
    try:
        nx, nu = _integer(model.nx, "model.nx", 1), _integer(model.nu, "model.nu", 1)
        hash(model)
        lower, upper = (np.asarray(b, dtype=float) for b in model.state_bounds())
    except (AttributeError, TypeError) as exc:
        raise _fail("model", "must be a hashable ODE model with nx, nu, rhs(x, u) and "
                    f"state_bounds() ({_first_line(exc)})") from None
    if lower.shape != (nx,) or upper.shape != (nx,) or np.any(lower > upper):
        raise _fail("model.state_bounds", f"must be two arrays ({nx},) with lower <= upper")
    check_labels(model, nx, nu, "MacsProblem.model")
    out["elements"] = _integer(problem.elements, "elements", 1)
    out["order"] = _integer(problem.order, "order", 1)
    control_order = problem.order if problem.control_order is None else problem.control_order
    out["control_order"] = _integer(control_order, "control_order", 0)

    x0 = np.array(_numbers(problem.initial_state, "initial_state", nx))
    if np.any(x0 < lower) or np.any(x0 > upper):
        raise _fail("initial_state", f"{tuple(x0)} lies outside the model's state bounds")
    out["initial_state"] = tuple(x0)
    t_lo, t_hi = _numbers(problem.final_time, "final_time", 2)
    if not 0 < t_lo <= t_hi:
        raise _fail("final_time", f"must satisfy 0 < lo <= hi, got {(t_lo, t_hi)}")
    out["final_time"] = (t_lo, t_hi)
    bounds = np.array(_numbers(problem.control_bounds, "control_bounds", 2 * nu)).reshape(nu, 2)
    if np.any(bounds[:, 0] > bounds[:, 1]):
        raise _fail("control_bounds", f"need lo <= hi for every control, got {bounds.tolist()}")
    out["control_bounds"] = tuple((float(lo), float(hi)) for lo, hi in bounds)

    if not isinstance(problem.final_state, Mapping):
        raise _fail("final_state", f"must be a mapping {{index: value}}, got "
                    f"{problem.final_state!r}")
    final = {}
    for key, value in problem.final_state.items():
        if isinstance(key, bool) or not isinstance(key, int | np.integer) or not 0 <= key < nx:
            raise _fail("final_state", f"index {key!r} is not a state index in 0..{nx - 1}")
        (v,) = _numbers(value, f"final_state[{key}]", 1)
        if not lower[key] <= v <= upper[key]:
            raise _fail(f"final_state[{key}]", f"{v} lies outside the model's state bounds")
        final[int(key)] = v
    out["final_state"] = dict(sorted(final.items()))

    flags = problem.periodic_controls
    flags = (flags,) * nu if isinstance(flags, bool | np.bool_) else tuple(flags)
    if len(flags) != nu or not all(isinstance(f, bool | np.bool_) for f in flags):
        raise _fail("periodic_controls", f"must be one bool or {nu} bools, got "
                    f"{problem.periodic_controls!r}")
    out["periodic_controls"] = tuple(bool(f) for f in flags)

    # boundary data at which every expression must evaluate to finite numbers
    xf = x0.copy()
    xf[list(final)] = list(final.values())
    u_mid = bounds.mean(axis=1)
    xs, us, tf = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("t_f")
    try:
        rhs = ca.SX(model.rhs(xs, us))
    except Exception as exc:  # any failure of user code becomes one line
        raise _fail("model.rhs", f"does not evaluate on CasADi symbols: {_first_line(exc)}") \
            from None
    if rhs.shape != (nx, 1):
        raise _fail("model.rhs", f"must have shape ({nx}, 1), got {rhs.shape}")
    if not np.all(np.isfinite(ca.Function("f", [xs, us], [rhs])(x0, u_mid).full())):
        raise _fail("model.rhs", "is not finite at the initial state and mid-range controls")

    objectives = tuple(problem.objectives) if isinstance(problem.objectives, Sequence) else None
    if objectives is None or len(objectives) < 2:
        raise _fail("objectives", f"need a sequence of at least 2 Objective, got "
                    f"{problem.objectives!r}")
    compiled = []
    for i, objective in enumerate(objectives):
        where = f"objectives[{i}]"
        if not isinstance(objective, Objective):
            raise _fail(where, f"must be an Objective, got {objective!r}")
        if objective.mayer is None and objective.running is None:
            raise _fail(where, "needs a mayer term, a running term or both")
        mayer = None if objective.mayer is None else _compile(
            objective.mayer, f"{where}.mayer", xs, tf, (xf, t_lo))
        running = None if objective.running is None else _compile(
            objective.running, f"{where}.running", xs, us, (x0, u_mid))
        if not isinstance(objective.unit, str) or not objective.unit.strip():
            raise _fail(f"{where}.unit", f"must be a unit string, got {objective.unit!r}")
        compiled.append(Objective(mayer, running, str(objective.name), objective.unit))
    out["objectives"] = tuple(compiled)

    u_start = np.clip(0.0, bounds[:, 0], bounds[:, 1])   # the DFET's default guess
    out["path_constraints"] = _path_constraints(problem.path_constraints, nx, nu, x0,
                                                np.vstack([u_mid, u_start]))

    if problem.reference_front is not None:
        front = np.array(problem.reference_front, dtype=float)
        m = len(compiled)
        if front.ndim != 2 or front.shape[1] != m or len(front) < 2:
            raise _fail("reference_front", f"must have shape (k >= 2, {m}), got {front.shape}")
        if not np.all(np.isfinite(front)):
            raise _fail("reference_front", "must be finite")
        if np.any(np.ptp(front, axis=0) <= 0):
            raise _fail("reference_front", "has no extent in some objective")
        front.setflags(write=False)
        out["reference_front"] = front
    return out


def _path_constraints(constraints, nx: int, nu: int, x0: np.ndarray, controls: np.ndarray
                      ) -> tuple[CompiledConstraint, ...]:
    """The path constraints compiled; finite with their Jacobians at x_0 and ``controls``
    (mid-range, the DFET's default guess: (2, nu)), and those of x alone met at x_0; one
    ValueError naming the field otherwise."""
    compiled = compile_constraints(constraints, {"x": nx, "u": nu},
                                   "MacsProblem.path_constraints")
    for i, constraint in enumerate(compiled):
        where = f"path_constraints[{i}] ({constraint.name})"
        check_smooth(constraint, {"x": np.vstack([x0, x0]), "u": controls},
                     f"MacsProblem.{where}", ["mid-range controls", "the DFET's default guess"])
        gap = constraint.violation({"x": x0[None, :], "u": controls[:1]})[0]
        if not constraint.depends_on("u") and gap > 0:
            raise _fail(where, f"is broken by {gap:.3g} at the initial state {x0.tolist()}")
    return compiled


def _digest(problem: MacsProblem) -> str:
    """SHA-256 of everything but the model: the data and the serialised objective functions."""
    parts = [problem.name, problem.initial_state, problem.final_time, problem.control_bounds,
             sorted(problem.final_state.items()), problem.periodic_controls, problem.elements,
             problem.order, problem.control_order,
             [(c.serialized, c.lower, c.upper) for c in problem.path_constraints]]
    for objective in problem.objectives:
        parts += [objective.name, objective.unit] + [None if t is None else t.serialize()
                                     for t in (objective.mayer, objective.running)]
    digest = hashlib.sha256(repr(parts).encode())
    if problem.reference_front is not None:
        digest.update(problem.reference_front.tobytes())
    return digest.hexdigest()
