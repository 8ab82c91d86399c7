"""Checkpoints of a run: a journal of its supersteps, replayed on resume.

Every scheme's coordinator is deterministic given its supersteps' results (its outer solver,
archive updates and random numbers are functions of them and of the run's options), so the
journal of the supersteps is the coordinator's state: on ``--resume`` the coordinator runs
again from the start and each superstep already in the journal returns its recorded results
(and timings) instead of solving, until the journal ends and the run goes on live. The
outer iterate, archive, agent train, random state and warm starts are thereby restored
exactly, and the final result is identical to an uninterrupted run's.

Durability: each superstep is appended to the log as it completes, without waiting for the
disk: a killed process (SIGKILL, out of memory, a crash) keeps every completed superstep.
The manifest's count (written to a temporary name and renamed) follows at most
:data:`PROGRESS_S` later; readers count the log's whole entries for progress
(:func:`recorded_supersteps`), and a resumed run reads the log. The disk
is synced (``fsync`` of the log, then of the manifest) at most every ``interval_s`` seconds
of run time (default :data:`INTERVAL_S`, or the environment variable :data:`INTERVAL_ENV`;
0: after every superstep) and when the run ends (its backend's ``with`` block exits:
:meth:`Journal.flush`), so a machine that loses power keeps at least the supersteps of the
last sync; resuming replays what is kept and recomputes the rest, to the same result bit for
bit. A run of hundreds of supersteps of a few ms each (a pursuit train) thereby pays two
``fsync`` per interval instead of two per superstep.

On disk, in the checkpoint directory:

* ``manifest.json``: ``format``, ``version``, the run's ``fingerprint`` (scheme, problem and
  options, ocpar's version) and the number of ``supersteps`` recorded (at most, as of its
  last rewrite);
* ``supersteps.log``: the supersteps in order, each its length (8 bytes, little-endian), the
  SHA-256 of its data (32 bytes) and its data (:func:`_pack`): the kernel, a digest of its
  tasks, its results and its trace as JSON, arrays as their raw bytes after it (dtype as
  ``.npy`` describes it, and shape, in the JSON); no pickles, no object arrays; objects are
  rebuilt only as dataclasses defined in ocpar's own modules (:func:`result_type`).

A resumed journal keeps the log's supersteps up to the first whose data do not match their
SHA-256 (a log cut short by a kill or a power loss ends at its last intact superstep) and
cuts the log there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import math
import os
import struct
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.trace import SuperstepTrace

FORMAT = "ocpar-checkpoint"
VERSION = 2
MANIFEST = "manifest.json"
#: Seconds of run time between durable checkpoints unless the journal is told otherwise.
INTERVAL_S = 1.0
#: The environment variable that sets the interval (seconds) for runs started from the
#: command line or the service (e.g. ``0``: every superstep durable as it completes).
INTERVAL_ENV = "OCPAR_CHECKPOINT_INTERVAL_S"
#: Seconds of run time between rewrites of the manifest's count between syncs (a progress
#: figure for readers, exact for supersteps longer than this: renaming a file over another
#: costs ~3 ms on ext4, as much as a pursuit train's superstep).
PROGRESS_S = 0.05
LOG = "supersteps.log"
_HEADER = struct.Struct("<Q32s")  # an entry's length and SHA-256

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
    parts: list[bytes] = []
    _feed(parts, value, {})
    return hashlib.sha256(b"".join(parts)).hexdigest()


def _feed(parts: list[bytes], value: Any, fed: dict[int, bytes]) -> None:
    """Append the bytes that stand for ``value`` to ``parts``; ``fed``: those of each
    dataclass instance already fed, by ``id`` (tasks share e.g. their problem's shape)."""
    if isinstance(value, Columns):
        parts.append(f"columns:{value.cls.__qualname__}:{value.length}".encode())
        for name, (kind, data) in value.fields.items():
            parts.append(f"{name}:{kind}".encode())
            _feed(parts, data, fed)
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        if (known := fed.get(id(value))) is not None:
            parts.append(known)
            return
        start = len(parts)
        parts.append(f"dc:{type(value).__qualname__}".encode())
        for f in dataclasses.fields(value):
            parts.append(f.name.encode())
            _feed(parts, getattr(value, f.name), fed)
        fed[id(value)] = b"".join(parts[start:])
    elif isinstance(value, np.ndarray):
        parts.append(f"nd:{value.dtype.str}:{value.shape}".encode())
        parts.append(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, list | tuple):
        parts.append(f"seq:{len(value)}".encode())
        for item in value:
            _feed(parts, item, fed)
    elif isinstance(value, Mapping):
        parts.append(f"map:{len(value)}".encode())
        for key in sorted(value, key=repr):
            _feed(parts, key, fed)
            _feed(parts, value[key], fed)
    else:
        parts.append(f"{type(value).__qualname__}:{value!r}".encode())


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


def _write_atomically(path: Path, data: bytes, sync: bool = True) -> None:
    """Write ``data`` to a temporary file and rename it ``path``; ``sync``: the data on disk
    (``fsync``) before the rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if sync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def interval_from_environment() -> float:
    """The checkpoint interval (s) that :data:`INTERVAL_ENV` sets, else :data:`INTERVAL_S`."""
    text = os.environ.get(INTERVAL_ENV, "").strip()
    if not text:
        return INTERVAL_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0:  # also NaN
        raise CheckpointError(f"{INTERVAL_ENV}={text!r}: expected seconds >= 0")
    return value


def _pack(meta: dict, arrays: list[np.ndarray]) -> bytes:
    """An entry's data: the length of its JSON (8 bytes), the JSON (``meta`` with each array's
    ``.npy`` dtype description and shape under ``"arrays"``) and the arrays' bytes (C order)."""
    meta = meta | {"arrays": [[np.lib.format.dtype_to_descr(a.dtype), list(a.shape)]
                              for a in arrays]}
    text = json.dumps(meta).encode()
    return b"".join([len(text).to_bytes(8, "little"), text,
                     *(np.ascontiguousarray(a).tobytes() for a in arrays)])


