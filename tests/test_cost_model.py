"""The BSP cost model: makespans, synchronisation cost fit, predictions, trace helpers."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math

import numpy as np
import pytest

from ocpar.bsp.cost_model import (
    Prediction,
    SyncCost,
    coordinator_share,
    makespan,
    median_overhead,
    predict,
    serial_time,
    task_times,
)
from ocpar.bsp.partition import contiguous_blocks, longest_first
from ocpar.bsp.trace import SuperstepTrace

FREE = SyncCost(a_s=0.0, b_s=0.0)


def brute_force_opt(times, workers) -> float:
    """Optimal makespan by trying every assignment (small cases only)."""
    best = math.inf
    for assignment in itertools.product(range(workers), repeat=len(times)):
        loads = [0.0] * workers
        for t, w in zip(times, assignment, strict=True):
            loads[w] += t
        best = min(best, max(loads))
    return best


# --- makespan ---------------------------------------------------------------------------


def test_equal_tasks_on_blocks():
    assert makespan([1.0] * 60, 4, "blocks") == 15.0
    assert makespan([1.0] * 60, 4, "lpt") == 15.0
    # 61 tasks: one block gets 16
    assert makespan([1.0] * 61, 4, "blocks") == 16.0
    assert makespan([0.25] * 60, 1, "blocks") == 15.0


def test_heterogeneous_lpt_beats_blocks():
    times = [5.0, 5.0, 1.0, 1.0, 1.0, 1.0]
    # blocks {5, 5, 1} {1, 1, 1}; LPT {5, 1, 1} {5, 1, 1}
    assert makespan(times, 2, "blocks") == 11.0
    assert makespan(times, 2, "lpt") == 7.0


def test_more_workers_than_tasks():
    assert makespan([3.0, 1.0, 2.0], 8, "blocks") == 3.0
    assert makespan([3.0, 1.0, 2.0], 8, "lpt") == 3.0
    assert makespan([], 4, "blocks") == 0.0
    assert makespan([], 4, "lpt") == 0.0


def test_graham_tight_instance():
    # the classic worst case for P = 2: LPT {3, 2, 2} {3, 2} = 7, OPT {3, 3} {2, 2, 2} = 6
    times = [3.0, 3.0, 2.0, 2.0, 2.0]
    assert makespan(times, 2, "lpt") == 7.0
    assert brute_force_opt(times, 2) == 6.0
    ratio = makespan(times, 2, "lpt") / brute_force_opt(times, 2)
    assert ratio == pytest.approx(4 / 3 - 1 / (3 * 2))  # the bound is attained


@pytest.mark.parametrize("seed", range(12))
def test_graham_bound(seed):
    rng = np.random.default_rng(seed)
    workers = int(rng.integers(2, 4))
    times = list(rng.integers(1, 10, int(rng.integers(workers + 1, 9))).astype(float))
    opt = brute_force_opt(times, workers)
    lpt = makespan(times, workers, "lpt")
    assert opt <= lpt <= (4 / 3 - 1 / (3 * workers)) * opt + 1e-12


@pytest.mark.parametrize("seed", range(10))
def test_lpt_makespan_is_that_of_longest_first(seed):
    rng = np.random.default_rng(seed)
    times = list(rng.integers(0, 5, 50).astype(float))  # many ties
    for workers in (1, 3, 7, 64):
        groups = longest_first(times, workers)
        assert makespan(times, workers, "lpt") == max(sum(times[i] for i in g) for g in groups)


# --- synchronisation cost ---------------------------------------------------------------


def test_sync_cost_at():
    sync = SyncCost(a_s=1e-3, b_s=2e-4)
    assert sync.at(1) == 1e-3
    assert sync.at(8) == pytest.approx(1e-3 + 3 * 2e-4)


def test_sync_fit_recovers_exact_data():
    a, b = 2e-3, 5e-4
    sync = SyncCost.fit({p: a + b * math.log2(p) for p in (1, 2, 4, 8, 16, 32)})
    assert sync.a_s == pytest.approx(a, rel=1e-9)
    assert sync.b_s == pytest.approx(b, rel=1e-9)
    # two points determine the line
    sync = SyncCost.fit({2: a + b, 64: a + 6 * b})
    assert (sync.a_s, sync.b_s) == (pytest.approx(a, rel=1e-9), pytest.approx(b, rel=1e-9))


def test_sync_fit_one_point_and_clamping():
    assert SyncCost.fit({8: 0.01}) == SyncCost(a_s=0.01, b_s=0.0)
    assert SyncCost.fit({4: -0.001}) == SyncCost(a_s=0.0, b_s=0.0)
    # overheads falling with P: b would be negative → b = 0, a = mean
    sync = SyncCost.fit({1: 0.02, 4: 0.01})
    assert sync.b_s == 0.0
    assert sync.a_s == pytest.approx(0.015)
    # a would be negative (a = -0.01, b = 0.01) → a = 0, b = Σxy/Σx² over x = log2 P
    sync = SyncCost.fit({2: 0.0, 8: 0.02})
    assert sync.a_s == 0.0
    assert sync.b_s == pytest.approx(0.06 / 10)


def test_sync_fit_separates_latency_and_bytes():
    """σ(P, h) = a + b log2 P + g h: supersteps on 1 and 2 workers of varying bytes give back
    a, b and g; with the coordinator running a chunk itself only (P−1)/P of h crosses."""
    a, b, g = 3e-4, 2e-4, 1.5e-9
    samples = [(p, h, a + b * math.log2(p) + g * h)
               for p in (1, 2, 4) for h in (0.0, 2e5, 8e5, 5e6)]
    sync = SyncCost.fit_supersteps(samples, local_chunk=True)
    assert (sync.a_s, sync.b_s, sync.g_s_per_byte) == (
        pytest.approx(a, rel=1e-6), pytest.approx(b, rel=1e-6), pytest.approx(g, rel=1e-6))
    assert sync.at(2, 1e6) == pytest.approx(a + b + g * 0.5e6)
    assert SyncCost(a, b, g).at(2, 1e6) == pytest.approx(a + b + g * 1e6)
    (one,) = predict([[1.0], [1.0]], [2], "blocks", SyncCost(0.0, 0.0, 1e-6),
                     superstep_bytes=[1e6, 3e6])
    assert one.sync_s == pytest.approx(4.0)
    with pytest.raises(ValueError, match="2 supersteps"):
        predict([[1.0], [1.0]], [2], "blocks", FREE, superstep_bytes=[1.0])


# --- predictions ------------------------------------------------------------------------


def test_prediction_at_one_worker_is_the_serial_sum():
    steps = [[0.5, 1.5, 2.0], [0.25] * 8, [3.0]]
    sync = SyncCost(a_s=0.01, b_s=0.002)
    for policy in ("blocks", "lpt"):
        (p1,) = predict(steps, [1], policy, sync, serial_s=4.0)
        assert p1.wall_s == pytest.approx(4.0 + 4.0 + 2.0 + 3.0 + 3 * sync.at(1))
        assert p1.compute_s == pytest.approx(9.0)
        assert p1.sync_s == pytest.approx(3 * 0.01)
        assert p1.serial_s == 4.0
        assert (p1.speedup, p1.efficiency) == (1.0, 1.0)


def test_prediction_parts():
    sync = SyncCost(a_s=0.1, b_s=0.05)
    (p4,) = predict([[1.0] * 60, [2.0] * 4], [4], "blocks", sync, serial_s=3.0)
    assert p4 == Prediction(
        workers=4,
        wall_s=pytest.approx(3.0 + 15.0 + 2.0 + 2 * 0.2),
        compute_s=17.0,
        sync_s=pytest.approx(2 * 0.2),
        serial_s=3.0,
        speedup=pytest.approx((3.0 + 68.0 + 0.2) / 20.4),
        efficiency=pytest.approx((3.0 + 68.0 + 0.2) / 20.4 / 4),
    )


def test_coordinator_share_grows_with_workers():
    # 1 s serial + 8 tasks of 1 s: T(1) = 9 s, T(8) = 2 s (no sync cost)
    p1, p8 = predict([[1.0] * 8], [1, 8], "blocks", FREE, serial_s=1.0)
    assert p1.coordinator_share == pytest.approx(1 / 9)
    assert p8.coordinator_share == pytest.approx(1 / 2)
    (empty,) = predict([], [4], "lpt", FREE)
    assert empty.coordinator_share == 0.0


def test_predictions_follow_the_workers_order():
    out = predict([[1.0] * 8], [8, 1, 2], "lpt", FREE)
    assert [p.workers for p in out] == [8, 1, 2]
    assert [p.wall_s for p in out] == [1.0, 8.0, 4.0]
    assert predict([[1.0]], [], "lpt", FREE) == []


def test_equal_tasks_scale_perfectly_without_sync_cost():
    workers = list(range(1, 65))
    out = predict([[1.0] * 64] * 3, workers, "blocks", FREE)
    speedups = [p.speedup for p in out]
    assert speedups == sorted(speedups)  # monotone (ceil(64/P) never grows)
    for p in out:
        assert p.speedup <= p.workers + 1e-12
        assert p.compute_s == 3 * math.ceil(64 / p.workers)
    assert out[63].speedup == 64.0
    assert out[63].efficiency == 1.0


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("policy", ["blocks", "lpt"])
def test_speedup_bounded_by_workers_and_amdahl(seed, policy):
    rng = np.random.default_rng(seed)
    steps = [list(rng.lognormal(-3, 1, int(rng.integers(1, 80)))) for _ in range(5)]
    sync = SyncCost(a_s=float(rng.uniform(0, 1e-3)), b_s=float(rng.uniform(0, 1e-3)))
    serial = float(rng.uniform(0, 0.5))
    out = predict(steps, range(1, 65), policy, sync, serial_s=serial)
    t1 = out[0].wall_s
    work = sum(map(sum, steps))
    longest = sum(map(max, steps))
    for p in out:
        assert p.wall_s == pytest.approx(p.serial_s + p.compute_s + p.sync_s)
        assert p.compute_s >= max(work / p.workers, longest) - 1e-12
        assert 0 < p.speedup <= p.workers + 1e-9
        assert p.speedup <= t1 / serial + 1e-9
        assert p.efficiency == pytest.approx(p.speedup / p.workers)


def test_sync_cost_gives_an_optimal_worker_count():
    # 10 supersteps of 64 tasks of 10 ms; σ(P) = 30 ms · log2 P: T/10 = 0.64/P + 0.03 log2 P,
    # smallest at P = 16 (0.16 s) among powers of two (8 and 32: 0.17 s)
    sync = SyncCost(a_s=0.0, b_s=0.03)
    out = predict([[0.01] * 64] * 10, [1, 2, 4, 8, 16, 32, 64], "lpt", sync)
    best = max(out, key=lambda p: p.speedup)
    assert best.workers == 16
    assert best.wall_s == pytest.approx(1.6)
    assert out[-1].speedup < out[-2].speedup < best.speedup


def test_lpt_predicts_better_than_blocks_on_a_skewed_workload():
    steps = [[float(i + 1) for i in range(40)]]
    blocks = predict(steps, [4], "blocks", FREE)[0]
    lpt = predict(steps, [4], "lpt", FREE)[0]
    assert blocks.compute_s == 355.0  # the last block: 31 + ... + 40
    assert lpt.compute_s == 205.0  # 820 / 4, balanced exactly
    assert lpt.speedup > blocks.speedup


# --- traces -----------------------------------------------------------------------------


def make_trace(index: int, cpu: list[float], wall: list[float], overhead: float):
    """A 2-worker trace of tasks split as the engine's contiguous blocks split them."""
    blocks = contiguous_blocks(len(cpu), 2)
    busy = [sum(wall[b.start:b.stop]) for b in blocks]
    return SuperstepTrace(
        index=index,
        tasks=len(cpu),
        wall_s=max(busy) + overhead,
        worker_busy_s=busy,
        worker_cpu_s=[sum(cpu[b.start:b.stop]) for b in blocks],
        worker_tasks=[len(b) for b in blocks],
        worker_peak_rss_mb=[100.0, 100.0],
        task_wall_s=wall,
        task_cpu_s=cpu,
        task_worker=[w for w, b in enumerate(blocks) for _ in b],
    )


