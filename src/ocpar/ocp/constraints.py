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
variable the transcription lacks, returns no rows or a matrix, or bounds of the wrong length
or with lower > upper or NaN, are one ``ValueError``.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import casadi as ca
import numpy as np

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
    return CompiledConstraint(name, compiled.arguments, compiled.sizes, compiled.serialized,
                              lower, upper)


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
    if expr.is_empty() or min(expr.shape) != 1:
        raise ValueError(f"{label}: must return a number or a column, got shape {expr.shape}")
    expr = ca.vec(expr)
    inputs = [symbols[a] for a in arguments]
    strays = set(map(str, ca.symvar(expr))) - {str(s) for v in inputs for s in ca.symvar(v)}
    if strays:
        raise ValueError(f"{label}: depends on symbols other than its arguments: "
                         f"{', '.join(sorted(strays))}")
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