def _unpack(data: bytes) -> tuple[dict, list[np.ndarray]]:
    """The meta and arrays of :func:`_pack` (raises ValueError if they do not fit)."""
    length = int.from_bytes(data[:8], "little")
    meta = json.loads(data[8:8 + length])
    arrays, offset = [], 8 + length
    for descr, shape in meta["arrays"]:
        dtype = np.lib.format.descr_to_dtype(descr)
        if dtype.hasobject:
            raise ValueError("an object array")
        count = math.prod(shape)
        arrays.append(np.frombuffer(data, dtype, count, offset).reshape(shape).copy())
        offset += count * dtype.itemsize
    if offset != len(data):
        raise ValueError(f"{len(data) - offset} bytes past its arrays")
    return meta, arrays


def _intact(log: BinaryIO) -> list[tuple[int, int]]:
    """(offset, length) of the entries of ``log`` up to the first one cut short or altered."""
    entries: list[tuple[int, int]] = []
    offset = 0
    while True:
        header = log.read(_HEADER.size)
        if len(header) < _HEADER.size:
            break
        length, sha = _HEADER.unpack(header)
        if hashlib.sha256(log.read(length)).digest() != sha:
            break
        entries.append((offset + _HEADER.size, length))
        offset += _HEADER.size + length
    return entries


def recorded_supersteps(directory: str | Path) -> int:
    """The supersteps whose entries the log of the checkpoint in ``directory`` holds whole,
    now (their headers read, their data not checked: progress for readers, exact where the
    manifest's count lags by up to :data:`PROGRESS_S`); 0 without a log."""
    count = offset = 0
    try:
        with open(Path(directory) / LOG, "rb") as log:
            size = os.fstat(log.fileno()).st_size
            while offset + _HEADER.size <= size:
                log.seek(offset)
                length, _ = _HEADER.unpack(log.read(_HEADER.size))
                offset += _HEADER.size + length
                if offset > size:
                    break
                count += 1
    except OSError:
        return 0
    return count


