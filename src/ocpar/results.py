"""What every scheme's result shares: the common fields of ``result.json``, one status
vocabulary, and the exit status of each status.

Statuses (the same words in every scheme):

* ``converged``: the run ended by its scheme's own stopping rule with an answer (formation:
  the outer optimality test; pursuit: an agent improved on its leader by less than ε, or the
  full-horizon NLP solved; MACS: the evaluation budget spent with a non-empty archive);
* ``not_converged``: it stopped at a bound (outer iterations, agents) without meeting it;
* ``failed``: it has no usable answer (an inner solve failed for good, no feasible point,
  a formation answer that fails its verification, :mod:`ocpar.formation.verify`);
* ``separation_not_met``: a formation run with a required minimum separation whose rounds
  ended (round limit) with two agents closer than required; its paths are returned, with
  by how much they miss;
* ``obstacles_not_cleared``: a formation run with obstacles whose returned paths, checked
  against them by exact segment distances, enter one (an inner solve accepted short of its
  tolerance); its paths are returned, with where and by how much;
* ``cancelled``: stopped by its stop file at a superstep boundary (``ocpar cancel``); such a
  run writes no result.json, its checkpoint resumes it.

Unless the status is ``converged``, a result reports none of its scheme's headline figures:
not in Python (:meth:`RunResult.headline_attributes` are NaN or None, the values the last
iterate had kept apart in :attr:`RunResult.last_iterate`), not in ``result.json``
(:attr:`RunResult.headline_fields`: null), not in the summary ("not reached", no sentinel
numbers), and its plots' titles say its status and why (:meth:`RunResult.title`).

A result is written as three files (:mod:`ocpar.result_files`): ``result.json`` the summary
(:meth:`RunResult.to_dict`), ``result.nc`` its arrays (:meth:`RunResult.dataset`: trajectories
and per-agent data, named dimensions, units) and ``trace.json`` the per-superstep trace.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ocpar.bsp import SuperstepTrace
from ocpar.result_files import Array, coordinates, without_coordinates, write_result
from ocpar.timing import PHASES

if TYPE_CHECKING:
    import xarray as xr

    from ocpar.models.labels import Labels  # (not imported at run time: it imports CasADi)

#: The conventions the array file follows (its ``Conventions`` attribute).
CONVENTIONS = "CF-1.10"


def array(dims: str, values: Any, units: str | Labels, long_name: str, *,
          entry_units: str | None = None, **attrs: Any) -> Array:
    """A Dataset variable: ``dims`` space-separated dimension names ('' for a scalar),
    ``values`` an array of that many axes, its ``units`` (a string a unit library parses,
    '1' for a nondimensional number or an index; or the :class:`~ocpar.models.labels.Labels`
    of its last dimension's entries: their common unit, or, where they differ, no ``units``
    and ``units_by_component`` naming the coordinate that holds them: ``entry_units``, a
    derived quantity's own (:func:`derived_units`, e.g. ``velocity_units``), by default
    ``<last dimension>_units``, the entries' own (:func:`components`)) and ``long_name``;
    ``attrs`` more attributes (netCDF values: strings, numbers, lists of them)."""
    names = tuple(dims.split())
    if not isinstance(units, str):
        unit = units.unit
        unit_attrs = ({"units": unit} if unit is not None
                      else {"units_by_component": entry_units or f"{names[-1]}_units"})
    else:
        unit_attrs = {"units": units}
    return (names, np.asarray(values), {**unit_attrs, "long_name": long_name, **attrs})


def text(values: Iterable[str]) -> np.ndarray:
    """Strings as an array the array file writes as variable-length strings."""
    return np.array(list(values), dtype=object)


def components(dim: str, labels: Labels, long_name: str) -> dict[str, Array]:
    """The coordinate ``dim`` naming a vector's entries (``labels.names``) and ``<dim>_units``
    their units (``labels.units``, strings a unit library parses)."""
    return {dim: array(dim, text(labels.names), "1", long_name),
            f"{dim}_units": array(dim, text(labels.units), "1", f"units of each {long_name}")}


def derived_units(name: str, dim: str, labels: Labels) -> dict[str, Array]:
    """The coordinate ``<name>_units`` along ``dim``: the units of each entry of the variable
    ``name``, a quantity derived from ``dim``'s entries in units of its own (``labels``,
    e.g. :meth:`Labels.per <ocpar.models.labels.Labels.per>`: a velocity's m/s, m/s, rad/s
    beside the configuration's m, m, rad), which that variable's ``units_by_component``
    names (:func:`array`'s ``entry_units``); none where its entries share one unit (then
    its ``units`` says it)."""
    if labels.unit is not None:
        return {}
    return {f"{name}_units": array(dim, text(labels.units), "1", f"units of each {name} entry")}


def time_axes(times: np.ndarray, unit: str) -> dict[str, Array]:
    """The time coordinates of a path sampled at ``times`` (n,) in ``unit``: ``time``
    (dimension ``time``, n) the samples and ``interval_time`` (dimension ``interval_time``,
    n−1) the start t_k of each interval [t_k, t_k+1] (a control held on it is the one in
    force from t_k: ``sel(interval_time=t, method="ffill")`` gives the interval holding t)."""
    times = np.asarray(times, float)
    return {
        # (CF's standard name ``time`` needs a unit of time: not given to a nondimensional one)
        "time": array("time", times, unit, "time", axis="T",
                      **({} if unit == "1" else {"standard_name": "time"})),
        "interval_time": array("interval_time", times[:-1], unit,
                               "start time t_k of each interval [t_k, t_k+1]"),
    }


def _reached(value: Any) -> bool:
    """Whether ``value`` is a figure (not None, not NaN)."""
    return value is not None and not (isinstance(value, float | np.floating)
                                      and math.isnan(value))


#: Exit status of a run by its status (2 is bad usage, before anything runs).
EXIT_STATUS = {"converged": 0, "not_converged": 1, "failed": 3, "cancelled": 4,
               "separation_not_met": 5, "obstacles_not_cleared": 6}
STATUSES = tuple(EXIT_STATUS)


@dataclass(kw_only=True)
class RunResult:
    """The fields every scheme's result has. ``inner_solves``: inner problems solved (MACS:
    objective evaluations, each a DFET solve); ``failed_solves`` those that failed for good;
    ``retries`` extra attempts made; ``wall_time_s`` the run's wall time (s); ``trace`` one
    record per superstep; ``timings`` where the run's time went, by phase (s,
    :mod:`ocpar.timing`: a scheme gives ``verification_s``, the driver the others);
    ``last_iterate`` the headline figures of a run that is not ``converged``, by attribute
    name, as its last iterate had them (e.g. ``last_iterate["total_cost"]``): for tools that
    study a failure, never a headline (the attributes themselves are NaN or None,
    :meth:`headline_attributes`; empty for a converged run); ``solver_options`` the inner
    solvers' options, the run's and those used (:func:`ocpar.ocp.solver_options.used`; empty
    where a scheme does not say). A scheme's result adds its own fields (:meth:`scheme_fields`,
    the summary's) and arrays (:meth:`arrays`, the array file's)."""

    scheme: ClassVar[str]
    #: The scheme's headline figures, keys of ``result.json``: written as null unless the
    #: status is ``converged`` (a run reports no figure it did not reach).
    headline_fields: ClassVar[tuple[str, ...]] = ()
    #: The status words this scheme's runs can end with (a subset of :data:`STATUSES`), each
    #: defined in docs/faults.md's table for the scheme.
    statuses: ClassVar[tuple[str, ...]] = ("converged", "not_converged", "failed", "cancelled")

    problem: str
    backend: str
    workers: int
    status: str
    wall_time_s: float
    inner_solves: int = 0
    failed_solves: int = 0
    retries: int = 0
    message: str = ""
    trace: list[SuperstepTrace] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    last_iterate: dict[str, Any] = field(default_factory=dict)
    solver_options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.status not in self.statuses:
            raise ValueError(f"a {self.scheme} run's status {self.status!r} is not one of "
                             f"{', '.join(self.statuses)}")
        if self.status != "converged":   # (a scheme may give ``converged`` its own meaning)
            self._withhold_headlines()

    def headline_attributes(self) -> tuple[str, ...]:
        """The attributes holding the headline figures (:attr:`headline_fields` unless a
        scheme names others): NaN (None where the attribute may be None; a dict of figures:
        each NaN) unless the status is ``converged``."""
        return self.headline_fields

    def _withhold_headlines(self) -> None:
        """Move each headline figure the run did not reach into :attr:`last_iterate` and
        leave NaN or None in its place (a figure already withheld stays as it was kept)."""
        types = {f.name: str(f.type) for f in fields(self)}
        for name in self.headline_attributes():
            value = getattr(self, name)
            if isinstance(value, dict):
                if any(_reached(v) for v in value.values()):
                    self.last_iterate[name] = dict(value)
                setattr(self, name, dict.fromkeys(value, math.nan))
                continue
            if _reached(value):
                self.last_iterate[name] = value
            setattr(self, name, None if "None" in types[name] else math.nan)

    @property
    def supersteps(self) -> int:
        return len(self.trace)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    @property
    def exit_status(self) -> int:
        """The command line's exit status for this result (:data:`EXIT_STATUS`)."""
        return EXIT_STATUS[self.status]

    def headline_keys(self) -> tuple[str, ...]:
        """The keys of :attr:`headline_fields` (a scheme may add keys only known per run)."""
        return self.headline_fields

    def why(self) -> str:
        """Why the run ended as it did: the first clause of its message ('' without one)."""
        return self.message.splitlines()[0].split("; ")[0] if self.message else ""

    def not_reached(self) -> str:
        """What a summary line says instead of a headline figure the run did not reach:
        'not reached (<status>: <why>)'."""
        return f"not reached ({self.status}: {self.why()})"

    def headline_title(self) -> str:  # pragma: no cover - provided by each scheme
        """The scheme's headline figures as a plot title (of a converged run)."""
        raise NotImplementedError

    def title(self) -> str:
        """Every plot's headline: :meth:`headline_title` if the status is ``converged``, else
        '<status>: <why>' (no figure the run did not reach)."""
        if self.status == "converged":   # (a scheme may give ``converged`` its own meaning)
            return self.headline_title()
        return f"{self.status.replace('_', ' ')}: {self.why()}"

    def scheme_fields(self) -> dict:  # pragma: no cover - provided by each scheme
        """The scheme's own fields of ``result.json`` (JSON values)."""
        raise NotImplementedError

    def arrays(self) -> dict[str, Array]:  # pragma: no cover - provided by each scheme
        """The scheme's arrays (trajectories, per-agent data) by name (:func:`array`); a
        variable named like a dimension is its coordinate."""
        raise NotImplementedError

    def file_attributes(self) -> dict[str, str]:
        """The array file's attributes: ``Conventions`` (:data:`CONVENTIONS`), ``scheme``,
        ``problem``, ``status``, ``title`` (:meth:`title`) and ``message``."""
        return {"Conventions": CONVENTIONS, "scheme": self.scheme, "problem": self.problem,
                "status": self.status, "title": self.title(), "message": self.message}

    def dataset(self) -> xr.Dataset:
        """:meth:`arrays` as an :class:`xarray.Dataset` with :meth:`file_attributes` (what
        :func:`ocpar.load` reads back from the array file)."""
        import xarray as xr  # (not imported by a run: the array file is written without it)

        variables = self.arrays()
        return xr.Dataset({name: (dims, values, without_coordinates(attrs))
                           for name, (dims, values, attrs) in variables.items()},
                          attrs=self.file_attributes()).set_coords(coordinates(variables))

    def write(self, directory: str | Path) -> list[Path]:
        """Write this result into ``directory`` as ``result.json``, ``result.nc`` and
        ``trace.json`` (:func:`ocpar.result_files.write_result`); returns their paths."""
        return write_result(self, directory)

    def to_dict(self) -> dict:
        """The ``result.json`` summary: the common fields, ``title`` (:meth:`title`), then
        the scheme's own (its :meth:`headline_keys` null unless the status is ``converged``).
        The trace and the arrays are files of their own (:mod:`ocpar.result_files`)."""
        fields = self.scheme_fields()
        if self.status != "converged":   # (a scheme may give ``converged`` its own meaning)
            fields |= {key: None for key in self.headline_keys() if key in fields}
        return {
            "scheme": self.scheme, "problem": self.problem, "backend": self.backend,
            "workers": self.workers, "status": self.status, "message": self.message,
            "title": self.title(),
            "supersteps": self.supersteps, "inner_solves": self.inner_solves,
            "failed_solves": self.failed_solves, "retries": self.retries,
            "wall_time_s": self.wall_time_s, **fields,
            "solver_options": self.solver_options, "timings": self.all_timings(),
        }

    def all_timings(self) -> dict[str, float]:
        """:attr:`timings` with ``solve_s`` (the :attr:`wall_time_s`), in the order of
        :data:`ocpar.timing.PHASES` (those not measured left out), ``total_s`` last."""
        known = self.timings | {"solve_s": self.wall_time_s}
        ordered = {key: known[key] for key in PHASES if key in known}
        return ordered | {key: value for key, value in known.items() if key not in ordered
                          and key != "total_s"} | (
            {"total_s": known["total_s"]} if "total_s" in known else {})
