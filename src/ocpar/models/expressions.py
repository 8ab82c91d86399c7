"""Models written as CasADi expressions, with nothing of the user's to install on the workers.

:func:`ode_model` turns symbols x, u and expressions ẋ = f(x, u), g(x, u) into an
:class:`ExpressionOde` (an :class:`~ocpar.models.OdeModel`: pursuit, MACS, multiple shooting,
DFET); :func:`lagrangian_model` turns q, q̇, u and L(q, q̇), F(q, u) (and holonomic constraints
c(q) = 0) into an :class:`ExpressionLagrangian` (a :class:`~ocpar.models.MechanicalSystem`:
the formation scheme's DMOC agents). Each holds its CasADi functions serialised
(``casadi.Function.serialize``) as text, so the model is a value object of ocpar's own class:
it pickles as that text and unpickles wherever ocpar is installed (every MPI rank, every Dask
worker) without importing the module that built it, and equal content compares and hashes
equal, so a worker builds a shape's transcription once however often it receives it.

Expressions may be ``casadi.SX`` or ``casadi.MX`` (MX is expanded to SX: the transcriptions
evaluate models on SX symbols; functions inside that have no SX form, e.g. an interpolant of
tabulated data, stay calls), numbers, or lists of them (stacked as a column); each may also
be a ``casadi.Function`` of the same arguments, called on the symbols.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np

from ocpar.models.labels import check_labels

#: A CasADi expression, a number, a list of them (a column) or a ``casadi.Function``.
Expression = Any
#: A bound: one number for every entry, or one per entry.
Bound = float | Sequence[float]
#: Names or units of a vector's entries: one string per entry (units: or one for all).
Strings = str | Sequence[str]
#: Gauss–Newton steps of :meth:`ExpressionLagrangian.project` at most, and its tolerance on |c|.
PROJECT_STEPS, PROJECT_TOL = 50, 1e-13


@lru_cache(maxsize=256)
def _function(text: str) -> ca.Function:
    """The CasADi function serialised as ``text``, deserialised once per process."""
    return ca.Function.deserialize(text)


def _symbols(value: object, label: str) -> ca.SX | ca.MX:
    """``value`` checked to be a column of CasADi symbols (SX or MX) with at least one entry."""
    if not isinstance(value, ca.SX | ca.MX) or not value.is_column() or value.is_empty() \
            or not value.is_valid_input():
        raise ValueError(f"{label}: must be a column of CasADi symbols (casadi.SX.sym or "
                         f"casadi.MX.sym), got {_describe(value)}")
    return value


def _describe(value: object) -> str:
    if isinstance(value, ca.SX | ca.MX | ca.DM):
        return f"a {type(value).__name__} expression of shape {value.shape}"
    return f"an object of type {type(value).__name__}"


def _expression(value: Expression, inputs: Sequence[ca.SX | ca.MX], label: str
                ) -> ca.SX | ca.MX:
    """``value`` as an expression of the type of ``inputs`` (a Function is called on them)."""
    kind = type(inputs[0])
    try:
        if isinstance(value, ca.Function):
            if value.n_in() != len(inputs) or value.n_out() != 1:
                raise ValueError(f"takes {value.n_in()} arguments and returns {value.n_out()}, "
                                 f"expected {len(inputs)} and 1")
            value = value(*inputs)
        elif isinstance(value, list | tuple):
            value = ca.vertcat(*value)
        return kind(value)
    except Exception as exc:  # a user's input: any failure is one line naming the field
        raise ValueError(f"{label}: not a CasADi expression of the symbols: "
                         f"{type(exc).__name__}: {exc}".splitlines()[0]) from None


def _serialize(name: str, inputs: Sequence[tuple[str, ca.SX | ca.MX]],
               outputs: Sequence[tuple[str, Expression, tuple[int, int]]]) -> str:
    """The CasADi function ``name`` (inputs → outputs) as text: each output (label, its
    expression, its shape) checked to have that shape and to depend on ``inputs`` alone; MX
    expanded to SX."""
    symbols = [s for _, s in inputs]
    kinds = {type(s) for s in symbols}
    if len(kinds) > 1:
        raise ValueError(f"{', '.join(n for n, _ in inputs)}: mix SX and MX symbols; "
                         "use one kind")
    exprs = []
    for label, value, shape in outputs:
        expr = _expression(value, symbols, label)
        if expr.shape != shape:
            raise ValueError(f"{label}: shape {expr.shape}, expected {shape}")
        exprs.append(ca.densify(expr))
    names = ", ".join(n for n, _ in inputs)
    try:
        function = ca.Function(name, symbols, exprs, [n for n, _ in inputs],
                               [label.split(".")[-1] for label, _, _ in outputs])
    except RuntimeError:  # free symbols: name them (by their names, as the user wrote them)
        known = {str(e) for s in symbols for e in ca.symvar(s)}
        for (label, _, _), expr in zip(outputs, exprs, strict=True):
            strays = sorted({str(e) for e in ca.symvar(expr)} - known)
            if strays:
                raise ValueError(f"{label}: depends on symbols other than {names}: "
                                 f"{', '.join(strays)}") from None
        raise ValueError(f"{name}: depends on symbols other than {names} (others of the "
                         "same names)") from None
    if function.is_a("MXFunction"):
        try:
            function = function.expand()
        except Exception as exc:
            raise ValueError(f"{name}: its MX expressions do not expand to SX (the "
                             f"transcriptions evaluate models on SX symbols): {exc}"
                             .splitlines()[0]) from None
    return function.serialize()


def _bounds(bounds: tuple[Bound, Bound] | None, n: int, label: str
            ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(lower, upper), each a number or ``n`` numbers, as two tuples of ``n`` floats with
    lower ≤ upper and no NaN; None: unbounded."""
    if bounds is None:
        return (-math.inf,) * n, (math.inf,) * n
    try:
        lower, upper = (np.broadcast_to(np.asarray(b, float), (n,)) for b in bounds)
    except (TypeError, ValueError):
        raise ValueError(f"{label}: expected (lower, upper), each a number or {n} numbers, "
                         f"got {bounds!r}") from None
    if np.isnan(lower).any() or np.isnan(upper).any() or (lower > upper).any():
        raise ValueError(f"{label}: need lower <= upper, no NaN, got {bounds!r}")
    return tuple(map(float, lower)), tuple(map(float, upper))


