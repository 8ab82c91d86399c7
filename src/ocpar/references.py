"""Problems by reference: ``package.module:factory`` names a function that builds a problem.

A configuration's ``problem = "mypkg.problems:make"`` (with an optional ``[problem_args]``
table) or a command line's ``--problem mypkg.problems:make --problem-arg agents=4`` imports
``mypkg.problems`` and calls ``make(agents=4)``; the result must be an instance of the
scheme's problem type. The module must be importable in the coordinator and in every worker
(docs/user-problems.md).
"""

from __future__ import annotations

import importlib
import re
import typing
from collections.abc import Mapping
from typing import Any

#: ``package.module:attribute`` (dotted names of Python identifiers on both sides).
REFERENCE = re.compile(r"(?:[^\W\d]\w*)(?:\.[^\W\d]\w*)*:(?:[^\W\d]\w*)(?:\.[^\W\d]\w*)*\Z")


class ProblemReferenceError(ValueError):
    """A reference that does not give a problem; the message is one line naming the reference
    and the cause."""


def is_reference(text: str) -> bool:
    """Whether ``text`` is meant as a reference (it has a colon) rather than a built-in name."""
    return ":" in text


def _type_names(expected: Any) -> str:
    """``A`` or ``A or B`` for a type, a tuple of types or a union."""
    types = expected if isinstance(expected, tuple) else typing.get_args(expected) or (expected,)
    return " or ".join(t.__name__ for t in types)


def load_problem(reference: str, kwargs: Mapping[str, Any], expected: Any) -> Any:
    """Import ``module`` of ``reference`` = ``module:factory``, call ``factory(**kwargs)`` and
    check the result is an ``expected`` instance (a type, a tuple of types or a union).
    Raises :class:`ProblemReferenceError`."""
    where = f"problem {reference!r}"
    if not REFERENCE.match(reference):
        raise ProblemReferenceError(f"{where}: expected package.module:factory (Python names "
                                    "separated by dots, one colon)")
    module_name, _, attribute = reference.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or module_name
        raise ProblemReferenceError(
            f"{where}: no module named {missing!r} (is it installed, or on PYTHONPATH in the "
            "coordinator and every worker?)") from None
    except Exception as exc:  # the user's module failed while importing
        raise ProblemReferenceError(
            f"{where}: importing {module_name} raised {type(exc).__name__}: {exc}") from None
    factory: Any = module
    for part in attribute.split("."):
        if not hasattr(factory, part):
            raise ProblemReferenceError(f"{where}: module {module_name} has no attribute "
                                        f"{attribute!r}")
        factory = getattr(factory, part)
    if not callable(factory):
        raise ProblemReferenceError(f"{where}: {attribute} is an object of type "
                                    f"{type(factory).__name__}, not a function")
    try:
        problem = factory(**kwargs)
    except Exception as exc:
        raise ProblemReferenceError(
            f"{where}: {attribute}({_arguments(kwargs)}) raised {type(exc).__name__}: "
            f"{exc}") from None
    if not isinstance(problem, expected):
        raise ProblemReferenceError(
            f"{where}: {attribute}() returned an object of type {type(problem).__name__}, not "
            f"{_type_names(expected)}")
    return problem


def _arguments(kwargs: Mapping[str, Any]) -> str:
    return ", ".join(f"{key}={value!r}" for key, value in kwargs.items())
