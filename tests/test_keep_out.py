"""Keep-out half-spaces in DMOC and the formation's separation rounds (--min-separation)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from conftest import run_cli, script_module

from ocpar.__main__ import main
from ocpar.bsp import open_backend
from ocpar.examples import formation_halo, formation_sphere
from ocpar.examples.formation_point_masses import make as point_masses
from ocpar.formation import FormationOptions, solve_formation
from ocpar.formation.keep_out import exact as exact_separation
from ocpar.formation.keep_out import rounds as keep_out
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, transcription
from ocpar.ocp.dmoc import UNUSED_OFFSET


def sampled_min_distance(positions: np.ndarray, samples: int = 100) -> float:
    """All pairs, ``samples`` sub-steps per interval of the linear interpolant: an
    independent, brute-force minimum distance (positions (n, N+1, d))."""
    s = np.linspace(0.0, 1.0, samples + 1)[:-1, None, None, None]
    start, end = positions[:, :-1], positions[:, 1:]
    fine = ((1 - s) * start[None] + s * end[None])           # (samples, n, N, d)
    fine = fine.transpose(1, 2, 0, 3).reshape(len(positions), -1, positions.shape[-1])
    fine = np.concatenate([fine, positions[:, -1:]], axis=1)  # (n, samples N + 1, d)
    return min(float(np.min(np.linalg.norm(fine[i] - fine[j], axis=-1)))
               for i, j in itertools.combinations(range(len(positions)), 2))


def point_mass_shape(slots: int) -> DmocShape:
    return DmocShape(PointMass(dim=2, mass=1.0), intervals=10, duration=1.0,
                     solver="ipopt" if slots else "newton", keep_out_slots=slots,
                     keep_out_positions=(0, 1) if slots else ())


BOUNDARY = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # rest to rest, (0,0) → (1,0)


def keep_out_params(slots: int, half_spaces: dict[int, tuple[list[float], float, float]],
                    penalty: float = 1e3) -> np.ndarray:
    """Boundary data, then slot 0 of interval k = (normal, b at its start, b at its end)."""
    data = np.zeros((10, slots, 4))
    data[..., 2:] = UNUSED_OFFSET
    for k, (normal, b0, b1) in half_spaces.items():
        data[k, 0] = [*normal, b0, b1]
    return np.concatenate([BOUNDARY, data.ravel(), [penalty]])


def test_unused_slots_leave_the_dmoc_optimum_unchanged():
    free = transcription(point_mass_shape(0)).solve(BOUNDARY)
    kept = transcription(point_mass_shape(3)).solve(keep_out_params(3, {}))
    assert kept.success and kept.cost == pytest.approx(free.cost, rel=1e-10)
    np.testing.assert_allclose(kept.q, free.q, atol=1e-10)
    assert np.all(np.isnan(kept.end_hessian))


def test_moving_half_space_holds_at_the_nodes_and_costs_more():
    """y ≥ 0.1 + 0.1 (t − t_k)/h on intervals 3..6 (moving up by 0.1 over each): the nodes
    meet the offsets at both ends, so the linear path meets the moving plane throughout; the
    unconstrained path (y = 0) does not, so the cost rises."""
    planes = {k: ([0.0, 1.0], 0.1 + 0.1 * (k - 3), 0.2 + 0.1 * (k - 3)) for k in range(3, 7)}
    solution = transcription(point_mass_shape(2)).solve(keep_out_params(2, planes))
    assert solution.success
    for k, (_, b0, b1) in planes.items():
        assert solution.q[k, 1] >= b0 - 1e-9 and solution.q[k + 1, 1] >= b1 - 1e-9
    assert solution.cost > transcription(point_mass_shape(0)).solve(BOUNDARY).cost + 1.0


def focus(agents: int, spacing: float) -> np.ndarray:
    """Node positions (agents, 11, 2) of straight paths from a line y = 0 to the same line
    reversed at y = 10: all of them pass through (0, 5) at t = T/2, a squeezed band."""
    offsets = spacing * (np.arange(agents) - (agents - 1) / 2)
    s = np.linspace(0.0, 1.0, 11)[None, :]
    return np.stack([offsets[:, None] * (1 - 2 * s), np.broadcast_to(10 * s, (agents, 11))],
                    axis=-1)


def test_spread_widens_a_squeezed_band_and_keeps_the_ends():
    positions = focus(9, 1.0)
    assert sampled_min_distance(positions) < 1e-9
    target, iterations = keep_out.spread(positions, 0.5)
    assert iterations < keep_out.SPREAD_ITERATIONS
    assert sampled_min_distance(target) >= 0.5 - 1e-9
    np.testing.assert_array_equal(target[:, [0, -1]], positions[:, [0, -1]])


def _spread_reference(positions: np.ndarray, distance: float) -> tuple[np.ndarray, int]:
    """The spread's Jacobi projection written plainly: every pair and interval measured
    every iteration, the pushes summed by np.add.at (no listing, no incremental update)."""
    target = positions.copy()
    n, nodes, _ = target.shape
    i, j = np.triu_indices(n, 1)
    i, j, k = (np.repeat(i, nodes - 1), np.repeat(j, nodes - 1),
               np.tile(np.arange(nodes - 1), len(i)))
    for iteration in range(keep_out.SPREAD_ITERATIONS):
        start, end = target[i, k] - target[j, k], target[i, k + 1] - target[j, k + 1]
        step = end - start
        s = np.clip(-np.sum(start * step, axis=1) / np.sum(step * step, axis=1), 0, 1)
        rel = (1 - s[:, None]) * start + s[:, None] * end
        gap = np.linalg.norm(rel, axis=1)
        short = gap < distance
        if not np.any(short):
            return target, iteration
        a, b, c, s = i[short], j[short], k[short], s[short]
        direction = rel[short] / gap[short, None]
        amount = (distance * (1 + keep_out.SPREAD_MARGIN) - gap[short]) / 2 \
            / ((1 - s) ** 2 + s ** 2)
        push, count = np.zeros_like(target), np.zeros((n, nodes))
        for node, weight in ((c, amount * (1 - s)), (c + 1, amount * s)):
            np.add.at(push, (a, node), weight[:, None] * direction)
            np.add.at(push, (b, node), -weight[:, None] * direction)
            np.add.at(count, (a, node), 1)
            np.add.at(count, (b, node), 1)
        push[:, [0, -1]] = 0
        target += push / np.maximum(count, 1)[..., None]
    return target, keep_out.SPREAD_ITERATIONS


def test_spread_equals_the_plain_projection():
    """40 agents crossing a grid to a random permutation of it: the spread (pairs listed by
    the spatial index, re-measured only where a node moved, pushes summed by bincount) takes
    the same iterations to the same targets as the projection over all pairs every
    iteration (bit for bit: the same pushes summed in the same order)."""
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(8), np.arange(5)), axis=-1).reshape(-1, 2) * 0.2
    ends = np.stack([grid, grid[rng.permutation(40)]])     # start and end ≥ 0.2 apart
    s = np.linspace(0, 1, 9)[None, :, None]
    positions = (1 - s) * ends[0][:, None] + s * ends[1][:, None]
    positions[:, 1:-1] += rng.normal(0, 0.02, (40, 7, 2))
    target, iterations = keep_out.spread(positions, 0.12)
    expected, expected_iterations = _spread_reference(positions, 0.12)
    assert 10 < iterations == expected_iterations < keep_out.SPREAD_ITERATIONS
    np.testing.assert_allclose(target, expected, rtol=0, atol=1e-12)
    assert np.abs(target - positions).max() > keep_out.SPREAD_LIST_MARGIN * 0.12 / 2

def test_spread_targets_meet_every_half_space():
    """The half-spaces built about the spread targets hold at the targets' nodes: the agents'
    keep-out problems are feasible together (the targets are a witness)."""
    target, _ = keep_out.spread(focus(9, 1.0), 0.5)
    pairs = keep_out.conflicts(target, 0.5)
    entries = np.concatenate([pairs, pairs[:, [1, 0, 2]]])
    data, dropped = keep_out.half_spaces(target, entries, 0.5, 8)
    assert dropped == 0 and len(pairs) > 8
    normal, offsets = data[..., :2], data[..., 2:]
    used = offsets[..., 0] != UNUSED_OFFSET
    assert used.sum() == len(entries)
    for node in (0, 1):
        reach = np.einsum("nksd,nkd->nks", normal, target[:, node:node + 10])
        assert np.all(reach[used] >= offsets[..., node][used] - 1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_trust_region_is_the_box_that_keeps_far_pairs_apart(dim):
    """A node may move h = 0.5 D / (2 √d) along each axis from its target, no more: at most
    0.25 D in all, so pairs 1.5 D apart on the targets stay ≥ D apart."""
    rng = np.random.default_rng(dim)
    target = rng.normal(size=(3, 5, dim))
    data = keep_out.trust_region(target, 2.0)
    assert data.shape == (3, 4, 2 * dim, dim + 2)
    h = 0.5 * 2.0 / (2 * np.sqrt(dim))

    def holds(nodes):
        lhs = np.einsum("nksd,nkd->nks", data[..., :dim], nodes[:, :-1])
        rhs = np.einsum("nksd,nkd->nks", data[..., :dim], nodes[:, 1:])
        return np.all(lhs >= data[..., dim] - 1e-12) and np.all(rhs >= data[..., dim + 1] - 1e-12)

    corner = np.sign(rng.normal(size=(3, 5, dim)))
    assert holds(target) and holds(target + h * corner)
    assert np.linalg.norm(h * corner, axis=-1).max() == pytest.approx(0.25 * 2.0)
    assert not holds(target + 1.01 * h * corner)


def test_newton_refuses_keep_outs():
    """newton asked for explicitly; the default (auto) batches a point mass's keep-outs by
    the convex QP, IPOPT behind it."""
    with pytest.raises(ValueError, match="equalities only"):
        DmocShape(PointMass(dim=2), keep_out_slots=2, keep_out_positions=(0, 1),
                  solver="newton")
    shape = DmocShape(PointMass(dim=2), keep_out_slots=2, keep_out_positions=(0, 1))
    assert shape.chosen_solver == "ipopt"
    nlp = transcription(shape)
    assert nlp.batches and nlp.keep_out_qp is not None
    assert transcription(point_mass_shape(2)).keep_out_qp is None   # ipopt asked for


@pytest.fixture(scope="module")
def twelve():
    """12 point masses, whose unconstrained optimum brings two within 1.37 of each other."""
    problem = point_masses(agents=12)
    return problem, solve_formation(problem), solve_formation(
        problem, options=FormationOptions(min_separation=2.0))


def test_twelve_agents_are_separated_at_all_times(twelve):
    problem, free, kept = twelve
    assert free.separation.distance < 1.5
    assert kept.status == "converged" and kept.separation_rounds > 0
    positions = problem.positions(kept.trajectories)
    assert sampled_min_distance(positions) >= 2.0 - 1e-9
    assert kept.unconstrained_cost == free.total_cost
    assert kept.total_cost >= free.total_cost
    np.testing.assert_array_equal(kept.phi, free.phi)
    assert kept.required_separation == 2.0


@pytest.fixture(scope="module")
def four(twelve):
    """The 12 masses with D = 4: the monolithic NLP, the hierarchical scheme (the exact
    separation, the default) and its separation rounds alone."""
    problem, _, _ = twelve
    return [solve_formation(problem, options=FormationOptions(min_separation=4.0, **extra))
            for extra in ({"mode": "monolithic"}, {}, {"separation": "rounds"})]


def test_the_monolithic_mode_imposes_the_separation_exactly(twelve, four):
    """``--mode monolithic --min-separation 4``: every pair's separating planes in the one NLP
    (added for the pairs that come close): the paths keep 4 apart at all times (sampled
    here), a pair binds at 4, and the cost is the exact optimum's, below the separation
    rounds' alone (whose fixed planes stop short of it, ~1e-4 above)."""
    problem, _, _ = twelve
    exact, _, rounds = four
    assert exact.status == "converged" and exact.verification.passed
    positions = problem.positions(exact.trajectories)
    assert sampled_min_distance(positions) >= 4.0 * (1 - 1e-9)
    assert exact.separation.distance == pytest.approx(4.0, rel=1e-9)
    assert exact.total_cost < rounds.total_cost
    assert rounds.total_cost / exact.total_cost - 1 < 1e-3