@dataclass(frozen=True)
class ExpressionOde:
    """A controlled ODE ẋ = f(x, u) with running cost g(x, u) (an
    :class:`~ocpar.models.OdeModel`), held as the serialised CasADi function
    ``function`` (x (nx,), u (nu,)) → (f (nx,), g). Built by :func:`ode_model`; bounds as tuples
    (±inf where unbounded); names and units as :mod:`ocpar.models.labels` reads them."""

    function: str
    nx: int
    nu: int
    state_lower: tuple[float, ...]
    state_upper: tuple[float, ...]
    control_lower: tuple[float, ...]
    control_upper: tuple[float, ...]
    state_names: tuple[str, ...] | None = None
    control_names: tuple[str, ...] | None = None
    state_units: str | tuple[str, ...] | None = None
    control_units: str | tuple[str, ...] | None = None
    time_unit: str = "1"
    cost_unit: str = "1"
    position_indices: tuple[int, ...] | None = None
    name: str = ""

    def __repr__(self) -> str:
        return f"ExpressionOde(nx={self.nx}, nu={self.nu}, {len(self.function)} characters)"

    def rhs(self, x: Any, u: Any) -> Any:
        """f(x, u) (nx, 1): CasADi symbols in, an expression out; numbers in, a ``DM`` out."""
        return _function(self.function)(x, u)[0]

    def running_cost(self, x: Any, u: Any) -> Any:
        """g(x, u), a scalar."""
        return _function(self.function)(x, u)[1]

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (nx,) on the state."""
        return np.array(self.state_lower), np.array(self.state_upper)

    def control_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (nu,) on the control."""
        return np.array(self.control_lower), np.array(self.control_upper)


