"""One schema for a scheme's options: a frozen dataclass whose fields are the options.

Each field is declared once with :func:`option` (default, help text, choices, range); the
command line (:func:`add_options`), the keys of a TOML configuration (:mod:`ocpar.config`)
and Python (construct the dataclass) are all read from it. The field's type says how an option
is written: ``bool`` a flag (``--quiet``; TOML ``true``/``false``), ``int`` and ``float`` a
number, ``str`` a string, ``tuple[float, ...]`` a list of numbers (``--initial-angles
0.1,0.2,0.3``; a TOML array), ``X | None`` an option that may stay unset, ``dict`` a table of
keyword arguments (``--problem-arg KEY=VALUE`` repeated; a TOML table; with ``dotted``
its keys are dotted names, ``--solver-option ipopt.tol=1e-8``, a TOML table of sub-tables).

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Example:
...     steps: int = option(10, "number of steps", low=1)
>>> [spec.flag for spec in option_specs(Example).values()]
['--steps']
"""

from __future__ import annotations

import argparse
import json
import math
import tomllib
import types
import typing
from collections.abc import Sequence
from dataclasses import MISSING, dataclass, field, fields
from functools import cache
from typing import Any

#: How a field's type is written: a flag, a number, a string or a table of scalars.
KINDS = {bool: "flag", int: "integer", float: "number", str: "string", dict: "table",
         tuple: "list"}


def option(default: Any = MISSING, help: str = "", *, name: str | None = None,
           flag: str | None = None, choices: typing.Iterable[Any] | None = None,
           low: float | None = None, high: float | None = None, above: float | None = None,
           metavar: str | None = None, group: str | None = None,
           default_factory: Any = MISSING, dotted: bool = False) -> Any:
    """A dataclass field that is also an option: ``name`` its configuration key (default: the
    field's name), ``flag`` its command-line flag (default ``--`` + name with dashes),
    ``choices`` the values allowed, ``low``/``high`` inclusive bounds, ``above`` an exclusive
    lower bound, ``group`` the heading of ``--help`` it is listed under; ``dotted``: a table
    whose keys are dotted names (``ipopt.tol``)."""
    metadata = {"help": help, "name": name, "flag": flag,
                "choices": tuple(choices) if choices is not None else None,
                "low": low, "high": high, "above": above, "metavar": metavar, "group": group,
                "dotted": dotted}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata={"option": metadata})
    return field(default=default, metadata={"option": metadata})


@dataclass(frozen=True)
class OptionSpec:
    """One option of an options dataclass, as the command line and TOML see it."""

    field: str            # max_evaluations
    key: str              # max_evals (the TOML key)
    flag: str             # --max-evals
    kind: str             # "flag", "integer", "number", "string", "table" or "list"
    optional: bool        # None allowed (the option may stay unset)
    default: Any
    help: str
    choices: tuple | None
    low: float | None
    high: float | None
    above: float | None
    metavar: str | None
    group: str | None
    dotted: bool = False   # a table whose keys are dotted names (ipopt.tol)

    def check(self, value: Any) -> Any:
        """``value`` (already of the option's type) if it is in range; else ValueError with a
        message naming what is expected."""
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"invalid choice {value!r} (choose from "
                             f"{', '.join(map(str, self.choices))})")
        if self.kind in ("integer", "number"):
            if self.above is not None and not (math.isfinite(value) and value > self.above):
                what = "positive" if self.above == 0 else f"above {self.above:g},"
                raise ValueError(f"expected a {what} finite number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"expected a finite number, got {value!r}")
            if (self.low is not None and value < self.low) or \
                    (self.high is not None and value > self.high):
                raise ValueError(f"expected {self._range()}, got {value!r}")
        if self.kind == "list":
            value = numbers(value)
        return value

    def _range(self) -> str:
        integer = self.kind == "integer"
        what = "an integer" if integer else "a number"

        def text(bound: float) -> str:   # an integer in full: 10000000, not 1e+07
            return str(int(bound)) if integer else f"{bound:g}"

        if self.low is not None and self.high is not None:
            return f"{what} between {text(self.low)} and {text(self.high)}"
        if self.low is not None:
            return f"{what} of at least {text(self.low)}"
        return f"{what} of at most {text(self.high)}"

    def parse(self, text: str) -> Any:
        """The option's value from command-line ``text`` (ValueError if it is not one)."""
        if self.kind == "integer":
            try:
                value: Any = int(text)
            except ValueError:
                raise ValueError(f"expected an integer, got {text!r}") from None
        elif self.kind == "number":
            try:
                value = float(text)
            except ValueError:
                raise ValueError(f"expected a number, got {text!r}") from None
        elif self.kind == "list":
            parsed = parse_value(text if text.lstrip().startswith("[") else f"[{text}]")
            if not isinstance(parsed, list):
                raise ValueError(f"expected numbers separated by commas, got {text!r}")
            value = parsed
        else:
            value = text
        return self.check(value)


def numbers(value: Any) -> tuple[float, ...]:
    """``value`` (a list or tuple of finite numbers) as a tuple of floats, or ValueError."""
    if not isinstance(value, list | tuple) or not value or not all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
            for x in value):
        raise ValueError(f"expected a non-empty list of finite numbers, got {value!r}")
    return tuple(float(x) for x in value)