def test_the_hierarchical_separation_is_the_monolithic_optimum(twelve, four):
    """``--agents 12 --min-separation 4`` (the issue's case: the rounds alone end 1.04e-4
    above): the clusters of close agents with their planes, the rotation searched, reach the
    monolithic NLP's optimum (solved by other code, :mod:`ocpar.formation.monolithic`); the
    paths keep 4 apart at all times (sampled) and a pair binds at 4."""
    problem, _, _ = twelve
    monolithic, hierarchical, rounds = four
    assert hierarchical.status == "converged" and hierarchical.verification.passed
    assert "exact separation" in hierarchical.message
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-9)
    assert rounds.total_cost / hierarchical.total_cost - 1 > 5e-5
    assert sampled_min_distance(problem.positions(hierarchical.trajectories)) >= 4 * (1 - 1e-9)
    assert hierarchical.separation.distance == pytest.approx(4.0, rel=1e-9)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-7)


@pytest.mark.parametrize("distance", [0.5])
def test_the_exact_separation_turns_the_formation(distance):
    """Six masses on two staggered rows (scripts/separation_exact.py; no mirror symmetry):
    the exact optimum turns the formation by 0.159 rad for D = 0.5, which the rounds alone
    (fixed angles) do not; the hierarchical answer is the monolithic NLP's, angles included."""
    problem = script_module("separation_exact").make_problem(6)
    hierarchical, monolithic, rounds = (
        solve_formation(problem, options=FormationOptions(min_separation=distance, **extra))
        for extra in ({}, {"mode": "monolithic"}, {"separation": "rounds"}))
    assert hierarchical.status == "converged"
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-9)
    assert rounds.total_cost > hierarchical.total_cost * (1 + 1e-3)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-7)
    turn = np.angle(np.mean(np.exp(1j * (hierarchical.phi - rounds.phi))))
    assert turn == pytest.approx(0.159, abs=1e-3)
    assert sampled_min_distance(problem.positions(hierarchical.trajectories)) \
        >= distance * (1 - 1e-9)


