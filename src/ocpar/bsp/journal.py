"""Checkpoints of a run: a journal of its supersteps, replayed on resume.

Every scheme's coordinator is deterministic given its supersteps' results (its outer solver,
archive updates and random numbers are functions of them and of the run's options), so the
journal of the supersteps is the coordinator's state: on ``--resume`` the coordinator runs
again from the start and each superstep already in the journal returns its recorded results
(and timings) instead of solving, until the journal ends and the run goes on live. The
outer iterate, archive, agent train, random state and warm starts are thereby restored
exactly, and the final result is identical to an uninterrupted run's.

On disk, in the checkpoint directory:

* ``manifest.json``: ``format``, ``version``, the run's ``fingerprint`` (scheme, problem and
  options, ocpar's version) and the number of ``supersteps`` recorded;
* ``superstep-00000.npz`` …: per superstep the kernel, a digest of its tasks, its results and
  its trace: arrays as arrays, everything else as JSON; no pickles (loaded with
  ``allow_pickle=False``); objects are rebuilt only as dataclasses defined in ocpar's own
  modules (:func:`result_type`).

Each file is written to a temporary name and renamed, the manifest last, so a run killed at any
moment leaves the last complete superstep.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import io
import json
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.trace import SuperstepTrace

FORMAT = "ocpar-checkpoint"
VERSION = 1
MANIFEST = "manifest.json"

class CheckpointError(ValueError):
    """A checkpoint cannot be written, read or resumed (one-line message)."""


def result_type(name: str) -> type:
    """The class ``module:qualname`` named in a checkpoint: only a dataclass defined in an
    ``ocpar`` module (so a checkpoint cannot make a run build arbitrary objects)."""
    module, _, qualname = name.partition(":")
    if module.split(".")[0] != "ocpar" or not qualname.isidentifier():
        raise CheckpointError(f"the checkpoint names {name!r}, which is not an ocpar class")
    try:
        cls = getattr(importlib.import_module(module), qualname)
    except (ImportError, AttributeError):
        raise CheckpointError(f"the checkpoint holds {name}, which this run does not know") \
            from None
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise CheckpointError(f"the checkpoint names {name!r}, which is not a result class")
    return cls


def digest(value: Any) -> str:
    """A stable hash (hex) of tasks: dataclasses field by field, arrays by dtype, shape and
    bytes, numbers by repr; the same tasks give the same digest in any process."""
    h = hashlib.sha256()
    _feed(h, value)
    return h.hexdigest()


def _feed(h: Any, value: Any) -> None:
    if isinstance(value, Columns):
        h.update(f"columns:{value.cls.__qualname__}:{value.length}".encode())
        for name, (kind, data) in value.fields.items():
            h.update(f"{name}:{kind}".encode())
            _feed(h, data)
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"dc:{type(value).__qualname__}".encode())
        for f in dataclasses.fields(value):
            h.update(f.name.encode())
            _feed(h, getattr(value, f.name))
    elif isinstance(value, np.ndarray):
        h.update(f"nd:{value.dtype.str}:{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, list | tuple):
        h.update(f"seq:{len(value)}".encode())
        for item in value:
            _feed(h, item)
    elif isinstance(value, Mapping):
        h.update(f"map:{len(value)}".encode())
        for key in sorted(value, key=repr):
            _feed(h, key)
            _feed(h, value[key])
    else:
        h.update(f"{type(value).__qualname__}:{value!r}".encode())


class _Encoder:
    """Values to JSON with arrays set aside (referenced as {"array": k})."""

    def __init__(self) -> None:
        self.arrays: list[np.ndarray] = []

    def value(self, v: Any) -> Any:
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                raise CheckpointError("object arrays cannot be checkpointed")
            self.arrays.append(v)
            return {"array": len(self.arrays) - 1}
        if isinstance(v, np.generic):
            return self.value(v.item())
        if v is None or isinstance(v, bool | int | str):
            return v
        if isinstance(v, float):
            return {"float": v.hex()}  # exact, and NaN/inf survive
        if isinstance(v, list | tuple):
            if v and all(type(x) is float for x in v):  # e.g. per-task times: one array
                self.arrays.append(np.array(v, dtype=float))
                return {"floats": len(self.arrays) - 1}
            return {"list": [self.value(x) for x in v]}
        if isinstance(v, Mapping) and all(isinstance(k, str) for k in v):
            return {"dict": {k: self.value(x) for k, x in v.items()}}
        if dataclasses.is_dataclass(v):
            return {"object": _type_name(type(v)), "fields": self.value(vars(v))}
        raise CheckpointError(f"a {type(v).__name__} cannot be checkpointed")

    def results(self, results: Any) -> Any:
        packed = to_columns(results)
        if not isinstance(packed, Columns):
            return {"items": self.value(list(packed))}
        return {"columns": _type_name(packed.cls), "length": packed.length,
                "fields": {name: [kind, self.value(data)]
                           for name, (kind, data) in packed.fields.items()}}


def _type_name(cls: type) -> str:
    name = f"{cls.__module__}:{cls.__qualname__}"
    if result_type(name) is not cls:
        raise CheckpointError(f"{name} cannot be checkpointed")
    return name


def _decode(v: Any, arrays: list[np.ndarray]) -> Any:
    if not isinstance(v, dict):
        return v
    if "array" in v:
        return arrays[v["array"]]
    if "float" in v:
        return float.fromhex(v["float"])
    if "floats" in v:
        return arrays[v["floats"]].tolist()
    if "list" in v:
        return [_decode(x, arrays) for x in v["list"]]
    if "dict" in v:
        return {k: _decode(x, arrays) for k, x in v["dict"].items()}
    if "object" in v:
        obj = object.__new__(result_type(v["object"]))
        obj.__dict__.update(_decode(v["fields"], arrays))
        return obj
    raise CheckpointError(f"unknown entry in checkpoint: {sorted(v)}")


def _decode_results(entry: dict, arrays: list[np.ndarray]) -> Any:
    if "items" in entry:
        return _decode(entry["items"], arrays)
    fields = {name: (kind, _decode(data, arrays)) for name, (kind, data) in entry["fields"].items()}
    return Columns(cls=result_type(entry["columns"]), length=entry["length"], fields=fields)


@dataclass(frozen=True)
class Recorded:
    """One superstep read back: its results (a list, or :class:`Columns` if it was a columnar
    superstep) and its trace."""

    results: Any
    trace: SuperstepTrace


def _write_atomically(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class Journal:
    """The checkpoint in ``directory`` of the run with ``fingerprint`` (a JSON-able dict).

    ``resume=False`` starts a new checkpoint (refused if the directory holds one);
    ``resume=True`` opens an existing one (refused if it is missing, of another format or
    version, or of another run) and :meth:`replay` serves its supersteps.
    """

    def __init__(self, directory: str | Path, fingerprint: dict, resume: bool) -> None:
        self.directory = Path(directory)
        self.fingerprint = json.loads(json.dumps(fingerprint))
        manifest = self.directory / MANIFEST
        if resume:
            try:
                stored = json.loads(manifest.read_text())
            except FileNotFoundError:
                raise CheckpointError(f"{self.directory} holds no checkpoint") from None
            except (OSError, ValueError) as exc:
                raise CheckpointError(f"cannot read {manifest}: {exc}") from None
            if stored.get("format") != FORMAT or stored.get("version") != VERSION:
                raise CheckpointError(
                    f"{manifest} is not an ocpar checkpoint of format version {VERSION}")
            if stored.get("fingerprint") != self.fingerprint:
                raise CheckpointError(f"{self.directory} is the checkpoint of another run "
                                      f"({_difference(stored.get('fingerprint'), fingerprint)})")
            self.recorded_supersteps = int(stored["supersteps"])
        else:
            if manifest.exists():
                raise CheckpointError(f"{self.directory} already holds a checkpoint; resume it "
                                      "with --resume, or choose another directory")
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CheckpointError(f"cannot create {self.directory}: {exc}") from None
            self.recorded_supersteps = 0
        self.supersteps = self.recorded_supersteps
        if not resume:
            self._write_manifest()

    def _path(self, index: int) -> Path:
        return self.directory / f"superstep-{index:05d}.npz"

    def _write_manifest(self) -> None:
        manifest = {"format": FORMAT, "version": VERSION, "fingerprint": self.fingerprint,
                    "supersteps": self.supersteps}
        _write_atomically(self.directory / MANIFEST, json.dumps(manifest, indent=1).encode())

    def replay(self, index: int, kernel: str, tasks_digest: str) -> Recorded | None:
        """The recorded superstep ``index`` if there is one (None: run it live). Raises
        :class:`CheckpointError` if it ran another kernel or other tasks."""
        if index >= self.recorded_supersteps:
            return None
        try:
            with np.load(self._path(index), allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                arrays = [data[f"a{k}"] for k in range(meta["arrays"])]
        except (OSError, KeyError, ValueError) as exc:
            raise CheckpointError(f"cannot read superstep {index} of {self.directory}: "
                                  f"{exc}") from None
        if meta["kernel"] != kernel or meta["tasks"] != tasks_digest:
            raise CheckpointError(f"superstep {index} of {self.directory} ran other tasks "
                                  "than this run: the checkpoint is not this run's")
        trace = SuperstepTrace(**_decode(meta["trace"], arrays))
        return Recorded(results=_decode_results(meta["results"], arrays), trace=trace)

    def record(self, index: int, kernel: str, tasks_digest: str, results: Any,
               trace: SuperstepTrace) -> None:
        """Write superstep ``index`` (atomically), then the manifest that counts it."""
        encoder = _Encoder()
        fields = {f.name: getattr(trace, f.name) for f in dataclasses.fields(trace)}
        meta = {"kernel": kernel, "tasks": tasks_digest, "results": encoder.results(results),
                "trace": encoder.value(fields)}
        meta["arrays"] = len(encoder.arrays)
        buffer = io.BytesIO()
        np.savez(buffer, meta=np.array(json.dumps(meta)),
                 **{f"a{k}": a for k, a in enumerate(encoder.arrays)})
        _write_atomically(self._path(index), buffer.getvalue())
        self.supersteps = index + 1
        self._write_manifest()


def _difference(stored: Any, current: Mapping) -> str:
    if not isinstance(stored, Mapping):
        return "no fingerprint"
    keys = sorted(set(stored) | set(current))
    diffs = [f"{k}: {stored.get(k)!r} there, {current.get(k)!r} here"
             for k in keys if stored.get(k) != current.get(k)]
    return "; ".join(diffs)[:300] or "different"
