"""Resident agents (ocpar.bsp.resident): the formation's solutions stay on the workers, and
the run is bit for bit the same whatever holds them: serial, mpirun -n 2 and -n 8, Dask with
1, 2 or 3 workers, a Dask worker killed between supersteps, a run resumed from its checkpoint."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
from conftest import run_cli
from test_checkpoint import Crash, crash_after

import ocpar
from ocpar.bsp import open_backend
from ocpar.bsp.journal import Journal
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation
from ocpar.formation.hierarchical import OuterObjective
from ocpar.result_files import load_trace

AGENTS = 24


@pytest.fixture(scope="module")
def serial_run():
    return solve_formation(paper_example(AGENTS))


def assert_bitwise(result, reference) -> None:
    assert result.total_cost == reference.total_cost
    assert np.array_equal(result.phi, reference.phi)
    assert np.array_equal(result.agent_costs, reference.agent_costs)
    assert np.array_equal(result.trajectories, reference.trajectories)
    assert np.array_equal(result.controls, reference.controls)
    assert result.supersteps == reference.supersteps


def serial_reference(problem, angles) -> tuple[list[np.ndarray], np.ndarray]:
    """The outer gradient at each of ``angles`` and the paths at the last, served serially."""
    with open_backend("serial") as serial:
        reference = OuterObjective(problem, serial)
        gradients = [reference.gradient(phi) for phi in angles]
        return gradients, np.asarray(reference.solutions(angles[-1]).column("q"))


def test_a_superstep_moves_outcomes_and_the_paths_come_once(serial_run):
    """Every superstep but the last returns outcomes (no paths); the last gathers the
    paths, once."""
    with open_backend("serial") as backend:
        objective = OuterObjective(paper_example(AGENTS), backend)
        phi = serial_run.phi
        outcomes = objective.outcomes(phi)
        assert set(outcomes.fields) == {"cost", "end_gradient", "end_hessian", "success",
                                        "status", "attempts"}
        assert np.asarray(outcomes.column("end_hessian")).shape == (AGENTS, 2, 2)
        solutions = objective.solutions(phi)
        assert objective.solutions(phi) is solutions and len(backend.traces) == 2
        assert np.asarray(solutions.column("q")).shape == (AGENTS, 11, 2)
        assert np.array_equal(solutions.column("cost"), outcomes.column("cost"))


@pytest.mark.parametrize("workers", [pytest.param(1, marks=pytest.mark.slow), 2,
                                     pytest.param(3, marks=pytest.mark.slow)])
def test_dask_workers_give_the_serial_run_bit_for_bit(serial_run, workers):
    with open_backend("dask", workers=workers) as backend:
        result = solve_formation(paper_example(AGENTS), backend)
    assert_bitwise(result, serial_run)
    assert all(t.sent_bytes > 0 and t.received_bytes > 0 for t in result.trace)


@pytest.mark.parametrize("ranks", [2, 8])   # 8: oversubscribed, 3 agents per rank
def test_mpirun_gives_the_serial_run_bit_for_bit(serial_run, tmp_path, ranks):
    """On 2 ranks with fixed blocks (no states in a superstep's replies: the bytes are
    checked), on 8 with blocks moved by the measured costs (the timing noise of ~0.1 ms
    solves moves some)."""
    blocks = "fixed" if ranks == 2 else "measured"
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), "--resident-blocks",
                   blocks, "--quiet", "--output", str(tmp_path), mpi_ranks=ranks)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["workers"] == ranks
    assert data["total_cost"] == serial_run.total_cost
    assert data["phi"] == serial_run.phi.tolist()
    assert ocpar.load(tmp_path).dataset["cost"].values.tolist() == \
        serial_run.agent_costs.tolist()
    assert data["supersteps"] == serial_run.supersteps
    if ranks > 2:
        return   # 3 agents per rank: each message's framing outweighs its agents' numbers
    # the transport counts the bytes: a superstep's reply carries a few numbers per agent,
    # never the paths (rank 1's 12 agents' node positions alone are 12 * 11 * 2 doubles)
    first, *later = load_trace(tmp_path)
    assert all(0 < t["received_bytes"] < 12 * 11 * 2 * 8 for t in [first, *later])
    assert all(first["sent_bytes"] > t["sent_bytes"] > 0 for t in later)  # the boundary data


def test_a_resumed_run_rebuilds_the_workers_states_from_the_history(serial_run, tmp_path):
    """Killed after 3 supersteps and resumed: the journal serves them, the workers hold no
    states, and the next superstep replays each agent's three tasks to rebuild them."""
    backend = open_backend("serial")
    backend.journal = Journal(tmp_path, {"run": "formation"}, resume=False)
    crash_after(backend, 3)
    with pytest.raises(Crash):
        solve_formation(paper_example(AGENTS), backend)
    resumed = open_backend("serial")
    resumed.journal = Journal(tmp_path, {"run": "formation"}, resume=True)
    calls = []
    run = resumed._run_chunks
    resumed._run_chunks = lambda name, chunks: calls.append(chunks) or run(name, chunks)
    result = solve_formation(paper_example(AGENTS), resumed)
    assert_bitwise(result, serial_run)
    rebuilt = [item for chunks in calls for chunk in chunks for item in chunk
               if getattr(item, "history", None) is not None]
    assert len(rebuilt) == 1 and len(rebuilt[0].history) == 3
    assert len(rebuilt[0].rebuild) == AGENTS


