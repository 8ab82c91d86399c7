"""Run configurations: one TOML file describes a run of any scheme.

A configuration names its scheme and then sets, with one flat key each, the options of that
scheme's command line (``python -m ocpar.formation|pursuit|macs``): the key of ``--max-evals``
is ``max_evals``. There are no tables; comments group the keys::

    scheme = "formation"          # formation, pursuit or macs

    # the problem and the scheme's options
    problem = "point-mass-plane"
    agents = 60
    radius = 10.0
    ordering = "keep"

    # where it runs and what it writes
    backend = "dask"              # omit: serial, or mpi under mpirun
    workers = 2
    output = "runs/formation-60"  # relative to the current directory, as on the command line
    quiet = false

The valid keys are the fields of the scheme's options dataclass (:mod:`ocpar.options`;
``ocpar.formation.run.FormationRun`` etc.), from which the scheme's command line is generated
too, so a new option has its key without any change here. Values:

* an option that takes a value gets a TOML scalar of its type: an integer for integer options
  (``agents = 60``), an integer or float for float options (``radius = 10.0``, ``inf``), a
  string for the others (``backend = "dask"``); it becomes the option's text on the command
  line;
* a flag (``--quiet``, ``--no-reference``) gets a boolean: true gives the flag, false leaves
  it out;
* ``problem = "package.module:factory"`` names a problem factory (:mod:`ocpar.references`),
  and the table ``[problem_args]`` (after every top-level key, as TOML requires) its keyword
  arguments, scalars each: ``--problem-arg KEY=VALUE`` on the command line;
* the table ``[solver_options]`` sets the inner solvers' own options (``ipopt.tol = 1e-8``,
  or a sub-table ``[solver_options.ipopt]``; :mod:`ocpar.ocp.solver_options`):
  ``--solver-option ipopt.tol=1e-8`` on the command line.

* an option that takes a list of numbers gets a TOML array of numbers
  (``initial_angles = [0.1, 0.6]``), numbers separated by commas on the command line;

Unknown keys (with a suggestion when one is close), values of the wrong type, other arrays and
tables raise :class:`ConfigError`, whose message is one line ``CONFIG: KEY: problem``.
Everything else (ranges, choices, combinations, the problem itself) is left to the scheme's
command line: :meth:`RunConfig.argv` is the scheme's command line, run by its ``main(argv)``,
so a configuration and the equivalent command line are the same run with the same
``result.json``.

Example configurations for the papers' examples are packaged in ``ocpar/configs/``
(:func:`examples`); :func:`load_config` takes a path or such a name.
"""

from __future__ import annotations

import argparse
import difflib
import shlex
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

from ocpar.options import is_key, option_specs, parse_value, toml_scalar
from ocpar.schemes import SCHEMES, scheme_class

EXAMPLES_PACKAGE = "ocpar.configs"


class ConfigError(ValueError):
    """A configuration that cannot be run; the message is one line ``WHERE: KEY: problem``."""


@dataclass(frozen=True)
class Option:
    """One command-line option of a scheme, as a configuration key."""

    key: str     # max_evals
    flag: str    # --max-evals
    kind: str    # "flag", "integer", "number", "string", "table" or "list"
    dotted: bool = False   # a table whose keys are dotted names (ipopt.tol)


