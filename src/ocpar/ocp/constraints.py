"""Path constraints lower ≤ c(·) ≤ upper: one vocabulary that every transcription enforces.

A user writes a :class:`PathConstraint` with a Python function of CasADi symbols; its
parameter *names* say what it depends on, among what the transcription has:

- ``x``: the state (multiple shooting, DFET: ODE models);
- ``q``, ``v``: the configuration and its velocity (DMOC: mechanical systems);
- ``u``: the control (every transcription).

The function returns an expression of any number of rows; ``lower`` and ``upper`` are one
number for every row or one per row (−inf/inf for a one-sided row, equal for an equality).
A shape compiles its constraints once, with its model's dimensions
(:func:`compile_constraints`), into :class:`CompiledConstraint` objects: the CasADi function
serialised to text, so that a shape stays hashable and picklable (a lambda goes to MPI ranks
and Dask workers as text, with nothing to import there). Where each transcription imposes
the rows is its own docstring's business: DMOC at nodes and interval midpoints, multiple
shooting at the samples, DFET at the quadrature points.

Errors name the field and the constraint: a function that does not evaluate, names a
variable the transcription lacks, returns no rows, a row vector or a matrix, has a row that
depends on none of its arguments, or bounds of the wrong length or with lower > upper or NaN,
are one ``ValueError``.

A row that is a norm, sqrt(s) + c with s a sum of squares (``ca.norm_2``,
``np.linalg.norm``, ``ca.sqrt(ca.sumsqr(·))``, found in the CasADi expression) or |e| + c
(s = e²: ``ca.fabs``, the norm of one entry), is compiled
as its smooth square: lower ≤ sqrt(s) + c ≤ upper is s ≤ (upper − c)² (and s ≥ (lower − c)²
where lower − c > 0), the same set since sqrt is increasing on s ≥ 0, but with a derivative at
s = 0, where the solves start (zero controls); a :class:`NormSquared` warning says so once.
Its ``violation`` is then in the squared form's units. Anything else must be finite with its
Jacobian where the solves start: each scheme checks that with :func:`check_smooth`.
"""

from __future__ import annotations

import inspect
import math
import os
import sys
import sysconfig
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np


class NormSquared(UserWarning):
    """A norm row of a path constraint compiled as its smooth square (module docstring)."""


#: What a constraint's parameter names may be, and what each is.
ARGUMENTS = {"x": "the state", "q": "the configuration", "v": "the velocity",
             "u": "the control"}


@dataclass(frozen=True)
class PathConstraint:
    """lower ≤ function(…) ≤ upper along the whole path (module docstring).

    ``function``: a Python function whose parameter names (a subset of ``x``/``q``, ``v``,
    ``u``) pick its arguments, each a CasADi column symbol, returning a CasADi expression of
    r ≥ 1 rows (a number or a column). ``lower``/``upper``: a number or r numbers (default
    c ≤ 0). ``name`` labels it in messages and reports. E.g. a thrust limit |u| ≤ 2:
    ``PathConstraint(lambda u: ca.sumsqr(u), upper=4.0, name="thrust")``."""

    function: Callable[..., Any]
    lower: float | Sequence[float] = -math.inf
    upper: float | Sequence[float] = 0.0
    name: str = "path constraint"


@dataclass(frozen=True)
class CompiledFunction:
    """A user's function of named arguments compiled for given sizes: ``arguments`` the
    names it takes (in the transcription's order) and their ``sizes``; ``serialized`` the
    CasADi function (arguments → (rows, 1)) as text, so that it hashes and pickles."""

    name: str
    arguments: tuple[str, ...]
    sizes: tuple[int, ...]
    serialized: str

    @property
    def function(self) -> ca.Function:
        """The CasADi function (arguments → (r, 1)), deserialised once per process."""
        return _deserialize(self.serialized)

    def depends_on(self, *names: str) -> bool:
        """Whether it depends on any of ``names``."""
        return any(name in self.arguments for name in names)

    def __call__(self, values: Mapping[str, Any]) -> Any:
        """The rows at ``values`` (a symbol or number per argument name; extra names are
        ignored)."""
        return self.function(*(values[name] for name in self.arguments))

    def nonfinite(self, values: Mapping[str, np.ndarray]) -> tuple[int, str] | None:
        """The first of k points (values per argument name, (k, size)) where the rows or
        their Jacobian are not finite, as (index, "value" or "derivative"); None if none."""
        return nonfinite(self.function, [np.asarray(values[a], float) for a in self.arguments])