def test_angles_it_does_not_search_are_said():
    """On a sphere the formation's rotations are free directions without a shift family: the
    exact separation solves the clusters at the outer solve's angles and the run says it is
    not the optimum (``not_converged``), its paths separated."""
    problem = formation_sphere.make()
    result = solve_formation(problem, options=FormationOptions(min_separation=1.7))
    assert result.status == "not_converged"
    assert "3 free direction(s)" in result.message and "not the optimum" in result.message
    assert sampled_min_distance(problem.positions(result.trajectories)) >= 1.7 * (1 - 1e-9)


def test_a_round_resolves_moved_agents_and_those_near_a_partner():
    """Three agents standing still: 0 and 1 at 1.05 D (within 1.1 D), 2 far; the spread
    moved none: 0 and 1 re-solve, 2 does not; once the spread moves 2, it does too."""
    still = np.array([[0.0, 0.0], [1.05, 0.0], [9.0, 0.0]])[:, None, :].repeat(3, axis=1)
    entries = keep_out.conflicts(still, 1.0)
    entries = np.concatenate([entries, entries[:, [1, 0, 2]]])
    assert keep_out.resolving(still, still, entries, 1.0).tolist() == [0, 1]
    target = still.copy()
    target[2, 1] += 0.01
    assert keep_out.resolving(still, target, entries, 1.0).tolist() == [0, 1, 2]