def _kind(annotation: Any) -> tuple[str, bool]:
    args = typing.get_args(annotation)
    optional = isinstance(annotation, types.UnionType) and type(None) in args
    base = next(a for a in args if a is not type(None)) if optional else annotation
    base = typing.get_origin(base) or base
    if base not in KINDS:
        raise TypeError(f"an option's type must be one of bool, int, float, str, dict, "
                        f"tuple[float, ...] (or X | None), not {annotation}")
    return KINDS[base], optional


@cache
def option_specs(cls: type) -> dict[str, OptionSpec]:
    """Every option of the options dataclass ``cls`` by configuration key, in field order.
    Every field must be declared with :func:`option`."""
    hints = typing.get_type_hints(cls)
    specs = {}
    for f in fields(cls):
        meta = f.metadata.get("option")
        if meta is None:
            raise TypeError(f"{cls.__name__}.{f.name} is not declared with ocpar.options.option")
        kind, optional = _kind(hints[f.name])
        key = meta["name"] or f.name
        default = f.default if f.default_factory is MISSING else f.default_factory()
        specs[key] = OptionSpec(
            field=f.name, key=key, flag=meta["flag"] or "--" + key.replace("_", "-"),
            kind=kind, optional=optional, default=default, help=meta["help"],
            choices=meta["choices"], low=meta["low"], high=meta["high"], above=meta["above"],
            metavar=meta["metavar"], group=meta["group"], dotted=meta["dotted"])
    return specs


def parse_value(text: str) -> Any:
    """``text`` read as a TOML value (``2``, ``1e-5``, ``true``, ``"a b"``, ``{ n = 4 }``), or
    ``text`` itself when it is not one (``dask``, ``runs/x``)."""
    try:
        parsed = tomllib.loads(f"value = {text}")
    except tomllib.TOMLDecodeError:
        return text
    return parsed["value"] if set(parsed) == {"value"} else text


