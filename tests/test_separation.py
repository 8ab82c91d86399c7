"""Closest approach between agents on continuous paths (ocpar.formation.keep_out.separation)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
from conftest import run_cli

from ocpar.examples import formation_halo
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation
from ocpar.formation.keep_out import separation
from ocpar.formation.keep_out.separation import (
    check_separation_feasible,
    close_pairs,
    closest_approach,
    interval_closest,
    positions_at,
)

SAMPLES = 200   # per interval, for the sampled brute force


def sampled(positions: np.ndarray, samples: int = SAMPLES) -> np.ndarray:
    """Positions (n, N samples + 1, dim) on the piecewise-linear paths at a fine time grid."""
    n, _, dim = positions.shape
    s = np.arange(samples) / samples
    step = np.diff(positions, axis=1)[:, :, None]
    fine = positions[:, :-1, None] + s[None, None, :, None] * step
    return np.concatenate([fine.reshape(n, -1, dim), positions[:, -1:]], axis=1)


def brute_force(positions: np.ndarray, duration: float) -> tuple[float, tuple[int, int], float]:
    """All pairs at every sample time: (distance, pair, time) of the smallest, and the samples'
    spacing in time."""
    fine = sampled(positions)
    gaps = np.linalg.norm(fine[:, None] - fine[None, :], axis=-1)      # (n, n, samples)
    gaps[np.arange(len(fine)), np.arange(len(fine))] = np.inf
    i, j, k = np.unravel_index(np.argmin(gaps), gaps.shape)
    pair = (int(min(i, j)), int(max(i, j)))
    return float(gaps[i, j, k]), pair, k * duration / (fine.shape[1] - 1)


def random_paths(rng: np.random.Generator, n: int, intervals: int, dim: int) -> np.ndarray:
    return rng.uniform(0, 10, (n, 1, dim)) + rng.normal(0, 1, (n, intervals + 1, dim)).cumsum(1)


@pytest.mark.parametrize("seed", range(6))
def test_closest_approach_matches_sampled_brute_force(seed):
    rng = np.random.default_rng(seed)
    dim, duration = 2 + seed % 2, 3.0
    positions = random_paths(rng, 25, 8, dim)
    found = closest_approach(positions, duration)
    distance, pair, when = brute_force(positions, duration)
    # sampling can only overestimate; by at most the largest relative step between samples
    speed = np.abs(np.diff(positions, axis=1)).max() * 2 * np.sqrt(dim) / SAMPLES
    assert found.distance <= distance + 1e-12
    assert distance - found.distance <= speed
    assert found.agents == pair
    assert abs(found.time - when) <= duration / 8 / SAMPLES


def test_agents_crossing_between_nodes_meet_at_the_right_time():
    """Nodes far apart (≥ 5√2 at every node), but the paths cross mid-interval 1."""
    line = np.array([-15.0, -5.0, 5.0, 15.0])
    positions = np.stack([np.column_stack([line, np.zeros(4)]),
                          np.column_stack([np.zeros(4), line]),
                          np.column_stack([line + 100, np.zeros(4)])])
    found = closest_approach(positions, duration=6.0)
    assert found.distance == 0.0 and found.agents == (0, 1) and found.time == 3.0
    distance, fraction = interval_closest(positions, np.array([[0, 1]]))
    assert distance[0, 1] == 0.0 and fraction[0, 1] == 0.5
    np.testing.assert_allclose(distance[0, [0, 2]], 5 * np.sqrt(2))   # at the shared node
    np.testing.assert_array_equal(close_pairs(positions, 1.0), [[0, 1]])
    np.testing.assert_allclose(positions_at(positions, 3.0, 6.0)[:2], 0.0)


@pytest.mark.parametrize("seed", range(4))
def test_close_pairs_are_exactly_the_pairs_within_the_radius(seed):
    """Against the exact per-interval minimum of every pair (all pairs) and against sampling."""
    rng = np.random.default_rng(10 + seed)
    positions = random_paths(rng, 60, 6, 2 + seed % 2)
    pairs = np.array(list(itertools.combinations(range(60), 2)))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    fine = sampled(positions)
    sampled_minima = np.linalg.norm(fine[pairs[:, 0]] - fine[pairs[:, 1]], axis=-1).min(axis=1)
    for radius in (0.0, 0.3, 1.0, 3.0):
        found = close_pairs(positions, radius)
        np.testing.assert_array_equal(found, pairs[minima <= radius])
        assert np.all(sampled_minima[minima <= radius] >= minima[minima <= radius])
    exact = closest_approach(positions, 1.0)
    assert exact.distance == minima.min()
    assert exact.agents == tuple(pairs[np.argmin(minima)])


def test_crossing_bundles_match_all_pairs():
    """Two dense bundles (spacing 0.1) pass through each other in opposite directions, offset
    by 0.05: pairs of boxes that overlap in space all the time, told apart by their motion."""
    rng = np.random.default_rng(7)
    grid = 0.1 * np.stack(np.meshgrid(np.arange(20), np.arange(15)), -1).reshape(-1, 2)
    t = np.linspace(-1, 1, 5)[:, None]
    bundle = grid[:, None, :] + 1e-3 * rng.standard_normal((len(grid), 5, 2))
    velocity, offset = np.array([50.0, 0.0]), np.array([0.03, 0.05])
    positions = np.concatenate([bundle + t * velocity, bundle + offset - t * velocity])
    pairs = np.array(list(itertools.combinations(range(len(positions)), 2)))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    for radius in (0.06, 0.12):
        np.testing.assert_array_equal(close_pairs(positions, radius), pairs[minima <= radius])
    found = closest_approach(positions, 1.0)
    assert found.distance == minima.min() and found.agents == tuple(pairs[np.argmin(minima)])


def all_pairs(positions: np.ndarray, duration: float) -> tuple[float, tuple[int, int], float]:
    """The exact all-pairs minimum with the contract's ties (first pair in (i, j) order, then
    the earliest interval): distance, pair, time."""
    pairs = np.array(list(itertools.combinations(range(len(positions)), 2)))
    distance, fraction = interval_closest(positions, pairs)
    row = int(np.argmin(distance.min(axis=1)))
    k = int(np.argmin(distance[row]))
    when = float(k + fraction[row, k]) * duration / (positions.shape[1] - 1)
    return float(distance[row, k]), (int(pairs[row, 0]), int(pairs[row, 1])), when


def bundles(rng: np.random.Generator, n: int, intervals: int, dim: int) -> np.ndarray:
    """Paths in four bundles, each agent its bundle's random walk plus a fixed offset and a
    jitter of 1e-9 … 1e-3; a fan of agents that all pass near one point (a focus: paths that
    cross their neighbours' mid-interval); and exact repeats of some agents (ties at 0)."""
    centre = rng.normal(0, 5, (4, intervals + 1, dim)).cumsum(axis=1)
    size = 10.0 ** rng.uniform(-9, -3, (n, 1, 1))
    positions = (centre[rng.integers(0, 4, n)] + rng.normal(0, 1, (n, 1, dim)) * size
                 + rng.standard_normal((n, intervals + 1, dim)) * size * 1e-3)
    fan = n // 4
    t = np.linspace(0, 1, intervals + 1)[None, :, None]
    spread = rng.uniform(-1, 1, (fan, 1, dim))
    positions[:fan] = spread * (1 - 2 * t) + 1e-7 * rng.standard_normal((fan, 1, dim))
    if rng.random() < 0.5:
        positions[-5:] = positions[rng.integers(0, n - 5, 5)]
    return positions


@pytest.mark.parametrize("seed", range(6))
def test_bundled_and_coincident_paths_match_all_pairs(seed):
    """Near-coincident bundles, a focus and repeated agents (where a bound from node
    neighbours is far above the closest approach, and many pairs tie): the closest approach
    (distance, pair, time, ties) and the close pairs are the all-pairs exact ones."""
    rng = np.random.default_rng(100 + seed)
    positions = bundles(rng, 240, 7, 1 + seed % 3)
    found = closest_approach(positions, 2.0)
    assert (found.distance, found.agents, found.time) == all_pairs(positions, 2.0)
    pairs = np.array(list(itertools.combinations(range(len(positions)), 2)))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    for radius in (0.0, 1e-8, 1e-5, 1e-2):
        np.testing.assert_array_equal(close_pairs(positions, radius), pairs[minima <= radius])


@pytest.mark.parametrize("seed", range(3))
def test_levels_refined_in_small_chunks_give_the_all_pairs_answer(monkeypatch, seed):
    """Each tree level's node pairs refined a few at a time (the chunks of large fleets, here
    5 pairs), whole and cut into spatial cells: the closest approach and the close pairs are
    the all-pairs exact ones."""
    monkeypatch.setattr(separation, "PAIR_CHUNK", 5)
    positions = bundles(np.random.default_rng(500 + seed), 240, 7, 1 + seed % 3)
    expected = all_pairs(positions, 2.0)
    for found in (closest_approach(positions, 2.0), closest_approach(positions, 2.0,
                                                                     InProcess(16))):
        assert (found.distance, found.agents, found.time) == expected
    pairs = np.array(list(itertools.combinations(range(len(positions)), 2)))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    np.testing.assert_array_equal(close_pairs(positions, 1e-2), pairs[minima <= 1e-2])


def test_ten_thousand_agents_with_a_known_closest_pair():
    """Agents on a grid of spacing 10 wander by less than 1 in each coordinate (every pair stays
    ≥ 8 apart) except two that cross a cell's centre line at t = 0.35 T, 0.01 apart (≥ 4 from
    all others); the same pair, distance and time as the all-pairs exact minimum on a subset
    that holds them and their neighbours."""
    rng = np.random.default_rng(3)
    side, intervals = 100, 10
    grid = 10.0 * np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2)
    positions = grid[:, None, :] + rng.uniform(-1, 1, (side * side, intervals + 1, 2))
    a, b = 4321, 777
    tau = np.linspace(0, 1, intervals + 1)[:, None] - 0.35
    centre, offset = grid[a] + 5.0, 0.005 * np.array([1.0, 1.0]) / np.sqrt(2)
    positions[a] = centre + offset + tau * [30.0, 0.0]
    positions[b] = centre - offset + tau * [0.0, 30.0]
    found = closest_approach(positions, duration=2.0)
    assert found.agents == (b, a)
    np.testing.assert_allclose(found.distance, 0.01, rtol=1e-9)
    np.testing.assert_allclose(found.time, 0.7, rtol=1e-9)
    np.testing.assert_array_equal(close_pairs(positions, 3.0), [[b, a]])
    near = np.union1d(np.flatnonzero(np.linalg.norm(grid - grid[a], axis=1) < 40), [b])
    pairs = np.array(list(itertools.combinations(near, 2)))
    minima = interval_closest(positions, pairs)[0].min(axis=1)
    assert found.distance == minima.min() and found.agents == tuple(pairs[np.argmin(minima)])