def test_rounds_resolve_only_agents_near_a_conflict():
    """The 60 masses at D = 0.2 (--separation rounds): each round re-solves a few agents
    (the progress lines say how many), the others keep their unconstrained paths bit for
    bit, and the paths keep D apart (sampled)."""
    problem = point_masses()
    free = solve_formation(problem)
    lines: list[str] = []
    rounds = solve_formation(problem, options=FormationOptions(
        min_separation=0.2, separation="rounds", separation_rounds=3), progress=lines.append)
    resolved = [int(line.split("agents")[1].split()[0]) for line in lines
                if line.startswith("separation round")]
    assert rounds.status == "converged" and len(resolved) == rounds.separation_rounds > 0
    assert 0 < max(resolved) < 20
    kept = np.all(rounds.trajectories == free.trajectories, axis=(1, 2))
    assert np.sum(kept) >= 40   # measured: 48 never moved, 12 re-solved in each round
    assert sampled_min_distance(problem.positions(rounds.trajectories)) >= 0.2 * (1 - 1e-9)


def test_a_cluster_above_the_limit_leaves_the_rounds_answer(twelve, four, monkeypatch):
    """The 12 masses at D = 4 are one cluster of 12: with the limit at 8 the exact
    separation does not run, the rounds' answer (stopped once separated) stands, separated,
    above the monolithic optimum, and the message says its optimality is not proven."""
    problem, _, _ = twelve
    monolithic = four[0]
    monkeypatch.setattr(exact_separation, "MAX_CLUSTER", 8)
    result = solve_formation(problem, options=FormationOptions(min_separation=4.0))
    assert result.status == "converged"
    assert "exact separation not run: a cluster of 12 agents (more than 8)" in result.message
    increase = result.total_cost / result.unconstrained_cost - 1
    assert f"optimality not proven (cost {increase:.3g} relative above" in result.message
    assert sampled_min_distance(problem.positions(result.trajectories)) >= 4 * (1 - 1e-9)
    assert result.total_cost > monolithic.total_cost * (1 + 1e-6)