def ode_model(x: ca.SX | ca.MX, u: ca.SX | ca.MX, rhs: Expression, cost: Expression = 0.0, *,
              state_bounds: tuple[Bound, Bound] | None = None,
              control_bounds: tuple[Bound, Bound] | None = None,
              state_names: Sequence[str] | None = None,
              control_names: Sequence[str] | None = None,
              state_units: Strings | None = None, control_units: Strings | None = None,
              time_unit: str = "1", cost_unit: str = "1",
              position_indices: Sequence[int] | None = None, name: str = "") -> ExpressionOde:
    """The model ẋ = ``rhs``, running cost ``cost``, of the state symbols ``x`` (nx, 1) and
    control symbols ``u`` (nu, 1) (``casadi.SX.sym`` or ``casadi.MX.sym``): ``rhs`` an
    expression (nx, 1) (or a list of nx), ``cost`` a scalar (default 0: MACS problems give
    their objectives apart), either also a ``casadi.Function`` of (x, u).
    ``state_bounds``/``control_bounds``: (lower, upper), each a number or one per entry
    (default unbounded). Names and units: :mod:`ocpar.models.labels`; ``position_indices``
    the state entries that are a position in space (for schemes that ask); ``name`` the
    model's name in the results (default ``ExpressionOde``). One ValueError naming the
    argument for bad input.

    >>> import casadi as ca
    >>> x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    >>> model = ode_model(x, u, [x[1], u], u**2, control_bounds=(-1, 1))
    >>> model.nx, model.nu
    (2, 1)
    """
    x, u = _symbols(x, "x"), _symbols(u, "u")
    nx, nu = x.numel(), u.numel()
    function = _serialize("ode", [("x", x), ("u", u)],
                          [("rhs", rhs, (nx, 1)), ("cost", cost, (1, 1))])
    model = ExpressionOde(function, nx, nu, *_bounds(state_bounds, nx, "state_bounds"),
                          *_bounds(control_bounds, nu, "control_bounds"),
                          **_labels(nx, state_names, control_names, state_units, control_units,
                                    time_unit, cost_unit, position_indices, name))
    check_labels(model, nx, nu, "ode_model")
    return model


def _labels(n: int, state_names: Sequence[str] | None, control_names: Sequence[str] | None,
            state_units: Strings | None, control_units: Strings | None, time_unit: str,
            cost_unit: str, position_indices: Sequence[int] | None, name: str
            ) -> dict[str, Any]:
    """The names, units, position entries and name of a model of ``n`` state entries, as
    its fields (sequences as tuples: hashable; checked by :func:`check_labels` once built)."""
    if not isinstance(name, str):
        raise ValueError(f"name: must be a string, got {name!r}")
    def strings(value: Strings | None) -> str | tuple[str, ...] | None:
        return value if value is None or isinstance(value, str) else tuple(value)

    return {"state_names": strings(state_names), "control_names": strings(control_names),
            "state_units": strings(state_units), "control_units": strings(control_units),
            "time_unit": time_unit, "cost_unit": cost_unit,
            "position_indices": _indices(position_indices, n), "name": name}


def _indices(indices: Sequence[int] | None, n: int) -> tuple[int, ...] | None:
    """``position_indices`` checked: distinct entries of 0 … n−1."""
    if indices is None:
        return None
    out = tuple(indices)
    if not out or len(set(out)) != len(out) or not all(
            isinstance(i, int | np.integer) and 0 <= i < n for i in out):
        raise ValueError(f"position_indices: need distinct entries of 0..{n - 1}, got {out!r}")
    return tuple(int(i) for i in out)


@dataclass(frozen=True)
class ExpressionLagrangian:
    """A controlled mechanical system (a :class:`~ocpar.models.MechanicalSystem`): the
    serialised CasADi functions ``lagrangian_function`` (q, q̇) → L, ``force_function``
    (q, u) → F (nq,) and ``constraints_function`` q → c (nc,) (None: no constraints). Built
    by :func:`lagrangian_model`; autonomous (one L for every DMOC interval)."""

    lagrangian_function: str
    force_function: str
    constraints_function: str | None
    nq: int
    nu: int
    n_constraints: int = 0
    state_names: tuple[str, ...] | None = None
    control_names: tuple[str, ...] | None = None
    state_units: str | tuple[str, ...] | None = None
    control_units: str | tuple[str, ...] | None = None
    time_unit: str = "1"
    cost_unit: str = "1"
    position_indices: tuple[int, ...] | None = None
    cost_groups: tuple[tuple[str, int, int], ...] = ()
    name: str = ""

    def __repr__(self) -> str:
        return (f"ExpressionLagrangian(nq={self.nq}, nu={self.nu}, "
                f"n_constraints={self.n_constraints})")

    def lagrangian(self, q: Any, qdot: Any, interval: int = 0) -> Any:
        """L(q, q̇), a scalar (the same on every interval)."""
        return _function(self.lagrangian_function)(q, qdot)

    def generalized_force(self, q: Any, u: Any) -> Any:
        """F(q, u) (nq, 1)."""
        return _function(self.force_function)(q, u)

    def constraints(self, q: Any) -> Any:
        """c(q) (nc, 1); zero rows without constraints."""
        if self.constraints_function is None:
            return ca.DM(0, 1)
        return _function(self.constraints_function)(q)

    @property
    def cost_parts(self) -> dict[str, tuple[int, int]]:
        """The cost ∫|u|² dt split into named control groups {name: (first, last)}."""
        return {name: (first, last) for name, first, last in self.cost_groups}

    def project(self, q: np.ndarray) -> np.ndarray:
        """Rows (m, nq) moved onto c(q) = 0 by Gauss–Newton minimum-norm steps
        q ← q − Jᵀ(J Jᵀ)⁻¹ c(q) (the nearest configuration to first order; for initial
        guesses); rows where a step is not finite (J Jᵀ singular) are kept."""
        out = np.array(q, float)
        if self.constraints_function is None or not len(out):
            return out
        step = _projection_step(self.constraints_function).map(len(out))
        for _ in range(PROJECT_STEPS):
            nxt, residual = (np.asarray(a) for a in step(out.T))
            keep = np.all(np.isfinite(nxt), axis=0)
            out[keep] = nxt.T[keep]
            if not np.nanmax(np.abs(residual)) > PROJECT_TOL:
                break
        return out