def toml_scalar(value: bool | int | float | str) -> str:
    """``value`` written as a TOML scalar (read back by :func:`parse_value`)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    return json.dumps(value, ensure_ascii=False)


def parse_table(items: list[str], flag: str, dotted: bool = False) -> dict[str, Any]:
    """Repeated ``KEY=VALUE`` items of ``flag`` as a dict (VALUE a TOML scalar, or else a
    string: :func:`parse_value`); with ``dotted`` KEY is Python names joined by dots."""
    table: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not is_key(key, dotted):
            what = "Python names joined by dots" if dotted else "a Python name"
            raise ValueError(f"{flag}: expected KEY=VALUE with KEY {what}, got {item!r}")
        if key in table:
            raise ValueError(f"{flag}: {key} is given more than once")
        value = parse_value(text)
        if not isinstance(value, bool | int | float | str):
            raise ValueError(f"{flag}: {key}: expected a scalar, got {text!r}")
        table[key] = value
    return table


def is_key(key: str, dotted: bool = False) -> bool:
    """Whether ``key`` is a table's key: a Python name (with ``dotted``, names joined by
    dots)."""
    return all(part.isidentifier() for part in (key.split(".") if dotted else [key]))


def add_options(parser: argparse.ArgumentParser, cls: type, *, first: Sequence[str] = (),
                first_title: str = "essentials", order: Sequence[str | None] = (),
                untitled: str | None = None) -> dict[str | None, Any]:
    """Add one command-line option per field of ``cls``; an option not given stays out of the
    namespace (so :func:`options_from_namespace` knows what was given). ``--help`` lists the
    options of keys ``first`` in that order under ``first_title``, then the groups ``order``
    names (None: the options declared without a group, titled ``untitled``), then the others
    in field order; each option's help ends with its default (:func:`shown_default`).
    Returns the argument groups by title."""
    specs = option_specs(cls)
    listed = [specs[key] for key in first] + [s for s in specs.values() if s.key not in first]
    grouped: dict[str | None, list[OptionSpec]] = {}
    for spec in listed:
        grouped.setdefault(first_title if spec.key in first else spec.group, []).append(spec)
    titles = [first_title] + [g for g in order if g in grouped and g != first_title]
    titles += [g for g in grouped if g not in titles]
    groups = {}
    for title in titles:
        groups[title] = parser.add_argument_group(untitled if title is None else title)
        for spec in grouped[title]:
            _add_option(groups[title], spec)
    return groups


def shown_default(spec: OptionSpec) -> str:
    """`` (default VALUE)`` for ``--help``: an option's default value; `` (default: none)``
    for a table (empty unless given); nothing for a flag (off unless given) or an option
    unset by default (its help says what unset means)."""
    if spec.kind == "table":
        return " (default: none)"
    if spec.default is None or spec.kind == "flag":
        return ""
    value = ",".join(f"{x:g}" for x in spec.default) if spec.kind == "list" else spec.default
    return f" (default {value})"


def _add_option(target: Any, spec: OptionSpec) -> None:
    common = {"dest": spec.key, "default": argparse.SUPPRESS,
              "help": spec.help + shown_default(spec)}
    if spec.kind == "flag":
        target.add_argument(spec.flag, action="store_true", **common)
    elif spec.kind == "table":
        target.add_argument(spec.flag, action="append", metavar=spec.metavar or "KEY=VALUE",
                            **common)
    else:
        shown_choices = "{" + ",".join(map(str, spec.choices)) + "}" if spec.choices else None
        target.add_argument(spec.flag, type=_converter(spec),
                            metavar=spec.metavar or shown_choices, **common)


def _converter(spec: OptionSpec):
    def convert(text: str) -> Any:
        try:
            return spec.parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    convert.__name__ = spec.kind
    return convert


def options_from_namespace(cls: type, namespace: argparse.Namespace) -> tuple[Any, frozenset]:
    """The options dataclass ``cls`` built from a namespace of :func:`add_options`, and the
    keys given explicitly. Raises ValueError (a table item that is not KEY=VALUE, or the
    dataclass's own checks)."""
    given = vars(namespace)
    values = {}
    for key, spec in option_specs(cls).items():
        if key in given:
            value = given[key]
            values[spec.field] = parse_table(value, spec.flag, spec.dotted) \
                if spec.kind == "table" else value
    return cls(**values), frozenset(k for k in given if k in option_specs(cls))


def project(options: Any, cls: type) -> Any:
    """The dataclass ``cls`` with the fields it shares with ``options`` (e.g. a scheme's solver
    settings out of its run options)."""
    return cls(**{f.name: getattr(options, f.name) for f in fields(cls)})
