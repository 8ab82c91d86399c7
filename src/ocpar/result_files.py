"""A run's result as files, and :func:`load` to read them back.

Every run with an output directory writes three files there (:func:`write_result`):

* ``result.json``: the summary (:meth:`~ocpar.results.RunResult.to_dict`: the common fields,
  ``title``, the scheme's scalar and small fields), naming the other two as ``"arrays"`` and
  ``"trace_file"``;
* ``result.nc``: the arrays (:meth:`~ocpar.results.RunResult.arrays`, read back as the
  :meth:`~ocpar.results.RunResult.dataset`: trajectories, per-agent data, with named
  dimensions and each variable's ``units`` and ``long_name``), netCDF4, uncompressed: of the
  formats measured at 100,000 agents (``scripts/result_formats.py``, docs/results.md) the
  fastest to write (0.03 s through xarray's ``netcdf4`` engine; load 0.06 s), one file for
  an HTTP download (zlib level 1 halves its size for 30x the write time; zarr takes ~0.4 s
  and is a directory or a zip). It is written with netCDF4-python directly, as
  xarray would write it: the coordinator does not import xarray (0.5–1 s) to write it;
* ``trace.json``: the per-superstep trace, one record per superstep
  (:meth:`~ocpar.bsp.SuperstepTrace.to_dict`), the per-task values as runs of equal values
  (``{"values": [...], "repeats": [...]}``; :func:`load_trace` gives them back as lists).

``ocpar.load("runs/mine")`` returns the :class:`Run`: ``dataset, summary = ocpar.load(...)``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np

if TYPE_CHECKING:
    import xarray as xr

    from ocpar.bsp import SuperstepTrace

#: One variable of a result's Dataset: (dimension names, values, attributes: ``units``,
#: ``long_name``), as :class:`xarray.Dataset` takes it (:func:`array`).
Array = tuple[tuple[str, ...], np.ndarray, dict[str, Any]]

SUMMARY_FILE = "result.json"
ARRAYS_FILE = "result.nc"
TRACE_FILE = "trace.json"
#: The array file's attribute naming its parts (space-separated file names beside it), where
#: the workers wrote their agents' variables themselves.
PARTS_ATTRIBUTE = "agent_parts"
#: xarray's engine for the array file (netCDF4-python)
ENGINE = "netcdf4"
#: The fields of result.json that say where, how and how long a run ran, not what it
#: computed: two runs of one problem on different backends or worker counts differ only there.
RUNTIME_FIELDS = frozenset({"backend", "workers", "wall_time_s", "trace",
                            "peak_rss_mb_per_worker", "timings", "array_parts"})


class WrittenResult(Protocol):
    """What the writer reads of a result (:class:`ocpar.results.RunResult`)."""

    trace: list[SuperstepTrace]
    timings: dict[str, float]

    def arrays(self) -> dict[str, Array]: ...

    def file_attributes(self) -> dict[str, str]: ...

    def to_dict(self) -> dict: ...

    def all_timings(self) -> dict[str, float]: ...


def write_result(result: WrittenResult, directory: str | Path) -> list[Path]:
    """Write ``result`` into ``directory`` (made if missing) as ``result.json``,
    ``result.nc`` and ``trace.json``; returns their paths (summary first, then the array file
    and its parts). The summary is written last: once it is there, so are the others. The
    time the other two took is added to the result's ``timings["files_s"]``
    (:mod:`ocpar.timing`). A result whose agents' arrays its workers wrote as parts of the
    array file (a formation's ``parts``, :mod:`ocpar.formation.finish`) is written into the
    directory that holds them: result.nc names them (attribute :data:`PARTS_ATTRIBUTE`), and
    so does result.json (``array_parts``)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    arrays, trace = directory / ARRAYS_FILE, directory / TRACE_FILE
    parts = getattr(result, "parts", [])
    if missing := [p for p in parts if not (directory / p).is_file()]:
        raise ValueError(f"the run's workers wrote its agents' arrays as {', '.join(missing)} "
                         f"into the run's output directory, not {directory}: write the "
                         "result there")
    write_netcdf(result.arrays(), result.file_attributes()
                 | ({PARTS_ATTRIBUTE: " ".join(parts)} if parts else {}), arrays)
    trace.write_text("[" + ", ".join(_trace_record(t.to_dict(lists=False))
                                     for t in result.trace) + "]")
    result.timings["files_s"] = result.timings.get("files_s", 0.0) + time.perf_counter() - start
    return [write_summary(result, directory), arrays, *(directory / p for p in parts), trace]


def write_summary(result: WrittenResult, directory: str | Path) -> Path:
    """Write ``result.json`` (:meth:`~ocpar.results.RunResult.to_dict`, naming the array file
    and the trace, ``timings`` last) into ``directory``, atomically (:func:`_replace`).
    :func:`write_timings` rewrites its timings alone after the plots."""
    parts = getattr(result, "parts", [])
    fields = result.to_dict() | {"arrays": ARRAYS_FILE, "trace_file": TRACE_FILE} | (
        {"array_parts": parts} if parts else {})
    fields["timings"] = fields.pop("timings")
    return _replace(Path(directory) / SUMMARY_FILE, json.dumps(fields).encode())


#: How :func:`write_summary` writes the key of the last field, ``timings`` (a flat dict of
#: numbers: the last occurrence of this text in result.json is that key).
_TIMINGS_KEY = b', "timings": '


def write_timings(result: WrittenResult, directory: str | Path) -> Path:
    """Rewrite the ``timings`` of the ``result.json`` that :func:`write_summary` wrote into
    ``directory`` with the result's :meth:`~ocpar.results.RunResult.all_timings` (e.g. with
    the plots' time), the rest of the file kept as written, not encoded again: a formation's
    ``phi`` takes ~20 MB and ~2 s to encode at 1,000,000 agents. The first write stays the
    run's summary should the plots fail."""
    summary = Path(directory) / SUMMARY_FILE
    text = summary.read_bytes()
    head = text[:text.rindex(_TIMINGS_KEY) + len(_TIMINGS_KEY)]
    return _replace(summary, head + json.dumps(result.all_timings()).encode() + b"}")


def _replace(path: Path, content: bytes) -> Path:
    """Write ``content`` to ``path`` atomically (a new file renamed over the old one: a reader
    never sees half of it); returns ``path``."""
    partial = path.with_name(f".{path.name}.{os.getpid()}")
    partial.write_bytes(content)
    os.replace(partial, path)
    return path


#: The per-task lists of a trace record (one number per task: 10^6 of each per superstep at
#: 1,000,000 agents), written as runs of equal values (:func:`_runs`).
TASK_LISTS = ("task_wall_s", "task_cpu_s", "task_worker")


def _trace_record(record: dict) -> str:
    """One trace record as JSON, its :data:`TASK_LISTS` last, each as its runs of equal
    values (:func:`_runs`)."""
    lists = {key: record.pop(key) for key in TASK_LISTS if key in record}
    text = json.dumps(record)
    extra = "".join(f", {json.dumps(key)}: {_runs(v)}" for key, v in lists.items())
    return text[:-1] + extra + "}" if lists else text


def _runs(values: np.ndarray | list[float]) -> str:
    """``values`` (one per task) as JSON ``{"values": [...], "repeats": [...]}``: each run of
    equal consecutive values once, with its length (a batched kernel gives every task of its
    chunk the chunk's mean time: a run per worker, where a list would hold 10^6 numbers).
    :func:`load_trace` gives the list back."""
    values = np.asarray(values)
    if not values.size:
        return '{"values": [], "repeats": []}'
    starts = np.flatnonzero(np.r_[True, values[1:] != values[:-1]])
    repeats = np.diff(np.r_[starts, values.size])
    return json.dumps({"values": values[starts].tolist(), "repeats": repeats.tolist()})


def _expanded(record: dict) -> dict:
    """A trace record as :func:`load_trace` gives it: its per-task runs as lists."""
    for key in TASK_LISTS:
        if isinstance(runs := record.get(key), dict):
            record[key] = np.repeat(runs["values"], runs["repeats"]).tolist()
    return record


def write_netcdf(variables: dict[str, Array], attrs: dict[str, str], path: Path) -> None:
    """Write ``variables`` (:func:`~ocpar.results.array`) and the file's ``attrs`` to ``path``
    as netCDF4, uncompressed, as :meth:`xarray.Dataset.to_netcdf` would (string arrays as
    variable-length strings, no fill values; the coordinates that are not dimensions,
    :func:`~ocpar.result_files.coordinates`, named in the global ``coordinates`` attribute)."""
    import netCDF4

    with netCDF4.Dataset(path, "w", format="NETCDF4") as f:
        names = coordinates(variables)
        f.setncatts(attrs | ({"coordinates": " ".join(names)} if names else {}))
        for name, (dims, values, var_attrs) in variables.items():
            for dim, size in zip(dims, values.shape, strict=True):
                if dim not in f.dimensions:
                    f.createDimension(dim, size)
                elif len(f.dimensions[dim]) != size:
                    raise ValueError(f"{name}: dimension {dim} has {size} entries, another "
                                     f"variable's {len(f.dimensions[dim])}")
            text = values.dtype.kind in "OU"
            var = f.createVariable(name, str if text else values.dtype, dims, fill_value=False)
            var.setncatts(without_coordinates(var_attrs))
            var[...] = values.astype(object) if text else values


def coordinates(variables: dict[str, Array]) -> list[str]:
    """The names of ``variables`` that are coordinates besides those named like their
    dimension: each ``<dim>_units`` of a dimension's entries (:func:`components`), each
    variable another names as its ``bounds``, its ``units_by_component``
    (:func:`derived_units`) or in its ``coordinates`` attribute (e.g. each member's own node
    times). The array file lists them in its global ``coordinates`` attribute, which xarray
    reads."""
    dims = {d for dims, _, _ in variables.values() for d in dims}
    named = {n for _, _, attrs in variables.values()
             for n in [attrs.get("bounds", ""), attrs.get("units_by_component", ""),
                       *attrs.get("coordinates", "").split()] if n}
    return [name for name in variables
            if name in named or (name.endswith("_units") and name[:-6] in dims)]


def without_coordinates(attrs: dict[str, Any]) -> dict[str, Any]:
    """A variable's ``attrs`` without its ``coordinates`` (the file's global one lists them,
    :func:`coordinates`; xarray drops it on reading)."""
    return {key: value for key, value in attrs.items() if key != "coordinates"}


def categories(values: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """Strings ``values`` (n) as codes (n,) int16 into their distinct values (in order of first
    appearance): one pass, O(n) (per-agent solver statuses: a few distinct strings)."""
    index: dict[str, int] = {}
    codes = np.fromiter((index.setdefault(v, len(index)) for v in values), np.int16,
                        count=len(values))
    return codes, list(index)


class Run(NamedTuple):
    """A written run, read back by :func:`load`: ``dataset`` its arrays (in memory, the file
    closed), ``summary`` its ``result.json`` (a dict; None for an array file read on its own,
    e.g. one downloaded without its summary)."""

    dataset: xr.Dataset
    summary: dict | None


def _summary_path(path: Path) -> Path:
    """``result.json`` of ``path``: a run directory, its result.json or its array file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such run directory or file")
    if path.is_dir():
        return path / SUMMARY_FILE
    if path.suffix == ".json":
        return path
    return path.parent / SUMMARY_FILE


def read_summary(path: str | Path) -> dict:
    """The ``result.json`` of ``path`` (a run directory, its result.json or array file)."""
    return _read(_summary_path(Path(path)))


def _read(summary_path: Path) -> dict:
    if not summary_path.is_file():
        raise FileNotFoundError(f"no {SUMMARY_FILE} at {summary_path}")
    return json.loads(summary_path.read_text())


def load(path: str | Path) -> Run:
    """The run at ``path`` (a run directory, its ``result.json`` or its array file): its
    Dataset, loaded into memory, and its summary, e.g.
    ``ds, summary = ocpar.load("runs/formation")``; ``ds.configuration`` (agent, node,
    q_component). An array file with no result.json beside it loads with summary None.
    FileNotFoundError if the directory holds no result.json or array file."""
    summary_path = _summary_path(Path(path))
    if Path(path).suffix not in ("", ".json") and not summary_path.is_file():
        return Run(_joined(Path(path)), None)
    summary = _read(summary_path)
    arrays = summary_path.parent / summary.get("arrays", ARRAYS_FILE)
    if not arrays.is_file():
        raise FileNotFoundError(f"no array file {arrays.name} beside {summary_path}")
    return Run(_joined(arrays), summary)


def _joined(path: Path) -> xr.Dataset:
    """The array file at ``path`` loaded, with the agents' variables of its parts beside it
    (its :data:`PARTS_ATTRIBUTE`) joined along ``agent`` in order: the Dataset one file would
    hold. A variable whose ``categories`` attribute names another that a part holds (codes
    into the part's own names, e.g. solver statuses) gets codes into all parts' names in
    order of first appearance."""
    import xarray as xr

    whole = xr.load_dataset(path, engine=ENGINE)
    names = whole.attrs.pop(PARTS_ATTRIBUTE, None)
    if not names:
        return whole
    missing = [n for n in names.split() if not (path.parent / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{path.name} names its agents' parts {', '.join(missing)}, "
                                f"not beside it in {path.parent}")
    parts = [xr.load_dataset(path.parent / name, engine=ENGINE) for name in names.split()]
    first = parts[0]
    tables = {name: v.attrs["categories"] for name, v in first.data_vars.items()
              if v.attrs.get("categories") in first.variables}
    joined = xr.concat([p.drop_vars(list(tables.values())) for p in parts], dim="agent",
                       data_vars="minimal", coords="minimal", compat="override")
    for name, table in tables.items():   # codes into each part's own table: one table
        labels = np.concatenate([p[table].values[p[name].values] for p in parts])
        codes, distinct = categories(labels.tolist())
        joined[name] = (first[name].dims, codes.astype(first[name].dtype), first[name].attrs)
        joined[table] = (first[table].dims,   # as one file's loads: text of its longest
                         np.array(distinct, dtype=None if first[table].dtype.kind == "U"
                                  else object), first[table].attrs)
    return xr.merge([whole, joined], combine_attrs="override")


def by_dimensions(dataset: xr.Dataset) -> dict[tuple[str, ...], xr.Dataset]:
    """``dataset``'s data variables grouped by their dimensions, each group a Dataset of its
    own (with the coordinates on those dimensions), e.g. ``("agent",)``: the per-agent
    variables, ``("agent", "time", "q_component")``: the node paths. Each group's
    :meth:`~xarray.Dataset.to_dataframe` has one row per point of its own dimensions
    (``ds.to_dataframe()`` of the whole Dataset takes the product of every dimension)."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for name, variable in dataset.data_vars.items():
        groups.setdefault(tuple(variable.dims), []).append(name)
    return {dims: dataset[names] for dims, names in groups.items()}


def load_trace(path: str | Path) -> list[dict]:
    """The per-superstep trace of the run at ``path`` (as :func:`load` takes it): one record
    per superstep (:meth:`~ocpar.bsp.SuperstepTrace.to_dict`), its per-task values as lists
    (the file holds their runs)."""
    summary_path = _summary_path(Path(path))
    name = _read(summary_path).get("trace_file", TRACE_FILE)
    return [_expanded(record)
            for record in json.loads((summary_path.parent / name).read_text())]