def test_fewer_than_two_agents_have_no_closest_pair():
    found = closest_approach(np.zeros((1, 3, 2)), 1.0)
    assert found.agents == (-1, -1) and found.distance == np.inf


@pytest.mark.parametrize("bad", [np.zeros((3, 1, 2)), np.zeros((3, 2)), np.full((2, 3, 2), np.nan)])
def test_bad_positions_are_refused(bad):
    with pytest.raises(ValueError, match="positions must"):
        closest_approach(bad, 1.0)


def test_feasibility_names_the_closest_start_or_final_pair():
    start = np.column_stack([np.arange(6.0), np.zeros(6)])
    start[4] = [2.3, 0.0]                       # 0.3 from agent 2 (and 0.7 from agent 3)
    final = np.column_stack([np.zeros(6), np.arange(6.0) * 2])
    check_separation_feasible(start, final, 0.29)
    with pytest.raises(ValueError, match=r"agents 2 and 4 are 0\.3 apart at their start") as exc:
        check_separation_feasible(start, final, 0.5)
    assert "\n" not in str(exc.value)
    far = 10 * start
    final = np.column_stack([np.zeros(6), [0.0, 2.0, 5.0, 9.0, 14.0, 20.0]])
    with pytest.raises(ValueError, match=r"agents 0 and 1 are 2 apart at their final"):
        check_separation_feasible(far, final, 2.5)
    with pytest.raises(ValueError, match="min separation must be"):
        check_separation_feasible(start, final, -1.0)