def test_trace_dict_has_every_field_and_its_own_lists():
    trace = make_trace(0, [0.1, 0.2, 0.3], [0.15, 0.25, 0.35], overhead=0.01)
    d = trace.to_dict()
    assert d == dataclasses.asdict(trace) | {"overhead_s": trace.overhead_s,
                                             "imbalance": trace.imbalance, "sent_bytes": 0,
                                             "received_bytes": 0}
    assert d["overhead_s"] == pytest.approx(0.01)
    d["task_wall_s"].append(9.0)  # the dict's lists are copies
    assert trace.task_wall_s == [0.15, 0.25, 0.35]


def test_task_times_from_traces_and_their_dicts():
    traces = [
        make_trace(0, [0.1, 0.2, 0.3], [0.15, 0.25, 0.35], overhead=0.01),
        make_trace(1, [0.4, 0.5], [0.45, 0.55], overhead=0.03),
        make_trace(2, [0.6, 0.7, 0.8, 0.9], [0.65, 0.75, 0.85, 0.95], overhead=0.02),
    ]
    dicts = json.loads(json.dumps([t.to_dict() for t in traces]))  # as in result.json
    cpu = [[0.1, 0.2, 0.3], [0.4, 0.5], [0.6, 0.7, 0.8, 0.9]]
    assert task_times(traces) == cpu
    assert task_times(dicts, use="cpu") == cpu
    assert task_times(traces, use="wall") == task_times(dicts, use="wall")
    assert task_times(dicts, use="wall")[1] == [0.45, 0.55]
    assert median_overhead(traces) == pytest.approx(0.02)
    assert median_overhead(dicts) == pytest.approx(0.02)
    stripped = [{k: v for k, v in d.items() if k != "overhead_s"} for d in dicts]
    assert median_overhead(stripped) == pytest.approx(0.02)
    inside = sum(t.wall_s for t in traces)
    assert serial_time(inside + 1.5, dicts) == pytest.approx(1.5)
    assert serial_time(inside - 1.0, traces) == 0.0
    assert coordinator_share(inside + 1.5, dicts) == pytest.approx(1.5 / (inside + 1.5))
    assert coordinator_share(inside, traces) == pytest.approx(0.0, abs=1e-12)
    assert coordinator_share(0.0, []) == 0.0
    # end to end: a one-point sync fit and a prediction at the measured worker count
    sync = SyncCost.fit({2: median_overhead(dicts)})
    (p2,) = predict(task_times(dicts, use="wall"), [2], "blocks", sync, serial_s=1.5)
    assert p2.compute_s == pytest.approx(sum(t.wall_s for t in traces) - 0.06)