def test_clusters_are_the_connected_components():
    groups = exact_separation.clusters(7, np.array([[0, 3], [3, 5], [1, 2]]))
    assert [g.tolist() for g in groups] == [[0, 3, 5], [1, 2], [4], [6]]


def test_round_limit_ends_with_its_own_status(twelve, monkeypatch):
    """One round meets D = 4 (the spread targets are separated); with the coordinator's
    spreading cut to one iteration its targets are not, and one round falls short."""
    problem, _, _ = twelve
    monkeypatch.setattr(keep_out, "SPREAD_ITERATIONS", 1)
    result = solve_formation(problem, options=FormationOptions(min_separation=4.0,
                                                                separation_rounds=1))
    assert result.status == "separation_not_met" and result.exit_status == 5
    assert result.separation.distance < 4.0
    assert f"short by {4.0 - result.separation.distance:.3g}" in result.message


@pytest.mark.slow
def test_rounds_are_identical_on_two_dask_workers(twelve):
    problem, _, serial = twelve
    with open_backend("dask", workers=2) as backend:
        parallel = solve_formation(problem, backend, FormationOptions(min_separation=2.0))
    assert parallel.workers == 2
    np.testing.assert_array_equal(parallel.trajectories, serial.trajectories)
    np.testing.assert_array_equal(parallel.agent_costs, serial.agent_costs)
    assert parallel.separation_rounds == serial.separation_rounds


