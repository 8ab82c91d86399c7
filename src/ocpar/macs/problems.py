"""The named examples of the MACS scheme (``--problem NAME`` on the command line): each name
refers to the factory of a module of :mod:`ocpar.examples`, written with the public API.

- ``goddard``: the MACS paper's Goddard-like ascent, min (t_f, −v_x(t_f));
- ``orbit-raising``: the paper's maximum-energy orbit raising, min (t_f, −E(t_f));
- ``double-integrator``: minimum time against minimum control energy (closed-form front);
- ``zermelo``, ``zermelo-polar``: a boat crossing a jet, min (t_f, ∫|u|² dt), with Cartesian
  controls and a speed limit, or polar controls (no reference front).
"""

from __future__ import annotations

from importlib import import_module

from ocpar.macs.problem import MacsProblem

#: name → "module:factory" of the named examples (imported on first use)
PROBLEMS = {
    "goddard": "ocpar.examples.macs_goddard:make",
    "orbit-raising": "ocpar.examples.macs_orbit_raising:make",
    "double-integrator": "ocpar.examples.macs_double_integrator:make",
    "zermelo": "ocpar.examples.macs_zermelo:make",
    "zermelo-polar": "ocpar.examples.macs_zermelo:make_polar",
}


def make_problem(name: str, elements: int | None = None) -> MacsProblem:
    """The named example ``name`` (one of :data:`PROBLEMS`) with ``elements`` DFET elements
    (None: the example's own)."""
    try:
        module, factory = PROBLEMS[name].split(":")
    except KeyError:
        raise ValueError(f"unknown problem {name!r}; choose one of {', '.join(PROBLEMS)}") from None
    make = getattr(import_module(module), factory)
    return make() if elements is None else make(elements=elements)
