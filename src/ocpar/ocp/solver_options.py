"""The inner solvers' own options, set per run: one mechanism for every transcription.

An option is named ``SOLVER.NAME`` and has a scalar value (bool, int, float or str):

* ``ipopt.NAME``: any of IPOPT's own options (``ipopt.tol``, ``ipopt.linear_solver``,
  ``ipopt.print_level``, ``ipopt.max_iter``, ``ipopt.mu_strategy``, …), over the defaults a
  transcription passes (:func:`ocpar.ocp.ipopt.ipopt_options`);
* ``sqpmethod.NAME``: CasADi's ``sqpmethod`` options of a scalar type
  (``casadi.nlpsol_options("sqpmethod")``: ``tol_pr``, ``tol_du``, ``max_iter``,
  ``hessian_approximation``, …; its QP solver stays ``qrqp``);
* ``qrqp.NAME``: the ``qrqp`` QP solver's (``casadi.conic_options("qrqp")``: ``max_iter``,
  ``constr_viol_tol``, ``dual_inf_tol``, …);
* ``newton.NAME``: the batched Newton kernel's (:data:`NEWTON_OPTIONS`): ``kkt_tol``, the
  KKT-residual tolerance a column must meet to be accepted, ``max_iter``, its Newton
  steps at most, and ``kkt_solver`` (ODE agents between two states): ``riccati``
  (:mod:`ocpar.ocp.riccati`, the default) or ``qr`` (:class:`~ocpar.ocp.batch.KktNewton`).

:func:`solver_options` turns what a user gives (a mapping of ``SOLVER.NAME`` to a value, or
nested ``{SOLVER: {NAME: value}}`` as a TOML table gives it) into the sorted tuple of (name,
value) pairs a shape stores (shapes are hashable: the solver-cache key), and checks it before
any worker starts, once per process and set of options: the names and types against CasADi's
own metadata (``nlpsol_option_type``, ``conic_option_type``; for IPOPT the type CasADi
converts each option to), then IPOPT's values by building and solving a one-variable NLP with
them (IPOPT's own range checks; a linear solver that this host cannot load fails there).
Anything wrong is a ValueError of one line naming the option. The transcriptions read the
options through :func:`ipopt`, :func:`sqpmethod` and :func:`newton`.
"""

from __future__ import annotations

import contextlib
import ctypes
import difflib
import io
import json
import math
import os
import re
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Mapping
from functools import cache
from typing import Any

import casadi as ca

from ocpar.ocp.ipopt import ipopt_options

Scalar = bool | int | float | str
#: A shape's solver options: (``SOLVER.NAME``, value) pairs sorted by name.
SolverOptions = tuple[tuple[str, Scalar], ...]

SOLVERS = ("ipopt", "sqpmethod", "qrqp", "newton")
#: The batched Newton kernel's options: name → (type, what it is).
NEWTON_OPTIONS = {
    "kkt_tol": (float, "the KKT-residual tolerance a column must meet to be accepted"),
    "max_iter": (int, "Newton steps at most"),
    "kkt_solver": (str, "how an ODE agent's Newton step solves its KKT system: riccati "
                        "(stage by stage, the default) or qr (sparse QR of the whole matrix)"),
}
#: The values of the batched Newton kernel's options of type str.
NEWTON_CHOICES = {"kkt_solver": ("riccati", "qr")}
#: ``sqpmethod`` options that are not the user's to set: its QP solver (the batches and
#: their failure handling are built on ``qrqp``).
FIXED_SQPMETHOD = frozenset({"qpsol"})
#: Options that name files or libraries on the host that solves (IPOPT writes or loads
#: them): the job service refuses them unless the operator allows them by name.
HOST_FILE_OPTIONS = frozenset({"ipopt.output_file", "ipopt.option_file_name",
                               "ipopt.file_append", "ipopt.file_print_level", "ipopt.hsllib",
                               "ipopt.pardisolib"})
#: IPOPT's linear solver that CasADi's build always has (others are tried when asked for).
BUILT_IN_LINEAR_SOLVER = "mumps"
#: The command line's help of ``--solver-option`` (each scheme adds where its options go).
SOLVER_OPTIONS_HELP = (
    "an inner solver's own option SOLVER.NAME=VALUE: ipopt.NAME (any IPOPT option: ipopt.tol, "
    "ipopt.linear_solver, ipopt.print_level, ipopt.max_iter, ...), sqpmethod.NAME and "
    "qrqp.NAME (CasADi's), newton.kkt_tol, newton.max_iter or newton.kkt_solver (the "
    "batched Newton kernel); "
    "checked before any worker starts; repeat for more (TOML: a [solver_options] table; "
    "docs/solver-options.md)")