def test_a_killed_dask_worker_s_agents_are_rebuilt_on_a_live_one(serial_run):
    """Two Dask workers; one is killed (SIGKILL) between supersteps: its agents' states are
    rebuilt on the other from their history, and every value and path is the serial one."""
    problem = paper_example(AGENTS)
    angles = [serial_run.phi + delta for delta in (0.03, 0.02, 0.01, 0.0)]
    expected, paths = serial_reference(problem, angles)
    with open_backend("dask", workers=2) as backend:
        objective = OuterObjective(problem, backend)
        got = [objective.gradient(phi) for phi in angles[:2]]
        victim = backend.client.run(os.getpid)[backend.addresses[1]]
        os.kill(victim, signal.SIGKILL)
        time.sleep(0.5)
        got += [objective.gradient(phi) for phi in angles[2:]]
        # its chunk ran again on a live worker (the one left, or the nanny's restarted one
        # if it registered in time)
        assert backend.lost_chunks >= 1 and victim not in backend.client.run(os.getpid).values()
        assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))
        assert np.array_equal(np.asarray(objective.solutions(angles[-1]).column("q")), paths)


def test_closing_frees_the_workers_states():
    from ocpar.bsp import resident

    with open_backend("serial") as backend:
        objective = OuterObjective(paper_example(4), backend)
        objective.value(paper_example(4).initial_phi())
        assert any(key == objective._agents.key for key, _ in resident._BLOCKS)
        objective.close()
        assert not any(key == objective._agents.key for key, _ in resident._BLOCKS)


def test_chunks_that_land_on_the_other_dask_worker_are_replayed_there(serial_run):
    """``tasks`` dispatch through the scheduler, which may run a chunk on another worker than
    its slot's (work stealing, a busy worker): that worker lacks the slot's states and the
    superstep sends a second round of chunks with their history. Here every superstep after
    the first sends slot w's chunk to the other worker. The second round must get its own
    results, not the first round's (they shared task keys once: 'slot 0 still lacks states
    after its history was sent' on a busy shared cluster), and the run is the serial one."""
    with open_backend("dask", workers=2, dispatch="tasks") as backend:
        step, rounds = backend._resident_superstep, []

        def swapped(*args):
            result = step(*args)
            backend.addresses.reverse()
            return result

        run = backend._run_chunks
        backend._resident_superstep = swapped
        backend._run_chunks = lambda name, chunks: rounds.append(chunks) or run(name, chunks)
        result = solve_formation(paper_example(AGENTS), backend)
    assert_bitwise(result, serial_run)
    replayed = [item for chunks in rounds for chunk in chunks for item in chunk
                if getattr(item, "history", None) is not None]
    assert len(replayed) >= 2 * (result.supersteps - 2)
