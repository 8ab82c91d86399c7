"""Partitioning policies: contiguous blocks, longest-first, and affinity-keeping longest-first."""

from __future__ import annotations

import numpy as np
import pytest

from ocpar.bsp.partition import (
    block_loads,
    contiguous_blocks,
    cost_balanced_blocks,
    longest_first,
    sticky_longest_first,
)


def loads(groups, costs):
    return [sum(costs[i] for i in g) for g in groups]


def span(groups, costs) -> float:
    return max(loads(groups, costs))


def imbalance(groups, costs) -> float:
    load = loads(groups, costs)
    return max(load) / (sum(load) / len(load))


def owner(groups, n_tasks):
    """Worker of each task, from a partition."""
    out = [None] * n_tasks
    for w, g in enumerate(groups):
        for i in g:
            out[i] = w
    return out


def assert_partition(groups, n_tasks, n_workers):
    assert len(groups) == n_workers
    for g in groups:
        assert list(g) == sorted(g)
    assert sorted(i for g in groups for i in g) == list(range(n_tasks))


def test_existing_policies_are_partitions():
    assert [list(b) for b in contiguous_blocks(10, 4)] == [[0, 1, 2], [3, 4, 5], [6, 7], [8, 9]]
    # longest first, ties to the lowest-numbered worker: 5→w0, 4→w1, 3→w1 (4<5), 2→w0
    assert longest_first([5, 4, 3, 2], 2) == [[0, 3], [1, 2]]


@pytest.mark.parametrize("seed", range(25))
def test_sticky_is_valid_and_within_tolerance(seed):
    rng = np.random.default_rng(seed)
    n_tasks = int(rng.integers(0, 40))
    n_workers = int(rng.integers(1, 9))
    costs = list(rng.lognormal(0.0, 1.0, n_tasks))
    # previous run had a possibly different worker count; some tasks are new (None)
    old_workers = int(rng.integers(1, 12))
    previous = [None if rng.random() < 0.1 else int(rng.integers(0, old_workers))
                for _ in range(n_tasks)]
    tolerance = float(rng.choice([0.0, 0.05, 0.2]))
    groups = sticky_longest_first(costs, n_workers, previous, tolerance)
    assert_partition(groups, n_tasks, n_workers)
    if n_tasks:
        plain = span(longest_first(costs, n_workers), costs)
        assert span(groups, costs) <= (1 + tolerance) * plain * (1 + 1e-12)
    # never fewer tasks in place than plain longest-first; deterministic
    def kept(g):
        return sum(a == b for a, b in zip(owner(g, n_tasks), previous, strict=True))

    assert kept(groups) >= kept(longest_first(costs, n_workers))
    assert groups == sticky_longest_first(costs, n_workers, previous, tolerance)


@pytest.mark.parametrize("seed", range(5))
def test_previous_none_is_longest_first(seed):
    rng = np.random.default_rng(seed)
    costs = list(rng.uniform(0, 1, 30))
    assert sticky_longest_first(costs, 4) == longest_first(costs, 4)
    assert sticky_longest_first(costs, 4, None) == longest_first(costs, 4)
    # no usable previous worker (all None or beyond the new worker count) is the same
    assert sticky_longest_first(costs, 4, [None] * 30) == longest_first(costs, 4)
    assert sticky_longest_first(costs, 4, [4 + i % 3 for i in range(30)]) == longest_first(
        costs, 4
    )


def test_ties_like_longest_first():
    # equal costs: longest_first deals tasks 0,1,2,3 to workers 0,1,2,3, then again
    assert sticky_longest_first([1.0] * 8, 4) == [[0, 4], [1, 5], [2, 6], [3, 7]]
    assert sticky_longest_first([1.0] * 8, 4, [None] * 8) == [[0, 4], [1, 5], [2, 6], [3, 7]]


def test_keeps_a_balanced_previous_assignment():
    # contiguous blocks of equal tasks are perfectly balanced: nothing moves, even at tol 0,
    # although plain longest_first would deal the tasks round-robin instead
    costs = [2.0] * 12
    blocks = [list(b) for b in contiguous_blocks(12, 3)]
    previous = owner(blocks, 12)
    assert sticky_longest_first(costs, 3, previous, tolerance=0.0) == blocks
    assert longest_first(costs, 3) != blocks


@pytest.mark.parametrize("seed", range(5))
def test_keeps_its_own_lpt_assignment_under_small_changes(seed):
    rng = np.random.default_rng(seed)
    costs = list(rng.uniform(1, 2, 40))
    previous = owner(longest_first(costs, 4), 40)
    # the same costs: LPT's own assignment is kept exactly, even at tolerance 0
    assert sticky_longest_first(costs, 4, previous, tolerance=0.0) == longest_first(costs, 4)
    # costs drift by ≤ 1 %: every task stays put within a 5 % tolerance
    drifted = [c * (1 + 0.01 * (2 * rng.random() - 1)) for c in costs]
    groups = sticky_longest_first(drifted, 4, previous, tolerance=0.05)
    assert owner(groups, 40) == previous


def test_moves_tasks_when_keeping_them_would_unbalance():
    # previous run: everything on worker 0; now 4 workers are available
    costs = [1.0] * 8
    groups = sticky_longest_first(costs, 4, [0] * 8, tolerance=0.05)
    assert_partition(groups, 8, 4)
    assert span(groups, costs) == 2.0
    # worker 0 keeps what fits (the two longest-first tasks, lowest indices)
    assert groups[0] == [0, 1]