def test_infeasible_separation_is_refused_before_any_solve():
    problem = point_masses(agents=12)
    with pytest.raises(ValueError, match=r"agents \d+ and \d+ are 5.1\d* apart at their "
                                         r"final positions"):
        solve_formation(problem, options=FormationOptions(min_separation=5.3))


def test_infeasible_separation_exits_2_with_one_line():
    proc = run_cli("-m", "ocpar.formation", "--min-separation", "100")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "min separation 100 cannot be met: agents" in lines[0]
    assert "start positions" in lines[0] and proc.stdout == ""


def test_configuration_key_refused_like_the_flag(tmp_path, capsys):
    config = tmp_path / "run.toml"
    out = tmp_path / "out"
    config.write_text(f'scheme = "formation"\nagents = 12\nmin_separation = 5.3\n'
                      f'output = "{out}"\n')
    with pytest.raises(SystemExit) as exit_info:
        main(["run", str(config)])
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip()
    assert line.startswith("ocpar.formation: error: min separation 5.3 cannot be met")
    assert not (out / "result.json").exists()


@pytest.mark.slow
def test_sixty_agents_half_unit_apart():
    """The paper's 60 masses (unconstrained optimum: 0.054 at the closest)."""
    problem = point_masses()
    result = solve_formation(problem, options=FormationOptions(min_separation=0.5))
    assert result.status == "converged"
    assert sampled_min_distance(problem.positions(result.trajectories)) >= 0.5 - 1e-9
    assert result.total_cost >= result.unconstrained_cost
    assert result.unconstrained_cost == solve_formation(problem).total_cost
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic",
                                                                    min_separation=0.5))
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-9)
    assert result.separation.distance == pytest.approx(0.5, rel=1e-9)


@pytest.mark.slow
def test_thirty_masses_at_half_their_spacing():
    """D = half the final spacing 2π 10/30: the rounds without the coordinator's spreading
    (before it) ended 30 rounds at 0.64."""
    problem = point_masses(agents=30)
    result = solve_formation(problem, options=FormationOptions(min_separation=1.0345))
    assert result.status == "converged"
    assert sampled_min_distance(problem.positions(result.trajectories)) >= 1.0345 - 1e-9
    assert result.total_cost >= result.unconstrained_cost


@pytest.mark.slow
def test_thirty_halo_spacecraft_fifty_metres_apart():
    """Positions in km: 50 m is 0.05; attitudes stay free."""
    problem = formation_halo.make(agents=30)
    result = solve_formation(problem, options=FormationOptions(min_separation=0.05))
    assert result.status == "converged" and result.separation_rounds > 0
    assert sampled_min_distance(problem.positions(result.trajectories)) >= 0.05 - 1e-9
    assert result.total_cost >= result.unconstrained_cost
    assert dataclasses.asdict(result.separation)["distance"] >= 0.05 * (1 - 1e-9)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic",
                                                                    min_separation=0.05))
    assert result.total_cost == pytest.approx(monolithic.total_cost, rel=1e-9)
    assert result.separation.distance == pytest.approx(0.05, rel=1e-9)
    np.testing.assert_allclose(result.phi, monolithic.phi, atol=1e-7)


@pytest.mark.slow
def test_a_thousand_masses_five_hundredths_apart():
    """The issue's 1,000 masses at D = 0.05 (unfinished after 600 s before): two rounds, the
    continuous paths verified ≥ D apart, one cluster of 1,000 too large for the exact
    separation, so the rounds' answer with its bound on the gap (28 s of CPU, 2026-12-07)."""
    problem = point_masses(agents=1000)
    result = solve_formation(problem, options=FormationOptions(min_separation=0.05))
    assert result.status == "converged" and result.verification.passed
    assert result.separation.distance >= 0.05 * (1 - 1e-9)
    assert result.separation_rounds <= 3
    assert "a cluster of 1000 agents" in result.message
    assert 0 < result.total_cost / result.unconstrained_cost - 1 < 1e-3