@dataclass(frozen=True)
class RunConfig:
    """A checked configuration: the scheme and its options in the file's order."""

    scheme: str
    options: dict[str, Any] = field(default_factory=dict)
    source: str = "<config>"

    def argv(self) -> list[str]:
        """The scheme's command-line arguments (of ``python -m ocpar.<scheme>``)."""
        by_key = scheme_options(self.scheme)
        argv: list[str] = []
        for key, value in self.options.items():
            option = by_key[key]
            if option.kind == "flag":
                argv += [option.flag] if value else []
                continue
            if option.kind == "table":
                argv += [f"{option.flag}={name}={toml_scalar(item)}"
                         for name, item in value.items()]
                continue
            if option.kind == "list":
                argv += [f"{option.flag}={','.join(toml_scalar(float(x)) for x in value)}"]
                continue
            text = repr(value) if isinstance(value, float) else str(value)
            # a value that starts with "-" would read as an option: attach it with "="
            argv += [f"{option.flag}={text}"] if text.startswith("-") else [option.flag, text]
        return argv

    def without(self, keys: frozenset[str]) -> RunConfig:
        """This configuration without ``keys`` (set again by flags on the command line)."""
        return RunConfig(self.scheme, {key: value for key, value in self.options.items()
                                       if key not in keys}, self.source)

    def flag_keys(self, flags: list[str]) -> frozenset[str]:
        """The keys that the scheme's command-line options among ``flags`` set."""
        by_flag = {option.flag: key for key, option in scheme_options(self.scheme).items()}
        return frozenset(by_flag[name] for token in flags
                         if (name := token.split("=", 1)[0]) in by_flag)

    def command(self, flags: Sequence[str] = ()) -> str:
        """The equivalent command line (with the scheme's ``flags`` after the configuration's
        options), quoted for a POSIX shell."""
        return shlex.join(["python", "-m", f"ocpar.{self.scheme}", *self.argv(), *flags])

    def with_overrides(self, overrides: Mapping[str, Any], where: str = "--set") -> RunConfig:
        """This configuration with some keys set again (``ocpar run --set KEY=VALUE``); a key
        not in the file goes at the end. The scheme itself cannot be changed."""
        options = dict(self.options)
        for key, value in overrides.items():
            if key == "scheme":
                raise ConfigError(f"{where}: scheme: the scheme is the file's ({self.scheme})")
            options[key] = check_value(self.scheme, key, value, where)
        return RunConfig(self.scheme, options, self.source)


@cache
def scheme_parser(scheme: str) -> argparse.ArgumentParser:
    """The scheme's own command-line parser (generated from :func:`scheme_class`)."""
    from ocpar.driver import build_parser

    return build_parser(scheme_class(scheme))


@cache
def scheme_options(scheme: str) -> dict[str, Option]:
    """Every option of the scheme by configuration key."""
    return {key: Option(key, spec.flag, spec.kind, spec.dotted)
            for key, spec in option_specs(scheme_class(scheme)).items()}


def _describe(value: Any) -> str:
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()})"
    if isinstance(value, int):
        return f"an integer ({value})"
    if isinstance(value, float):
        return f"a float ({value!r})"
    if isinstance(value, str):
        return f"a string ({value!r})"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "a table"
    return "a date/time"


EXPECTED = {
    "flag": "true or false",
    "integer": "an integer",
    "number": "a number",
    "string": "a string",
    "table": "a table of scalars",
    "list": "an array of numbers",
}
ACCEPTS = {
    "flag": (bool,),
    "integer": (int,),
    "number": (int, float),
    "string": (str,),
    "table": (dict,),
    "list": (list,),
}


def _suggestion(word: str, choices) -> str:
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def check_value(scheme: str, key: str, value: Any, where: str) -> Any:
    """``value`` if ``key`` is an option of ``scheme`` and the value has its type; otherwise
    raise :class:`ConfigError` ``WHERE: KEY: problem``."""
    options = scheme_options(scheme)
    if key not in options:
        raise ConfigError(f"{where}: {key}: unknown key for scheme {scheme}"
                          f"{_suggestion(key, options)}")
    kind = options[key].kind
    ok = isinstance(value, ACCEPTS[kind]) and (kind == "flag" or not isinstance(value, bool))
    if not ok:
        raise ConfigError(f"{where}: {key}: expected {EXPECTED[kind]}, got {_describe(value)}")
    if kind == "list" and not (value and all(
            isinstance(x, int | float) and not isinstance(x, bool) for x in value)):
        raise ConfigError(f"{where}: {key}: expected {EXPECTED[kind]}, got an array of "
                          f"{len(value)} item(s) not all numbers")
    if kind == "table" and options[key].dotted:
        value = dotted_table(value, key, where)
    if kind == "table":
        for name, item in value.items():
            if not is_key(name, options[key].dotted):
                raise ConfigError(f"{where}: {key}: {name!r} is not a Python name (a keyword "
                                  "argument of the factory)" if not options[key].dotted else
                                  f"{where}: {key}: {name!r} is not names joined by dots")
            if not isinstance(item, bool | int | float | str):
                raise ConfigError(f"{where}: {key}.{name}: expected a scalar, got "
                                  f"{_describe(item)}")
    return value


