"""The columnar wire format: exact round trips, and plain lists where columns do not apply."""

import pickle
from dataclasses import dataclass, field

import numpy as np
import pytest

from ocpar.bsp.columns import (
    LISTED,
    SHARED,
    STACKED,
    VALUES,
    Columns,
    from_columns,
    to_columns,
)
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.ocp import OcpTask, solve_task


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
    tasks = problem.tasks(problem.initial_phi() + 0.3).items()
    packed = to_columns(tasks)
    assert isinstance(packed, Columns)
    assert packed.fields["shape"][0] == SHARED and packed.fields["params"][0] == STACKED
    back = from_columns(pickle.loads(pickle.dumps(packed)))
    assert all(type(b) is OcpTask and b.shape == t.shape and _same(b.params, t.params)
               for b, t in zip(back, tasks, strict=True))

    solutions = [solve_task(t) for t in tasks]
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
    [Frozen(np.zeros(1), "a"), OcpTask(None, np.zeros(1))],  # two classes
])
def test_other_lists_pass_through_unchanged(items):
    assert to_columns(items) == items
    assert from_columns(items) is items


@dataclass
class Scalars:
    flag: bool
    count: int
    value: float
    big: int


def test_python_scalars_become_value_columns_and_come_back_as_python_scalars():
    items = [Scalars(i % 2 == 0, i, 0.1 * i, 2**70 + i) for i in range(5)]
    packed = to_columns(items)
    kinds = {k: kind for k, (kind, _) in packed.fields.items()}
    assert kinds == {"flag": VALUES, "count": VALUES, "value": VALUES, "big": LISTED}
    for b, i in zip(packed.items(), items, strict=True):
        assert all(_same(vars(b)[k], vars(i)[k]) for k in vars(i))


def test_take_and_concat_select_and_join_items_in_order():
    items = [Frozen(np.full(2, float(i)), f"t{i}") for i in range(6)]
    packed = to_columns(items)
    parts = [packed.take([4, 1]), packed.take([]), packed.take([0, 5, 2])]
    joined = Columns.concat(parts)
    assert [b.label for b in joined.items()] == ["t4", "t1", "t0", "t5", "t2"]
    assert joined.column("x")[:, 0].tolist() == [4.0, 1.0, 0.0, 5.0, 2.0]
    assert joined.fields["x"][0] == STACKED


def test_taking_a_range_gives_views_of_the_same_items_as_taking_its_indices():
    items = [Frozen(np.full(2, float(i)), f"t{i}", {"i": i} if i % 2 else {}) for i in range(6)]
    packed = to_columns(items)
    assert packed.fields["extra"][0] == LISTED
    for block in (range(1, 4), range(4, 6), range(3, 3)):
        part = packed.take(block)
        listed = packed.take(list(block))
        assert len(part) == len(block)
        pairs = zip(part.items(), listed.items(), strict=True)
        assert all(_same(vars(b)[k], vars(c)[k]) for b, c in pairs for k in vars(c))
        assert np.shares_memory(part.column("x"), packed.column("x")) or not len(block)
    assert packed.take(range(6)) is packed


def test_concat_keeps_columns_that_differ_between_parts_as_lists():
    a = to_columns([Frozen(np.zeros(2), "a", {}) for _ in range(2)])   # extra shared
    b = to_columns([Frozen(np.zeros(3), "b", {}) for _ in range(2)])   # other row shape
    joined = Columns.concat([a, b])
    assert joined.fields["x"][0] == LISTED and joined.fields["extra"][0] == LISTED
    assert [len(item.x) for item in joined.items()] == [2, 2, 3, 3]
    with pytest.raises(ValueError, match="different classes"):
        Columns.concat([a, to_columns([Scalars(True, 1, 1.0, 1)])])


def test_columns_of_stacks_arrays_with_one_row_per_item_and_shares_the_rest():
    params = np.arange(12.0).reshape(3, 4)
    packed = Columns.of(OcpTask, 3, shape="s", params=params)
    tasks = packed.items()
    assert [t.shape for t in tasks] == ["s"] * 3
    assert np.array_equal(np.stack([t.params for t in tasks]), params)


def test_concat_of_parts_unpickled_apart_keeps_an_equal_string_shared():
    # each worker's reply is unpickled on its own: equal statuses, distinct objects
    a, b = (pickle.loads(pickle.dumps(to_columns([Frozen(np.zeros(2), "Solve_Succeeded")
                                                  for _ in range(2)])))
            for _ in range(2))
    assert a.fields["label"][1] is not b.fields["label"][1]
    joined = Columns.concat([a, b])
    assert joined.fields["label"] == (SHARED, "Solve_Succeeded")
    assert joined.fields["extra"][0] == LISTED  # equal dicts, distinct objects: not shared
    assert [item.label for item in joined.items()] == ["Solve_Succeeded"] * 4
