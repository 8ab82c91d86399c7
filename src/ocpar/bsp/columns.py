"""Columnar form of a list of tasks or results: one column per attribute, not one object each.

Pickling a list of n small dataclass instances (a DMOC task: shape + 8 floats; its solution:
5 small arrays) costs ~10–25 µs per item on each side, because every item and every array is
its own pickled object; at 1000 agents that was ~40 ms per superstep in the coordinator, more
than the superstep's computation on 64 workers. :class:`Columns` keeps n instances of one
dataclass attribute by attribute: arrays of equal shape and dtype stacked into one array,
Python numbers and booleans of one type in one array, a value every item shares (``is``, or
an equal string) once, anything else in a list. Selecting, concatenating and reordering
columns costs a few numpy calls, whatever n is; :meth:`Columns.items` rebuilds the instances
(array attributes are views of the stacked column). Round trips are exact: same values,
bits, types, dtypes and shapes.

>>> from dataclasses import dataclass
>>> import numpy as np
>>> @dataclass
... class Item:
...     x: np.ndarray
...     tag: str
>>> items = [Item(np.arange(3.0) + i, "a") for i in range(4)]
>>> columns = to_columns(items)
>>> columns.column("x").shape
(4, 3)
>>> [(list(b.x), b.tag) for b in columns.take([2, 0]).items()]
[([2.0, 3.0, 4.0], 'a'), ([0.0, 1.0, 2.0], 'a')]
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

STACKED, VALUES, SHARED, LISTED = "stacked", "values", "shared", "listed"
"""Column kinds: arrays stacked on a new first axis; Python scalars of one type (bool, int,
float) in a 1-D array; one value shared by every item; a plain list."""

_SCALARS = (bool, int, float)


@dataclass(frozen=True)
class Columns:
    """``length`` instances of the dataclass ``cls``, attribute by attribute: ``fields`` maps
    an attribute name to (kind, data), kind one of :data:`STACKED` (data: array of shape
    (length, ...)), :data:`VALUES` (data: 1-D array), :data:`SHARED` (data: the one value)
    or :data:`LISTED` (data: list of ``length`` values)."""

    cls: type
    length: int
    fields: dict[str, tuple[str, Any]]

    @classmethod
    def of(cls, item_type: type, length: int, **columns: Any) -> Columns:
        """Columns built from whole columns: a numpy array with ``length`` rows is stacked,
        anything else is shared, e.g. ``Columns.of(OcpTask, n, shape=shape, params=P)``
        with P of shape (n, 8)."""
        fields = {}
        for name, data in columns.items():
            stacked = isinstance(data, np.ndarray) and data.ndim >= 1 and len(data) == length
            fields[name] = (STACKED, data) if stacked else (SHARED, data)
        return cls(cls=item_type, length=length, fields=fields)

    def __len__(self) -> int:
        return self.length

    def column(self, name: str) -> np.ndarray | list[Any]:
        """Attribute ``name`` of every item: an array for stacked and value columns (rows in
        item order), else a list."""
        kind, data = self.fields[name]
        if kind == SHARED:
            return [data] * self.length
        return data

    def take(self, indices: Sequence[int] | np.ndarray) -> Columns:
        """The items at ``indices``, in that order (a ``range`` of step 1: views of the
        columns, no copy; all items: these columns)."""
        if isinstance(indices, range) and indices.step == 1:
            if indices.start == 0 and indices.stop == self.length:
                return self
            index: slice | np.ndarray = slice(indices.start, indices.stop)  # views, no copy
        else:
            index = np.asarray(indices, dtype=np.intp)
        fields = {}
        for name, (kind, data) in self.fields.items():
            if kind in (STACKED, VALUES):
                fields[name] = (kind, data[index])
            elif kind == LISTED:
                fields[name] = (kind, data[index] if isinstance(index, slice)
                                else [data[i] for i in index.tolist()])
            else:
                fields[name] = (kind, data)
        return Columns(cls=self.cls, length=len(indices), fields=fields)

    @staticmethod
    def concat(parts: Sequence[Columns]) -> Columns:
        """The items of ``parts`` one after the other (all of one class, with the same
        attributes). A column stays stacked/valued where every part has it so with one dtype
        and row shape, shared where every part shares the same object or an equal string
        (parts unpickled from different workers hold equal, not identical, strings)."""
        if not parts:
            raise ValueError("nothing to concatenate")
        first = parts[0]
        if len(parts) == 1:
            return first
        if any(p.cls is not first.cls or p.fields.keys() != first.fields.keys() for p in parts):
            raise ValueError("columns of different classes or attributes cannot be joined")
        fields = {}
        for name, (kind, data) in first.fields.items():
            columns = [p.fields[name] for p in parts]
            if all(k == SHARED and _same(d, data) for k, d in columns):
                fields[name] = (SHARED, data)
            elif kind in (STACKED, VALUES) and all(
                    k == kind and d.dtype == data.dtype and d.shape[1:] == data.shape[1:]
                    for k, d in columns):
                fields[name] = (kind, np.concatenate([d for _, d in columns]))
            else:
                fields[name] = (LISTED, [v for p in parts for v in p._values(name)])
        return Columns(cls=first.cls, length=sum(p.length for p in parts), fields=fields)

    def _values(self, name: str) -> list[Any]:
        kind, data = self.fields[name]
        if kind == SHARED:
            return [data] * self.length
        if kind == VALUES:
            return data.tolist()
        return list(data)

    def items(self) -> list[Any]:
        """The instances (no ``__init__``/``__post_init__``: their attributes are set as they
        were read, already validated once)."""
        names, columns = [], []
        for name, (kind, data) in self.fields.items():
            names.append(name)
            if kind == SHARED:
                columns.append(itertools.repeat(data, self.length))
            else:
                columns.append(data.tolist() if kind == VALUES else data)
        new = object.__new__
        out = []
        for values in zip(*columns, strict=True):
            item = new(self.cls)
            item.__dict__.update(zip(names, values, strict=True))
            out.append(item)
        return out


def _same(value: Any, first: Any) -> bool:
    """``value`` can share one column entry with ``first``: the same object, or an equal string
    (immutable, so kept once)."""
    return value is first or (type(value) is str and type(first) is str and value == first)


def _column(values: list[Any]) -> tuple[str, Any]:
    first = values[0]
    if all(_same(v, first) for v in values):  # e.g. one shape, or a solver status
        return SHARED, first
    kind = type(first)
    if kind in _SCALARS and all(type(v) is kind for v in values):
        try:
            return VALUES, np.array(values, dtype=np.int64 if kind is int else kind)
        except OverflowError:  # ints beyond int64 stay Python ints
            return LISTED, values
    if kind is np.ndarray and first.dtype != object:
        shape, dtype = first.shape, first.dtype
        if all(type(v) is np.ndarray and v.shape == shape and v.dtype == dtype
               for v in values):
            return STACKED, np.array(values, dtype=dtype)  # 2x faster than np.stack
    return LISTED, values


def to_columns(items: Sequence[Any] | Columns) -> Columns | list[Any]:
    """``items`` as :class:`Columns` if they are ≥ 1 instances of one dataclass whose
    attributes (``__dict__``) have the same names; :class:`Columns` as they are; anything
    else as a list (pickled as usual)."""
    if isinstance(items, Columns):
        return items
    items = list(items)
    if not items:
        return items
    cls = type(items[0])
    if not dataclasses.is_dataclass(cls) or not hasattr(items[0], "__dict__"):
        return items
    names = items[0].__dict__.keys()
    if any(type(item) is not cls or item.__dict__.keys() != names for item in items):
        return items
    return Columns(cls=cls, length=len(items),
                   fields={name: _column([item.__dict__[name] for item in items])
                           for name in names})


def from_columns(packed: Columns | list[Any]) -> list[Any]:
    """The list of instances that :func:`to_columns` packed (a plain list passes through)."""
    return packed.items() if isinstance(packed, Columns) else packed