@dataclass(frozen=True)
class CompiledConstraint(CompiledFunction):
    """A :class:`PathConstraint` compiled (:class:`CompiledFunction`), with ``lower`` and
    ``upper`` one per row."""

    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()

    @property
    def rows(self) -> int:
        """Number of rows r."""
        return len(self.lower)

    def violation(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """How far each of k points breaks the rows: values per argument name (k, size);
        returns (k,) the largest max(lower − c, c − upper, 0) (NaN where c is not finite)."""
        k = len(next(iter(values[name] for name in self.arguments)))
        rows = np.asarray(self.function.map(k)(*(np.asarray(values[name], float).T
                                                  for name in self.arguments)))
        rows = rows.reshape(self.rows, k)
        lower, upper = np.array(self.lower)[:, None], np.array(self.upper)[:, None]
        gap = np.maximum(np.maximum(lower - rows, rows - upper), 0.0).max(axis=0)
        return np.where(np.all(np.isfinite(rows), axis=0), gap, np.nan)


@lru_cache(maxsize=256)
def _deserialize(text: str) -> ca.Function:
    return ca.Function.deserialize(text)


def compile_constraints(constraints: Sequence[PathConstraint | CompiledConstraint] | None,
                        sizes: Mapping[str, int], field: str = "path_constraints"
                        ) -> tuple[CompiledConstraint, ...]:
    """``constraints`` compiled for the argument ``sizes`` a transcription has (e.g.
    ``{"x": 4, "u": 2}``); compiled ones are checked against ``sizes`` and kept. One
    ValueError naming ``field`` and the constraint for anything malformed."""
    if constraints is None:
        return ()
    if isinstance(constraints, PathConstraint | CompiledConstraint) or not isinstance(
            constraints, Sequence):
        raise ValueError(f"{field}: must be a list of PathConstraint")
    return tuple(_compile(c, sizes, f"{field}[{i}]") for i, c in enumerate(constraints))


def _compile(constraint: object, sizes: Mapping[str, int], label: str) -> CompiledConstraint:
    if isinstance(constraint, CompiledConstraint):
        _check_sizes(constraint, sizes, label)
        return constraint
    if not isinstance(constraint, PathConstraint):
        raise ValueError(f"{label}: must be a PathConstraint, got {type(constraint).__name__}")
    name = constraint.name
    if not isinstance(name, str) or not name:
        raise ValueError(f"{label}: name must be a non-empty string")
    label = f"{label} ({name})"
    compiled = compile_function(constraint.function, sizes, label, name)
    rows = compiled.function.nnz_out(0)
    lower = _bound(constraint.lower, rows, f"{label}: lower")
    upper = _bound(constraint.upper, rows, f"{label}: upper")
    if any(lo > hi or lo == math.inf or hi == -math.inf
           for lo, hi in zip(lower, upper, strict=True)):
        raise ValueError(f"{label}: needs lower <= upper, lower < inf and upper > -inf in "
                         f"every row, got {lower} and {upper}")
    serialized, lower, upper = _square_norms(compiled, lower, upper, label)
    return CompiledConstraint(name, compiled.arguments, compiled.sizes, serialized,
                              lower, upper)


def _square_norms(compiled: CompiledFunction, lower: tuple[float, ...],
                  upper: tuple[float, ...], label: str
                  ) -> tuple[str, tuple[float, ...], tuple[float, ...]]:
    """The serialised function and bounds with each norm row sqrt(s) + c (s a sum of
    squares, upper − c ≥ 0) replaced by s in [(lower − c)² if lower − c > 0 else −inf,
    (upper − c)²] (module docstring); a :class:`NormSquared` warning if any was."""
    function = compiled.function
    symbols = function.sx_in()
    rows = ca.vertsplit(function.call(symbols)[0])
    lower, upper, squared = list(lower), list(upper), []
    for i, row in enumerate(rows):
        found = _norm_row(row)
        if found is None or upper[i] - found[1] < 0:
            continue
        s, c = found
        rows[i] = s
        lo, hi = lower[i] - c, upper[i] - c
        lower[i], upper[i] = (lo * lo if lo > 0 else -math.inf), hi * hi
        squared.append(f"row {i}: {s} in [{lower[i]:.6g}, {upper[i]:.6g}]")
    if not squared:
        return compiled.serialized, tuple(lower), tuple(upper)
    warnings.warn(f"{label}: a norm is not differentiable at 0; solved exactly as its "
                  f"square ({'; '.join(squared)})", NormSquared, stacklevel=_outside_ocpar())
    serialized = ca.Function("c", symbols, [ca.vertcat(*rows)], list(compiled.arguments),
                             ["c"]).serialize()
    return serialized, tuple(lower), tuple(upper)


def _outside_ocpar() -> int:
    """The ``stacklevel`` that makes a warning issued by this function's caller name the
    first frame of the user's code: outside the ocpar package, the standard library (e.g.
    ``dataclasses.replace``) and generated code (a dataclass's ``__init__``)."""
    inside = (os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
              os.path.abspath(sysconfig.get_paths()["stdlib"]))
    frame, level = sys._getframe(1), 1
    while frame is not None and (frame.f_code.co_filename.startswith("<") or os.path.abspath(
            frame.f_code.co_filename).startswith(inside)):
        frame, level = frame.f_back, level + 1
    return level


def _norm_row(row: ca.SX) -> tuple[ca.SX, float] | None:
    """(s, c) if the scalar ``row`` is sqrt(s) + c (or c + sqrt(s), sqrt(s) − c) with s a
    sum of squares, or |e| + c (s = e²), and c a constant; else None."""
    c = 0.0
    if row.op() in (ca.OP_ADD, ca.OP_SUB):
        a, b = row.dep(0), row.dep(1)
        sign = 1.0 if row.op() == ca.OP_ADD else -1.0
        if b.is_constant() and a.op() in (ca.OP_SQRT, ca.OP_FABS):
            row, c = a, sign * float(b)
        elif a.is_constant() and b.op() in (ca.OP_SQRT, ca.OP_FABS) and sign > 0:
            row, c = b, float(a)
    if row.op() == ca.OP_FABS:   # a norm of one entry: |e| = sqrt(e²)
        return row.dep(0) ** 2, c
    if row.op() != ca.OP_SQRT or not _sum_of_squares(row.dep(0)):
        return None
    return row.dep(0), c


def _sum_of_squares(e: ca.SX) -> bool:
    """Whether ``e`` is, structurally, a sum of squares (or non-negative constants, norms)."""
    op = e.op()
    if e.is_constant():
        return float(e) >= 0
    if op in (ca.OP_SQ, ca.OP_SQRT, ca.OP_FABS):
        return True
    if op == ca.OP_MUL:
        return bool(ca.is_equal(e.dep(0), e.dep(1), 2)) or (
            _sum_of_squares(e.dep(0)) and _sum_of_squares(e.dep(1)))
    if op == ca.OP_ADD:
        return _sum_of_squares(e.dep(0)) and _sum_of_squares(e.dep(1))
    if op == ca.OP_TWICE:
        return _sum_of_squares(e.dep(0))
    return False


def nonfinite(function: ca.Function, inputs: Sequence[np.ndarray]) -> tuple[int, str] | None:
    """The first of k points (``inputs``: one (k, size) array per input of ``function``)
    where its first output or that output's Jacobian in all inputs is not finite, as
    (index, "value" or "derivative"); None if none."""
    symbols = function.sx_in()
    out = function.call(symbols)[0]
    both = ca.Function("v", symbols, [out, ca.jacobian(out, ca.veccat(*symbols))])
    k = len(inputs[0])
    value, jac = both.map(k)(*(np.asarray(a, float).reshape(k, -1).T for a in inputs))
    bad_value = ~np.all(np.isfinite(np.asarray(value).reshape(-1, k)), axis=0)
    bad_jac = ~np.all(np.isfinite(np.asarray(jac).reshape(out.numel(), k, -1)), axis=(0, 2))
    bad = np.flatnonzero(bad_value | bad_jac)
    if not len(bad):
        return None
    i = int(bad[0])
    return i, "value" if bad_value[i] else "derivative"


def check_smooth(compiled: CompiledFunction, values: Mapping[str, np.ndarray], label: str,
                 where: Sequence[str]) -> None:
    """ValueError naming ``label`` unless ``compiled`` and its Jacobian are finite at the k
    points ``values`` (per argument name, (k, size)) where the solves start; ``where`` (k
    descriptions, e.g. "agent 3's start") says which point failed."""
    found = compiled.nonfinite(values)
    if found is None:
        return
    i, what = found
    at = ", ".join(f"{a} = {np.round(np.asarray(values[a], float)[i], 6).tolist()}"
                   for a in compiled.arguments)
    if what == "value":
        raise ValueError(f"{label}: not finite at {at} ({where[i]}), where the solves start")
    raise ValueError(f"{label}: not differentiable at {at} ({where[i]}), where the solves "
                     f"start: write a bound |e| <= U as sumsqr(e) <= U**2")


def _check_sizes(compiled: CompiledFunction, sizes: Mapping[str, int], label: str) -> None:
    """ValueError unless ``compiled`` was compiled for argument sizes within ``sizes``."""
    have = dict(zip(compiled.arguments, compiled.sizes, strict=True))
    if any(sizes.get(a) != n for a, n in have.items()):
        raise ValueError(f"{label} ({compiled.name}): compiled for {have}, this transcription "
                         f"has {dict(sizes)}")


def compile_function(function: object, sizes: Mapping[str, int], label: str,
                     name: str = "f", scalar: bool = False) -> CompiledFunction:
    """``function`` (its parameter names among ``sizes``) compiled to a
    :class:`CompiledFunction` returning a column (one row if ``scalar``); compiled ones are
    checked against ``sizes`` and kept. One ValueError naming ``label`` otherwise."""
    if isinstance(function, CompiledFunction):
        _check_sizes(function, sizes, label)
        return function
    arguments = _arguments(function, sizes, label)
    symbols = {a: ca.SX.sym(a, sizes[a]) for a in arguments}
    try:
        expr = ca.SX(function(**symbols))  # type: ignore[operator]
    except Exception as exc:
        raise ValueError(f"{label}: does not evaluate on CasADi symbols "
                         f"{', '.join(f'{a} ({sizes[a]},)' for a in arguments)}: "
                         f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
    if scalar and expr.shape != (1, 1):
        raise ValueError(f"{label}: must return a scalar, got shape {expr.shape}")
    if expr.is_empty() or expr.shape[1] != 1:
        what = "a row" if expr.shape[0] == 1 else "a matrix"
        raise ValueError(f"{label}: must return a number or a column, got {what} of shape "
                         f"{expr.shape}")
    inputs = [symbols[a] for a in arguments]
    strays = set(map(str, ca.symvar(expr))) - {str(s) for v in inputs for s in ca.symvar(v)}
    if strays:
        raise ValueError(f"{label}: depends on symbols other than its arguments: "
                         f"{', '.join(sorted(strays))}")
    expr = ca.densify(expr)
    variables = ca.veccat(*inputs)
    constant = [i for i in range(expr.numel()) if not ca.depends_on(expr[i], variables)]
    if constant:
        row = "" if expr.numel() == 1 else f"row {constant[0]} "
        raise ValueError(f"{label}: {row}depends on none of its arguments "
                         f"({', '.join(arguments)}): a constant is no constraint or cost")
    serialized = ca.Function("c", inputs, [expr], list(arguments), ["c"]).serialize()
    return CompiledFunction(name, arguments, tuple(sizes[a] for a in arguments), serialized)


def _arguments(function: object, sizes: Mapping[str, int], label: str) -> tuple[str, ...]:
    """The names ``function`` takes, in the order of ``sizes``, or ValueError."""
    if not callable(function):
        raise ValueError(f"{label}: function must be callable")
    try:
        names = list(inspect.signature(function).parameters)
    except (TypeError, ValueError):
        raise ValueError(f"{label}: function has no inspectable parameters") from None
    have = ", ".join(f"{a} ({ARGUMENTS[a]})" for a in sizes)
    unknown = [n for n in names if n not in sizes]
    if unknown or not names:
        what = f"takes {unknown[0]!r}" if unknown else "takes no arguments"
        raise ValueError(f"{label}: function {what}; it may take {have}")
    return tuple(a for a in sizes if a in names)


def _bound(value: object, rows: int, label: str) -> tuple[float, ...]:
    """``value`` (a number or ``rows`` numbers) as ``rows`` floats, no NaN."""
    try:
        array = np.broadcast_to(np.asarray(value, float), (rows,))
    except (TypeError, ValueError):
        raise ValueError(f"{label}: must be a number or {rows} numbers") from None
    if np.isnan(array).any():
        raise ValueError(f"{label}: NaN")
    return tuple(float(b) for b in array)


class ConstraintRows:
    """The rows a transcription appends to its NLP, with their bounds: ``add`` a constraint
    at the points where the transcription imposes it, then read ``expr`` (a column),
    ``lower`` and ``upper`` (arrays, one entry per row)."""

    def __init__(self) -> None:
        self._rows: list[Any] = []
        self._lower: list[float] = []
        self._upper: list[float] = []

    def add(self, constraint: CompiledConstraint, points: Sequence[Mapping[str, Any]]) -> None:
        """``constraint`` at each of ``points`` (symbols per argument name)."""
        for point in points:
            self._rows.append(constraint(point))
            self._lower += constraint.lower
            self._upper += constraint.upper

    @property
    def count(self) -> int:
        """Number of rows."""
        return len(self._lower)

    @property
    def expr(self) -> ca.SX:
        return ca.vertcat(*self._rows) if self._rows else ca.SX(0, 1)

    @property
    def lower(self) -> np.ndarray:
        return np.array(self._lower, float)

    @property
    def upper(self) -> np.ndarray:
        return np.array(self._upper, float)


def bound_sizes(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """max(|lo|, |hi|) over the finite bounds of each entry (1 where that is 0): the size an
    elastic slack of that bound is measured against."""
    size = np.maximum(*(np.where(np.isfinite(b), np.abs(b), 0.0)
                        for b in (np.asarray(lower, float), np.asarray(upper, float))))
    return np.where(size > 0, size, 1.0)


def check_control_bounds(bounds: object, nu: int) -> tuple[tuple[float, float], ...]:
    """``bounds`` as ``nu`` pairs (lo, hi) of floats with lo ≤ hi, lo < ∞, hi > −∞, or
    ValueError naming the field."""
    try:
        pairs = tuple((float(lo), float(hi)) for lo, hi in bounds)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        raise ValueError(f"control_bounds: must be {nu} pairs (lo, hi) of numbers") from None
    if len(pairs) != nu:
        raise ValueError(f"control_bounds: must be {nu} pairs (lo, hi), one per control entry, "
                         f"got {len(pairs)}")
    for j, (lo, hi) in enumerate(pairs):
        if not (lo <= hi and lo < np.inf and hi > -np.inf):
            raise ValueError(f"control_bounds: entry {j} needs lo <= hi (finite on one side at "
                             f"least, no NaN), got ({lo}, {hi})")
    return pairs