@lru_cache(maxsize=64)
def _projection_step(text: str) -> ca.Function:
    """q → (q − Jᵀ(J Jᵀ)⁻¹ c(q), c(q)) of the constraints serialised as ``text``."""
    c = _function(text)
    q = ca.SX.sym("q", c.size1_in(0))
    value = c(q)
    jac = ca.jacobian(value, q)
    return ca.Function("project", [q], [q - jac.T @ ca.solve(jac @ jac.T, value), value])


def lagrangian_model(q: ca.SX | ca.MX, qdot: ca.SX | ca.MX, L: Expression,
                     u: ca.SX | ca.MX, force: Expression, *,
                     constraints: Expression | None = None,
                     state_names: Sequence[str] | None = None,
                     control_names: Sequence[str] | None = None,
                     state_units: Strings | None = None, control_units: Strings | None = None,
                     time_unit: str = "1", cost_unit: str = "1",
                     position_indices: Sequence[int] | None = None,
                     cost_parts: Mapping[str, tuple[int, int]] | None = None,
                     name: str = "") -> ExpressionLagrangian:
    """The mechanical system of Lagrangian ``L`` (a scalar of the configuration symbols ``q``
    (nq, 1) and velocity symbols ``qdot`` (nq, 1)), generalised force ``force`` (nq, 1) of q
    and the control symbols ``u`` (nu, 1), and optional holonomic ``constraints`` c(q) = 0
    (nc, 1); each also a ``casadi.Function`` of those arguments. Names and units:
    :mod:`ocpar.models.labels` (the state is q); ``position_indices`` the entries of q that
    are the agent's position (default: the first d, d the formation curve's dimension);
    ``cost_parts`` {name: (first, last)} control groups the results split the cost into;
    ``name`` the model's name in the results (default ``ExpressionLagrangian``). One
    ValueError naming the argument for bad input.

    >>> import casadi as ca
    >>> q, v, u = ca.SX.sym("q", 2), ca.SX.sym("v", 2), ca.SX.sym("u", 2)
    >>> point = lagrangian_model(q, v, 0.5 * ca.dot(v, v), u, u)
    >>> point.nq, point.nu
    (2, 2)
    """
    q, qdot, u = _symbols(q, "q"), _symbols(qdot, "qdot"), _symbols(u, "u")
    nq, nu = q.numel(), u.numel()
    if qdot.numel() != nq:
        raise ValueError(f"qdot: {qdot.numel()} entries, q has {nq}")
    lag = _serialize("L", [("q", q), ("qdot", qdot)], [("L", L, (1, 1))])
    forces = _serialize("F", [("q", q), ("u", u)], [("force", force, (nq, 1))])
    held, nc = None, 0
    if constraints is not None:
        expr = _expression(constraints, [q], "constraints")
        nc = expr.numel()
        if nc == 0 or not expr.is_column():
            raise ValueError(f"constraints: must be a column of at least one entry, got shape "
                             f"{expr.shape}")
        held = _serialize("c", [("q", q)], [("constraints", expr, (nc, 1))])
    groups = tuple((str(name), int(a), int(b)) for name, (a, b) in (cost_parts or {}).items())
    if any(not 0 <= a < b <= nu for _, a, b in groups):
        raise ValueError(f"cost_parts: each (first, last) needs 0 <= first < last <= {nu}, "
                         f"got {dict(cost_parts or {})!r}")
    model = ExpressionLagrangian(lag, forces, held, nq, nu, nc, cost_groups=groups,
                                 **_labels(nq, state_names, control_names, state_units,
                                           control_units, time_unit, cost_unit,
                                           position_indices, name))
    check_labels(model, nq, nu, "lagrangian_model")
    return model