def test_heterogeneous_workload_beats_contiguous_blocks():
    # costs growing linearly with the index; previous superstep used contiguous blocks
    n, p = 40, 4
    costs = [float(i + 1) for i in range(n)]
    blocks = [list(b) for b in contiguous_blocks(n, p)]
    assert loads(blocks, costs) == [55.0, 155.0, 255.0, 355.0]
    groups = sticky_longest_first(costs, p, owner(blocks, n), tolerance=0.05)
    assert_partition(groups, n, p)
    assert imbalance(blocks, costs) == pytest.approx(355 / 205)
    assert imbalance(groups, costs) <= 1.05 * imbalance(longest_first(costs, p), costs)
    assert imbalance(groups, costs) < 1.06
    # and it keeps more tasks where they were than plain longest-first does
    kept = sum(a == b for a, b in zip(owner(groups, n), owner(blocks, n), strict=True))
    kept_plain = sum(
        a == b for a, b in zip(owner(longest_first(costs, p), n), owner(blocks, n), strict=True)
    )
    assert kept > kept_plain


def test_few_long_tasks_first():
    costs = [10.0, 10.0, 10.0] + [1.0] * 27  # total 57 on 3 workers
    blocks = [list(b) for b in contiguous_blocks(30, 3)]
    previous = owner(blocks, 30)
    assert loads(blocks, costs) == [37.0, 10.0, 10.0]
    groups = sticky_longest_first(costs, 3, previous)
    assert_partition(groups, 30, 3)
    # perfectly balanced, like plain longest-first: one long task per worker, worker 0 keeps
    # task 0 and its 7 short tasks; tasks 1 and 2 move, as do the short tasks that no longer
    # fit on workers 1 and 2 (19 and 28, 29)
    assert loads(groups, costs) == [19.0, 19.0, 19.0]
    assert sum(i in groups[0] for i in range(3)) == 1
    moved = [i for i, w in enumerate(owner(groups, 30)) if w != previous[i]]
    assert moved == [1, 2, 19, 28, 29]
    plain = owner(longest_first(costs, 3), 30)
    assert sum(a == b for a, b in zip(plain, previous, strict=True)) < 25


def test_bad_input():
    with pytest.raises(ValueError, match="at least one worker"):
        sticky_longest_first([1.0], 0)
    with pytest.raises(ValueError, match="1 previous workers for 2 tasks"):
        sticky_longest_first([1.0, 2.0], 2, [0])
    with pytest.raises(ValueError, match="previous\\[0\\]"):
        sticky_longest_first([1.0], 2, [-1])
    with pytest.raises(ValueError, match="costs"):
        sticky_longest_first([1.0, -1.0], 2)
    with pytest.raises(ValueError, match="tolerance"):
        sticky_longest_first([1.0], 2, tolerance=-0.1)


@pytest.mark.parametrize(("n", "workers"), [(12, 3), (12, 4), (10, 2), (7, 1), (64, 8)])
def test_equal_costs_give_contiguous_blocks(n, workers):
    assert cost_balanced_blocks([2.5] * n, workers) == contiguous_blocks(n, workers)
    assert cost_balanced_blocks([0.0] * n, workers) == contiguous_blocks(n, workers)


@pytest.mark.parametrize(("n", "workers"), [(10, 3), (11, 4), (5, 8), (0, 2)])
def test_equal_costs_give_blocks_within_one_agent(n, workers):
    blocks = cost_balanced_blocks([1.0] * n, workers)
    sizes = [len(b) for b in blocks]
    assert len(blocks) == workers and sum(sizes) == n
    assert max(sizes) - min(sizes) <= 1
    assert [b.start for b in blocks[1:]] == [b.stop for b in blocks[:-1]]


def test_skewed_costs_move_the_boundaries_towards_the_expensive_agents():
    """The first quarter costs 5 times the rest: worker 0 takes fewer agents, the loads come
    out equal to within one agent's cost, and the same costs give the same blocks."""
    costs = np.where(np.arange(400) < 100, 5.0, 1.0)
    blocks = cost_balanced_blocks(costs, 2)
    assert blocks == cost_balanced_blocks(costs.tolist(), 2)
    assert blocks == [range(0, 80), range(80, 400)]
    assert len(blocks[0]) < len(contiguous_blocks(400, 2)[0])
    loads = block_loads(costs, blocks)
    assert np.ptp(loads) <= costs.max()
    assert loads.max() < block_loads(costs, contiguous_blocks(400, 2)).max()
    # the expensive agents at the end: the boundaries move the other way
    reverse = cost_balanced_blocks(costs[::-1], 2)
    assert reverse == [range(0, 320), range(320, 400)]


@pytest.mark.parametrize("seed", range(5))
def test_balanced_blocks_are_a_partition_within_one_cost_of_the_ideal(seed):
    rng = np.random.default_rng(seed)
    costs = rng.exponential(size=500) * np.repeat(rng.uniform(0.2, 5.0, size=5), 100)
    for workers in (2, 3, 7):
        blocks = cost_balanced_blocks(costs, workers)
        assert [i for b in blocks for i in b] == list(range(500))
        assert block_loads(costs, blocks).max() <= costs.sum() / workers + costs.max()


def test_one_agent_heavier_than_a_share_leaves_a_block_empty():
    assert cost_balanced_blocks([100.0, 1.0, 1.0], 2) == [range(0, 1), range(1, 3)]
    assert cost_balanced_blocks([1.0, 100.0, 1.0], 3) == [range(0, 1), range(1, 2), range(2, 3)]
    assert cost_balanced_blocks([100.0], 3) == [range(0, 0), range(0, 1), range(1, 1)]


def test_balanced_blocks_bad_input():
    with pytest.raises(ValueError):
        cost_balanced_blocks([1.0, -1.0], 2)
    with pytest.raises(ValueError):
        cost_balanced_blocks([1.0, float("nan")], 2)
    with pytest.raises(ValueError):
        cost_balanced_blocks([1.0], 0)