def test_feasibility_on_ten_thousand_agents():
    grid = np.stack(np.meshgrid(np.arange(100.0), np.arange(100.0)), -1).reshape(-1, 2)
    check_separation_feasible(grid, grid + 1000, 1.0)
    grid[9876] = grid[1234] + [0.0, 0.25]
    with pytest.raises(ValueError, match=r"agents 1234 and 9876 are 0\.25 apart at their start"):
        check_separation_feasible(grid, grid + 1000, 0.5)


def independent_min(problem, result) -> float:
    """All pairs at 200 samples per interval on the positions of the returned paths."""
    fine = sampled(problem.positions(result.trajectories))
    n = len(fine)
    i, j = np.triu_indices(n, 1)
    return float(np.linalg.norm(fine[i] - fine[j], axis=-1).min())


def test_paper_optimum_reports_its_min_separation(tmp_path):
    """The 60 point masses' optimum (keep ordering): paths pass within 0.054 of each other."""
    problem = paper_example()
    result = solve_formation(problem)
    closest = result.separation
    assert closest.distance < 0.1 and closest.agents == (58, 59)
    reference = independent_min(problem, result)
    assert closest.distance <= reference <= closest.distance + 1e-3
    data = json.loads(result.write(tmp_path)[0].read_text())
    assert data["min_separation"] == closest.distance and data["closest_pair"] == [58, 59]
    assert 0 < data["closest_time"] < problem.shape.duration
    assert f"min separation {closest.distance:.6g} (agents 58 and 59" in result.summary()


