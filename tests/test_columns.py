"""The columnar wire format: exact round trips, and plain lists where columns do not apply."""

import pickle
from dataclasses import dataclass, field

import numpy as np
import pytest

from ocpar.bsp.columns import LISTED, SHARED, STACKED, Columns, from_columns, to_columns
from ocpar.formation import paper_example
from ocpar.ocp import DmocTask, solve_dmoc_task


@dataclass(frozen=True)
class Frozen:
    x: np.ndarray
    label: str
    extra: dict = field(default_factory=dict)


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return (isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and a.tobytes() == b.tobytes())
    return type(a) is type(b) and a == b


def test_dmoc_tasks_and_solutions_round_trip_bit_for_bit_through_pickle():
    problem = paper_example(agents=6)
    tasks = problem.tasks(problem.initial_phi() + 0.3)
    packed = to_columns(tasks)
    assert isinstance(packed, Columns)
    assert packed.fields["shape"][0] == SHARED and packed.fields["params"][0] == STACKED
    back = from_columns(pickle.loads(pickle.dumps(packed)))
    assert all(type(b) is DmocTask and b.shape == t.shape and _same(b.params, t.params)
               for b, t in zip(back, tasks, strict=True))

    solutions = [solve_dmoc_task(t) for t in tasks]
    back = from_columns(pickle.loads(pickle.dumps(to_columns(solutions))))
    for b, s in zip(back, solutions, strict=True):
        assert vars(b).keys() == vars(s).keys()
        assert all(_same(vars(b)[k], vars(s)[k]) for k in vars(s))


def test_fields_are_stacked_shared_or_listed_by_content():
    shared = {"k": 1}
    items = [Frozen(np.full((2, 3), i, dtype=np.float32), f"a{i}", shared) for i in range(4)]
    packed = to_columns(items)
    assert {k: kind for k, (kind, _) in packed.fields.items()} == {
        "x": STACKED, "label": LISTED, "extra": SHARED}
    assert packed.fields["x"][1].shape == (4, 2, 3)
    back = from_columns(packed)
    assert all(_same(b.x, i.x) and b.label == i.label for b, i in zip(back, items, strict=True))
    assert back[0].extra is back[3].extra  # shared stays one object, as it was


@pytest.mark.parametrize("xs", [
    [np.zeros(3), np.zeros(4)],                  # ragged shapes
    [np.zeros(3), np.zeros(3, dtype=np.int64)],  # mixed dtypes
    [np.zeros(3), [0.0, 0.0, 0.0]],              # not all arrays
])
def test_unstackable_fields_stay_lists_and_keep_their_values(xs):
    items = [Frozen(x, "a") for x in xs]
    packed = to_columns(items)
    assert packed.fields["x"][0] == LISTED
    back = from_columns(packed)
    assert all(_same(b.x, i.x) for b, i in zip(back, items, strict=True))


@pytest.mark.parametrize("items", [
    [],
    [1.0, 2.0],                                     # not dataclasses
    [Frozen(np.zeros(1), "a"), DmocTask(None, np.zeros(1))],  # two classes
])
def test_other_lists_pass_through_unchanged(items):
    assert to_columns(items) is items
    assert from_columns(items) is items