class Journal:
    """The checkpoint in ``directory`` of the run with ``fingerprint`` (a JSON-able dict).

    ``resume=False`` starts a new checkpoint (refused if the directory holds one);
    ``resume=True`` opens an existing one (refused if it is missing, of another format or
    version, or of another run) and :meth:`replay` serves its supersteps. ``interval_s``:
    seconds of run time between syncs to disk (0: every superstep; None:
    :func:`interval_from_environment`); :meth:`flush` syncs the rest.
    """

    def __init__(self, directory: str | Path, fingerprint: dict, resume: bool,
                 interval_s: float | None = None) -> None:
        self.directory = Path(directory)
        self.fingerprint = json.loads(json.dumps(fingerprint))
        self.interval_s = interval_from_environment() if interval_s is None else interval_s
        if not self.interval_s >= 0:
            raise CheckpointError(f"checkpoint interval {self.interval_s} s: expected >= 0")
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
        else:
            if manifest.exists():
                raise CheckpointError(f"{self.directory} already holds a checkpoint; resume it "
                                      "with --resume, or choose another directory")
            try:
                self.directory.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CheckpointError(f"cannot create {self.directory}: {exc}") from None
        self._log = self.directory / LOG
        #: Where each recorded superstep's data lies in the log: (offset, length) in bytes.
        self._entries: list[tuple[int, int]] = []
        try:
            with open(self._log, "r+b" if resume else "wb") as log:
                if resume:
                    self._entries = _intact(log)
                    log.truncate(sum(_HEADER.size + n for _, n in self._entries))
        except OSError as exc:
            raise CheckpointError(f"cannot open {self._log}: {exc}") from None
        self.recorded_supersteps = len(self._entries)
        self.supersteps = self.recorded_supersteps
        self._synced_at = self._counted_at = time.monotonic()
        if not resume:
            self._write_manifest(sync=True)

    def _write_manifest(self, sync: bool) -> None:
        self._counted_at = time.monotonic()
        manifest = {"format": FORMAT, "version": VERSION, "fingerprint": self.fingerprint,
                    "supersteps": self.supersteps}
        _write_atomically(self.directory / MANIFEST, json.dumps(manifest, indent=1).encode(),
                          sync)

    def replay(self, index: int, kernel: str, tasks_digest: str) -> Recorded | None:
        """The recorded superstep ``index`` if there is one (None: run it live). Raises
        :class:`CheckpointError` if it ran another kernel or other tasks."""
        if index >= self.recorded_supersteps:
            return None
        offset, length = self._entries[index]
        try:
            with open(self._log, "rb") as log:
                log.seek(offset)
                entry = log.read(length)
            meta, arrays = _unpack(entry)
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise CheckpointError(f"cannot read superstep {index} of {self.directory}: "
                                  f"{exc}") from None
        if meta["kernel"] != kernel or meta["tasks"] != tasks_digest:
            raise CheckpointError(f"superstep {index} of {self.directory} ran other tasks "
                                  "than this run: the checkpoint is not this run's")
        trace = SuperstepTrace(**_decode(meta["trace"], arrays))
        return Recorded(results=_decode_results(meta["results"], arrays), trace=trace)

    def record(self, index: int, kernel: str, tasks_digest: str, results: Any,
               trace: SuperstepTrace) -> None:
        """Append superstep ``index`` (the next one) to the log; sync it and the manifest to
        disk if :attr:`interval_s` has passed since the last sync, else rewrite the manifest
        if :data:`PROGRESS_S` has passed since its last rewrite."""
        if index != self.supersteps:
            raise CheckpointError(f"superstep {index} recorded after superstep "
                                  f"{self.supersteps - 1}")
        encoder = _Encoder()
        fields = {f.name: getattr(trace, f.name) for f in dataclasses.fields(trace)}
        meta = {"kernel": kernel, "tasks": tasks_digest, "results": encoder.results(results),
                "trace": encoder.value(fields)}
        data = _pack(meta, encoder.arrays)
        sync = time.monotonic() - self._synced_at >= self.interval_s
        with open(self._log, "ab") as log:  # written to the OS: a killed process keeps it
            end = log.tell()
            log.write(_HEADER.pack(len(data), hashlib.sha256(data).digest()) + data)
            if sync:
                log.flush()
                os.fsync(log.fileno())
        self._entries.append((end + _HEADER.size, len(data)))
        self.supersteps = index + 1
        if sync or time.monotonic() - self._counted_at >= PROGRESS_S:
            self._write_manifest(sync)
        if sync:
            self._synced_at = time.monotonic()

    def flush(self) -> None:
        """Sync every superstep recorded to disk: the log, then the manifest."""
        with open(self._log, "ab") as log:
            os.fsync(log.fileno())
        self._write_manifest(sync=True)
        self._synced_at = time.monotonic()


def _difference(stored: Any, current: Mapping) -> str:
    if not isinstance(stored, Mapping):
        return "no fingerprint"
    keys = sorted(set(stored) | set(current))
    diffs = [f"{k}: {stored.get(k)!r} there, {current.get(k)!r} here"
             for k in keys if stored.get(k) != current.get(k)]
    return "; ".join(diffs)[:300] or "different"