def test_halo_optimum_reports_its_min_separation():
    """30 rigid spacecraft: separation of the δx part only (km), not of the quaternions."""
    problem = formation_halo.make()
    result = solve_formation(problem)
    assert problem.position_indices == (0, 1, 2)
    reference = independent_min(problem, result)
    assert result.separation.distance <= reference <= result.separation.distance + 1e-4
    assert result.separation.distance < 0.05    # the unconstrained optimum: 21 m


@pytest.mark.parametrize("seed", range(2))
def test_the_intervals_on_mpi_ranks_give_the_same_closest_approach(seed, tmp_path):
    """The closest approach's intervals searched on 2 MPI ranks (a superstep of N interval
    tasks taken from a shared queue, not traced as a step of the run): the serial answer,
    which is the all-pairs one."""
    rng = np.random.default_rng(200 + seed)
    positions = bundles(rng, 240, 7, 2)
    np.save(tmp_path / "positions.npy", positions)
    script = tmp_path / "closest.py"
    script.write_text(
        "import json, sys, numpy as np\n"
        "from ocpar.bsp import open_backend\n"
        "from ocpar.formation.keep_out.separation import closest_approach\n"
        "with open_backend('mpi') as backend:\n"
        "    if backend.is_coordinator:\n"
        f"        found = closest_approach(np.load({str(tmp_path / 'positions.npy')!r}), 2.0,"
        " backend)\n"
        "        print(json.dumps([found.distance, list(found.agents), found.time,"
        " backend.traces]))\n"
        "    else:\n"
        "        backend.serve()\n")
    proc = run_cli(str(script), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    distance, agents, time, traces = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (distance, tuple(agents), time) == all_pairs(positions, 2.0)
    assert traces == []   # the checks are no steps of a run: not traced


class InProcess:
    """``workers`` simulated workers running a superstep's tasks here, one after another."""

    def __init__(self, workers: int) -> None:
        self.workers = workers

    def superstep(self, kernel, tasks, costs=None, record=True):
        return [kernel(task) for task in tasks]


@pytest.mark.parametrize("seed", range(4))
def test_intervals_cut_into_spatial_cells_give_the_same_closest_approach(seed):
    """More workers than intervals: each interval's search cut into ⌈P/N⌉ spatial cells (runs
    of the Z-order, pairs across a boundary found by the cell of their first box); on 8, 16
    and 40 workers the answer is the all-pairs one."""
    positions = bundles(np.random.default_rng(300 + seed), 240, 7, 1 + seed % 3)
    expected = all_pairs(positions, 2.0)
    for workers in (8, 16, 40):
        found = closest_approach(positions, 2.0, InProcess(workers))
        assert (found.distance, found.agents, found.time) == expected, workers


@pytest.mark.parametrize("tree_points", [separation.TREE_POINTS, 0], ids=["tree", "cKDTree"])
@pytest.mark.parametrize("dim", [2, 3])
def test_closest_pair_is_the_all_pairs_minimum(monkeypatch, tree_points, dim):
    monkeypatch.setattr(separation, "TREE_POINTS", tree_points)
    rng = np.random.default_rng(dim)
    for points in (rng.uniform(size=(2, dim)), rng.uniform(size=(700, dim)),
                   np.repeat(rng.uniform(size=(40, dim)), [1] * 39 + [2], axis=0),
                   np.column_stack([np.arange(300.0) ** 1.5] + [np.zeros(300)] * (dim - 1))):
        gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
        gaps[np.diag_indices(len(points))] = np.inf
        distance, (i, j) = separation.closest_pair(points)
        assert distance == gaps.min() and i < j and gaps[i, j] == distance