#: CasADi's option types, as the scalar Python types they take.
CASADI_TYPES = {"OT_INT": int, "OT_DOUBLE": float, "OT_BOOL": bool, "OT_STRING": str}
TYPE_WORDS = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}
#: The C library (its ``fflush``: IPOPT prints through C's buffered stdout).
_C = ctypes.CDLL(None)


def solver_options(given: Mapping[str, Any] | SolverOptions | None) -> SolverOptions:
    """``given`` (``{"ipopt.tol": 1e-8}``, ``{"ipopt": {"tol": 1e-8}}`` or pairs) as the
    sorted pairs a shape stores, checked (module docstring); ValueError of one line naming
    the option otherwise."""
    pairs = _flattened(given)
    _check(pairs)
    return pairs


def merged(base: SolverOptions, given: Mapping[str, Any] | SolverOptions | None
           ) -> SolverOptions:
    """``base`` with ``given`` set over it (checked as :func:`solver_options`)."""
    return solver_options(dict(base) | dict(solver_options(given)))


def of(options: SolverOptions, solver: str) -> dict[str, Scalar]:
    """The options of ``solver`` among ``options``, by their own names."""
    prefix = solver + "."
    return {key[len(prefix):]: value for key, value in options if key.startswith(prefix)}


def ipopt(options: SolverOptions, tol: float, max_iter: int, **extra: Any) -> dict:
    """``nlpsol`` options of IPOPT: the transcription's
    (:func:`~ocpar.ocp.ipopt.ipopt_options` of ``tol``, ``max_iter`` and ``extra``) with the
    user's ``ipopt.*`` over them; with none, exactly the transcription's."""
    settings = ipopt_options(tol, max_iter, **extra)
    settings["ipopt"] |= of(options, "ipopt")
    return settings


def sqpmethod(options: SolverOptions, settings: dict) -> dict:
    """``nlpsol`` options of ``sqpmethod``: the transcription's ``settings`` with the user's
    ``sqpmethod.*`` over them and ``qrqp.*`` over its ``qpsol_options``."""
    qp = settings.get("qpsol_options", {}) | of(options, "qrqp")
    return settings | of(options, "sqpmethod") | ({"qpsol_options": qp} if qp else {})


def newton(options: SolverOptions, name: str, default: Any) -> Any:
    """The batched Newton kernel's option ``name`` (:data:`NEWTON_OPTIONS`), or ``default``."""
    return of(options, "newton").get(name, default)


def used(options: SolverOptions, settings: Mapping[str, Mapping[str, Any]]) -> dict:
    """What a result records of a run's solver options: ``given``, the user's (by
    ``SOLVER.NAME``), and ``used``, ``settings`` (by inner NLP, then by solver: the options
    it is built with, defaults and the user's) as JSON values."""
    return {"given": dict(options), "used": _json(settings)}