def dotted_table(value: Mapping[str, Any], key: str, where: str) -> dict[str, Any]:
    """A table of dotted keys with its sub-tables' entries as ``SUB.NAME`` keys (``[KEY.ipopt]
    tol = 1e-8`` → ``{"ipopt.tol": 1e-8}``), one level deep."""
    flat: dict[str, Any] = {}
    for name, item in value.items():
        entries = item.items() if isinstance(item, dict) else [(None, item)]
        for sub, entry in entries:
            full = name if sub is None else f"{name}.{sub}"
            if full in flat:
                raise ConfigError(f"{where}: {key}.{full}: given more than once")
            flat[full] = entry
    return flat


def from_mapping(data: Mapping[str, Any], source: str) -> RunConfig:
    """Check a parsed configuration (``scheme`` plus option keys) and return it."""
    if "scheme" not in data:
        raise ConfigError(f"{source}: scheme: missing (one of {', '.join(SCHEMES)})")
    scheme = data["scheme"]
    if not isinstance(scheme, str):
        raise ConfigError(f"{source}: scheme: expected a string, got {_describe(scheme)}")
    if scheme not in SCHEMES:
        raise ConfigError(f"{source}: scheme: unknown scheme {scheme!r}, expected one of "
                          f"{', '.join(SCHEMES)}{_suggestion(scheme, SCHEMES)}")
    options = {key: check_value(scheme, key, value, source)
               for key, value in data.items() if key != "scheme"}
    return RunConfig(scheme, options, source)


def examples() -> dict[str, str]:
    """The packaged example configurations: name → first line of the header comment."""
    found = {}
    for entry in sorted(resources.files(EXAMPLES_PACKAGE).iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            lines = entry.read_text(encoding="utf-8").splitlines()
            found[entry.name[:-5]] = lines[0].lstrip("#").strip() if lines else ""
    return found


def read_config_text(name: str | Path) -> bytes:
    """The bytes of the file ``name``, or of the packaged example of that name when no such
    file exists."""
    path = Path(name)
    if path.is_file():
        try:
            return path.read_bytes()
        except OSError as exc:
            raise ConfigError(f"{name}: cannot read: {exc.strerror or exc}") from None
    stem = str(name).removesuffix(".toml")
    if "/" not in stem and stem in examples():
        return resources.files(EXAMPLES_PACKAGE).joinpath(f"{stem}.toml").read_bytes()
    if path.exists():
        raise ConfigError(f"{name}: not a file")
    raise ConfigError(f"{name}: no such file, nor an example configuration (ocpar run --list)"
                      f"{_suggestion(stem, examples())}")


def read_config_data(name: str | Path) -> dict[str, Any]:
    """The TOML table of the configuration file ``name`` (or the packaged example of that
    name), not yet checked. Raises :class:`ConfigError`."""
    raw = read_config_text(name)
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{name}: not UTF-8 text (byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{name}: invalid TOML: {exc}") from None


def load_config(name: str | Path, overrides: Mapping[str, Any] | None = None) -> RunConfig:
    """Read and check the configuration file ``name`` (or the packaged example of that name),
    then apply ``overrides`` (keys as in the file). Raises :class:`ConfigError`."""
    config = from_mapping(read_config_data(name), str(name))
    return config.with_overrides(overrides) if overrides else config


def parse_override(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` → (key, value): VALUE read as a TOML value (``2``, ``1e-5``, ``true``,
    ``"dask"``, ``{ agents = 4 }``), or taken as a string when it is not one (``dask``,
    ``runs/x``)."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"--set: {text}: expected KEY=VALUE")
    return key, parse_value(value)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``--set`` items as a mapping; a key given twice is refused."""
    overrides: dict[str, Any] = {}
    for item in items:
        key, value = parse_override(item)
        if key in overrides:
            raise ConfigError(f"--set: {key}: given more than once")
        overrides[key] = value
    return overrides