# --- bad input --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: makespan([1.0], 2, "round-robin"), "unknown policy 'round-robin'"),
        (lambda: predict([[1.0]], [1], "greedy", FREE), "unknown policy 'greedy'"),
        (lambda: makespan([1.0], 0, "lpt"), "at least 1, got 0"),
        (lambda: predict([[1.0]], [4, -2], "lpt", FREE), "at least 1, got -2"),
        (lambda: predict([[1.0]], [2.5], "lpt", FREE), "must be an integer"),
        (lambda: SyncCost(1.0, 0.0).at(0), "at least 1, got 0"),
        (lambda: makespan([1.0, -0.5], 2, "lpt"), r"times\[1\] must be a finite time ≥ 0"),
        (lambda: predict([[1.0], [2.0, -1.0]], [2], "lpt", FREE), r"supersteps\[1\]\[1\]"),
        (lambda: predict([[1.0, math.nan]], [2], "lpt", FREE), r"supersteps\[0\]\[1\]"),
        (lambda: predict([1.0, 2.0], [2], "lpt", FREE), "one list per superstep"),
        (lambda: predict([["a"]], [2], "lpt", FREE), "not a number"),
        (lambda: predict([[1.0]], [2], "lpt", FREE, serial_s=-1.0), "serial_s"),
        (lambda: SyncCost(-1.0, 0.0), "a_s must be"),
        (lambda: SyncCost(0.0, math.inf), "b_s must be"),
        (lambda: SyncCost.fit({}), "at least one"),
        (lambda: SyncCost.fit({0: 0.1}), "at least 1, got 0"),
        (lambda: SyncCost.fit({2: math.nan}), "overhead at P=2"),
        (lambda: task_times([], use="gpu"), "use must be 'cpu' or 'wall'"),
        (lambda: task_times([{"task_wall_s": [1.0]}]), "has no 'task_cpu_s'"),
        (lambda: task_times([{"task_cpu_s": [-1.0]}]), r"task_cpu_s\[0\]"),
        (lambda: task_times([42]), "neither a SuperstepTrace nor a dict"),
        (lambda: median_overhead([]), "no supersteps"),
        (lambda: coordinator_share(-1.0, []), "run_wall_s must be"),
        (lambda: coordinator_share(math.nan, []), "run_wall_s must be"),
        (lambda: median_overhead([None]), "neither a SuperstepTrace nor a dict"),
    ],
)
def test_bad_input_raises_with_a_message(call, message):
    with pytest.raises(ValueError, match=message):
        call()