def _json(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _json(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def _flattened(given: Mapping[str, Any] | SolverOptions | None) -> SolverOptions:
    """``given`` as sorted (``SOLVER.NAME``, value) pairs; a name given twice, a name not
    of that form or a value that is no scalar is a ValueError."""
    if not given:
        return ()
    if isinstance(given, Mapping):
        items = list(given.items())
    else:
        try:
            items = [(key, value) for key, value in given]
        except (TypeError, ValueError):
            raise ValueError(f"solver options: expected a table of SOLVER.NAME = value, got "
                             f"{given!r}") from None
    flat: dict[str, Scalar] = {}
    for key, value in items:
        inner = value.items() if isinstance(value, Mapping) else [(None, value)]
        for name, item in inner:
            full = key if name is None else f"{key}.{name}"
            if not isinstance(full, str):
                raise ValueError(f"solver options: {full!r}: expected SOLVER.NAME")
            if full in flat:
                raise ValueError(f"solver option {full}: given more than once")
            flat[full] = item
    for key, value in flat.items():
        solver, dot, name = key.partition(".")
        if not dot or solver not in SOLVERS or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*",
                                                                 name):
            raise ValueError(f"solver option {key!r}: expected SOLVER.NAME with SOLVER one of "
                             f"{', '.join(SOLVERS)}")
        if not isinstance(value, Scalar) or (isinstance(value, float)
                                             and not math.isfinite(value)):
            raise ValueError(f"solver option {key}: expected a finite scalar, got {value!r}")
    return tuple(sorted(flat.items()))


@cache
def _check(options: SolverOptions) -> None:
    """Every option's name and type, then IPOPT's values (ValueError of one line)."""
    for key, value in options:
        solver, _, name = key.partition(".")
        if solver == "ipopt":
            _check_type(key, value, _ipopt_type(key))
        elif solver == "newton":
            if name not in NEWTON_OPTIONS:
                raise ValueError(f"unknown solver option {key}{_close(name, NEWTON_OPTIONS)}; "
                                 f"newton has {', '.join(NEWTON_OPTIONS)}")
            kind = NEWTON_OPTIONS[name][0]
            _check_type(key, value, kind)
            if kind is str and value not in NEWTON_CHOICES[name]:
                raise ValueError(f"solver option {key}: {value!r} is not a valid value "
                                 f"(expected one of {', '.join(NEWTON_CHOICES[name])})")
            if kind is not str and not value > 0:
                raise ValueError(f"solver option {key}: expected a positive value, got {value!r}")
        else:
            _check_type(key, value, _casadi_type(solver, name))
            if isinstance(value, str) and (choices := _casadi_choices(solver, name)) \
                    and value not in choices:
                raise ValueError(f"solver option {key}: {value!r} is not a valid value "
                                 f"(expected one of {', '.join(choices)})")
            if isinstance(value, int | float) and not isinstance(value, bool) and value < 0:
                raise ValueError(f"solver option {key}: expected a value >= 0, got {value!r}")
    if ipopt_given := of(options, "ipopt"):
        _check_ipopt(ipopt_given)
    if (sqp := of(options, "sqpmethod")) or of(options, "qrqp"):
        _check_sqpmethod(sqpmethod(options, {"qpsol": "qrqp", "print_time": False}
                                   | ({} if "print_iteration" in sqp else
                                      {"print_iteration": False, "print_header": False,
                                       "print_status": False})))


def _check_type(key: str, value: Scalar, kind: type) -> None:
    ok = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
    if kind is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not ok:
        raise ValueError(f"solver option {key}: expected {TYPE_WORDS[kind]}, got {value!r}")


def _close(name: str, names: Any) -> str:
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _casadi_type(solver: str, name: str) -> type:
    """The scalar type of CasADi's ``sqpmethod`` or ``qrqp`` option ``name``."""
    if solver == "sqpmethod":
        names, kind = ca.nlpsol_options("sqpmethod"), ca.nlpsol_option_type
    else:
        names, kind = ca.conic_options("qrqp"), ca.conic_option_type
    settable = [n for n in names if CASADI_TYPES.get(kind(solver, n))
                and n not in FIXED_SQPMETHOD]
    if name not in settable:
        raise ValueError(f"unknown solver option {solver}.{name}{_close(name, settable)}; "
                         f"{solver} has {', '.join(sorted(settable))}")
    return CASADI_TYPES[kind(solver, name)]


def _casadi_choices(solver: str, name: str) -> list[str]:
    """The values CasADi's documentation of a string option lists (``a|b``), if it does."""
    info = (ca.nlpsol_option_info if solver == "sqpmethod" else ca.conic_option_info)(
        solver, name)
    return info.split("|") if re.fullmatch(r"[\w-]+(\|[\w-]+)+", info) else []


def _tiny_nlp() -> dict:
    """min (x − 1)² s.t. x ≥ 0: what the IPOPT and sqpmethod checks solve."""
    x = ca.SX.sym("x")
    return {"x": x, "f": (x - 1) ** 2, "g": x}


@cache
def _ipopt_type(key: str) -> type:
    """The type of IPOPT's option (``ipopt.NAME``), as CasADi converts it: probed by giving
    it a list, which CasADi's conversion refuses with the type it wanted."""
    name = key.partition(".")[2]
    try:
        ca.nlpsol("probe", "ipopt", _tiny_nlp(), {"ipopt": {name: [0.5, 0.5]}})
    except RuntimeError as exc:
        text = str(exc)
        if "No such IPOPT option" in text:
            raise ValueError(f"unknown solver option {key} (not an IPOPT option)") from None
        for probe, kind in (("is_double()", float), ("is_int()", int), ("is_string()", str)):
            if probe in text:
                return kind
    raise ValueError(f"solver option {key}: IPOPT's type of it is unknown to this check")


def _check_ipopt(options: dict[str, Scalar]) -> None:
    """Build IPOPT with ``options`` (its own range checks) and solve the tiny NLP with them
    (a linear solver that cannot be loaded fails there); ValueError of one line."""
    with _captured_stdout() as said:
        try:
            ca.nlpsol("check", "ipopt", _tiny_nlp(), ipopt_options(1e-8, 100) | {
                "ipopt": ipopt_options(1e-8, 100)["ipopt"] | options})
            refused = None
        except RuntimeError as exc:
            refused = str(exc)
    if refused is not None:
        raise ValueError(_ipopt_refusal(options, said(), refused))
    loading = {k: v for k, v in options.items()
               if f"ipopt.{k}" in HOST_FILE_OPTIONS or k == "linear_solver"}
    if options.get("linear_solver", BUILT_IN_LINEAR_SOLVER) != BUILT_IN_LINEAR_SOLVER and \
            not _loads(tuple(sorted(loading.items()))):
        raise ValueError(f"solver option ipopt.linear_solver: {options['linear_solver']!r} "
                         f"cannot be loaded on this host (IPOPT refused it when solving; "
                         f"{BUILT_IN_LINEAR_SOLVER} is built in)")
    quiet = {k: v for k, v in options.items() if k not in loading}
    quiet |= {"print_level": 0, "sb": "yes"}
    solver = ca.nlpsol("check", "ipopt", _tiny_nlp(), ipopt_options(1e-8, 100) | {
        "ipopt": ipopt_options(1e-8, 100)["ipopt"] | quiet})
    with _captured_stdout():
        solver(x0=0.5, lbg=0, ubg=math.inf)
    if solver.stats()["return_status"] == "Invalid_Option":
        raise ValueError(f"solver options {', '.join(f'ipopt.{k}' for k in options)}: IPOPT "
                         "refused them when solving (Invalid_Option)")


#: Solves the tiny NLP with IPOPT's options (JSON, argv[1]); exit status 3 if it refused them.
LOAD_PROBE = """
import json, sys, casadi as ca
x = ca.SX.sym("x")
s = ca.nlpsol("probe", "ipopt", {"x": x, "f": (x - 1) ** 2}, {"print_time": False,
              "ipopt": {"print_level": 0, "sb": "yes", **json.loads(sys.argv[1])}})
s(x0=0)
sys.exit(3 if s.stats()["return_status"] == "Invalid_Option" else 0)
"""


@cache
def _loads(options: tuple[tuple[str, Scalar], ...]) -> bool:
    """Whether IPOPT solves with the linear solver and library ``options``, tried in a
    process of its own: after failing to load HSL's MA97, IPOPT 3.14 crashes the process
    at its next solve (seen here), and the process that checks may be a server's."""
    try:
        probe = subprocess.run([sys.executable, "-c", LOAD_PROBE, json.dumps(dict(options))],
                               capture_output=True, timeout=120)
    except subprocess.TimeoutExpired:
        return False
    return probe.returncode == 0


def _ipopt_refusal(options: dict[str, Scalar], said: str, error: str) -> str:
    """One line from IPOPT's refusal of ``options`` (what it printed, ``said``, and CasADi's
    ``error``)."""
    match = re.search(r'Setting: "(.*)" is not a valid setting for Option: (\w+)', said)
    if match is None:
        last = error.strip().splitlines()[-1]
        return f"solver options {', '.join(f'ipopt.{k}' for k in options)}: IPOPT refused " \
               f"them ({last.strip()})"
    name = match.group(2)
    value = options.get(name, match.group(1))
    rest = said[match.end():]
    valid = re.findall(r"^\t(\S+) \(", rest, flags=re.MULTILINE)
    bounds = re.search(r"^(\S+ <=? )\(.*\)( <=? \S+)\s*$", rest, flags=re.MULTILINE)
    if valid:
        expected = f"one of {', '.join(valid)}"
    elif bounds:
        expected = f"{bounds.group(1)}{name}{bounds.group(2)}"
    else:
        expected = "see IPOPT's documentation"
    return f"solver option ipopt.{name}: {value!r} is not a valid value (expected {expected})"


def _check_sqpmethod(settings: dict) -> None:
    """Build ``sqpmethod`` with ``settings`` and solve the tiny NLP; ValueError of one line
    with CasADi's reason where it refuses them."""
    try:
        with _captured_stdout():
            solver = ca.nlpsol("check", "sqpmethod", _tiny_nlp(), settings)
            solver(x0=0.5, lbg=0, ubg=math.inf)
    except RuntimeError as exc:
        last = str(exc).strip().splitlines()[-1].strip()
        raise ValueError(f"solver options sqpmethod/qrqp: CasADi refused them ({last})") from None


@contextlib.contextmanager
def _captured_stdout() -> Iterator[Any]:
    """What IPOPT prints in the block, kept from the process's stdout: CasADi's Python
    interface sends it to ``sys.stdout``, IPOPT's own journal may go to file descriptor 1
    through C's buffered stdout (flushed before and after); yields a function that reads
    what was printed."""
    sys.stdout.flush()
    _C.fflush(None)
    saved = os.dup(1)
    python = io.StringIO()
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 1)
        text: list[str] = []
        try:
            with contextlib.redirect_stdout(python):
                yield lambda: "".join(text)
        finally:
            _C.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
        sink.seek(0)
        text += [python.getvalue(), sink.read().decode("utf-8", "replace")]
