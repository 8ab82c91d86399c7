"""Resident agents' blocks follow their measured costs (ocpar.bsp.resident): on a mixed fleet
whose expensive (thrust-limited) agents come first, the blocks move between supersteps, the
moved agents' states travel in the replies and the next chunks (never a history replay), and
every result is the serial run's bit for bit: Dask with 2 and 3 workers, mpirun -n 2."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest
from conftest import run_cli
from test_resident import assert_bitwise, serial_reference

import ocpar
from ocpar.bsp import open_backend
from ocpar.bsp.partition import block_loads, contiguous_blocks, unit_blocks
from ocpar.bsp.resident import (
    MOVE_SECONDS,
    MOVE_SECONDS_PER_BYTE,
    ResidentChunk,
    _nbytes,
)
from ocpar.examples.formation_mixed_fleet import make
from ocpar.formation import solve_formation
from ocpar.formation.hierarchical import OuterObjective
from ocpar.ocp.endpoint_agents import solve_agents
from ocpar.result_files import load_trace

AGENTS = 480
FACTORY = "ocpar.examples.formation_mixed_fleet:make"


def skewed():
    """The first half thrust-limited (~5x the cost of the unlimited second half)."""
    return make(agents=AGENTS, unlimited=AGENTS // 2)


@pytest.fixture(scope="module")
def serial_run():
    return solve_formation(skewed())


def recording(backend) -> list[ResidentChunk]:
    """Record every resident chunk item ``backend`` sends from now on (not the other
    supersteps' tasks, e.g. the verification's)."""
    items: list[ResidentChunk] = []
    run = backend._run_chunks

    def record(name, chunks):
        items.extend(item for chunk in chunks for item in chunk
                     if isinstance(item, ResidentChunk))
        return run(name, chunks)

    backend._run_chunks = record
    return items


def test_the_move_rule_on_given_estimates():
    """Equal estimates: no move; the first half 5x dearer: the boundary moves towards it;
    a saving smaller than the states' moving cost, a tolerance of None, an imbalance within
    the tolerance plus the timings' noise, or one worker: no move."""
    with open_backend("serial") as backend:
        agents = backend.resident(solve_agents, 100)
        assert agents.rebalanced() == [range(100)]  # one worker, no estimates
        agents.blocks = contiguous_blocks(100, 2)
        agents.costs = np.full(100, 1e-3)
        agents.state_bytes = 1000.0
        assert agents.rebalanced() == agents.blocks
        agents.costs[:50] *= 5
        assert agents.rebalanced() == [range(0, 30), range(30, 100)]
        # moving 20 agents' states must cost less than the 0.1 s a superstep saves
        agents.state_bytes = (0.1 - MOVE_SECONDS) / (20 * MOVE_SECONDS_PER_BYTE) * 1.01
        assert agents.rebalanced() == agents.blocks
        agents.state_bytes = (0.1 - MOVE_SECONDS) / (20 * MOVE_SECONDS_PER_BYTE) * 0.99
        assert agents.rebalanced() == [range(0, 30), range(30, 100)]
        # states of no size: a saving (1/3 of the larger load) below a move's fixed cost
        agents.state_bytes = 0.0
        for scale, moves in ((0.9, False), (1.1, True)):
            agents.costs = np.where(np.arange(100) < 50, 5.0, 1.0) * scale * MOVE_SECONDS / 100
            assert (agents.rebalanced() != agents.blocks) == moves
        agents.state_bytes = 1000.0
        agents.costs = np.where(np.arange(100) < 50, 5e-3, 1e-3)
        backend.resident_tolerance = None
        assert agents.rebalanced() == agents.blocks
        backend.resident_tolerance = 5.0  # imbalance 5/3 is within 1 + 5
        assert agents.rebalanced() == agents.blocks
        backend.resident_tolerance = 0.05
        assert agents.rebalanced() != agents.blocks
        agents.noise = 0.7  # the timings stray by as much as the imbalance: no move
        assert agents.rebalanced() == agents.blocks



def test_the_move_rule_near_its_fixed_cost_is_the_rule_written_out():
    """Random imbalances whose excess over the mean load lies around a move's fixed cost (where
    :meth:`~ocpar.bsp.resident.ResidentSet.rebalanced` skips proposing blocks that cannot
    pay): its answer is the docstring's rule computed here in full, blocks proposed always."""
    rng = np.random.default_rng(7)
    with open_backend("serial") as backend:
        agents = backend.resident(solve_agents, 100)
        agents.blocks, agents.state_bytes = contiguous_blocks(100, 3), 0.0
        moves = 0
        for _ in range(300):
            heavier = np.where(np.arange(100) < 34, rng.uniform(1.0, 3.0), 1.0)  # block 0's
            agents.costs = rng.uniform(0.5, 1.5, 100) * heavier * MOVE_SECONDS / 30
            loads = block_loads(agents.costs, agents.blocks)
            proposed = unit_blocks(100, 3, agents.costs)
            pays = (loads.max() > (1.05 + agents.noise) * loads.mean()
                    and loads.max() - block_loads(agents.costs, proposed).max() > MOVE_SECONDS)
            assert agents.rebalanced() == (proposed if pays else agents.blocks)
            moves += pays
        assert 0 < moves < 300

def test_dask_blocks_follow_the_costs_and_every_result_is_the_serial_one(serial_run):
    """Dask, 2 workers: with fixed blocks nothing moves; with measured ones worker 0 (the
    expensive half) gives agents away, their states come with the chunks (counted in the
    traces' bytes), nothing is replayed, and the run, its collected paths included, is the
    serial one bit for bit; so are an objective's gradients over more supersteps."""
    problem = skewed()
    angles = [serial_run.phi + delta for delta in (0.05, 0.04, 0.03, 0.02, 0.01, 0.0)]
    with open_backend("serial") as serial:
        reference = OuterObjective(problem, serial)
        expected = [reference.gradient(phi) for phi in angles]
        paths = np.asarray(reference.solutions(angles[-1]).column("q"))
    with open_backend("dask", workers=2) as backend:
        backend.resident_tolerance = None
        fixed = solve_formation(problem, backend)
        assert all(t.worker_tasks == [240, 240] for t in fixed.trace)
        backend.resident_tolerance = 0.05
        items = recording(backend)
        result = solve_formation(problem, backend)
        objective = OuterObjective(problem, backend)
        got = [objective.gradient(phi) for phi in angles]
        solutions = objective.solutions(angles[-1])
        moved = objective._agents.moved
    assert_bitwise(fixed, serial_run)
    assert_bitwise(result, serial_run)
    assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))
    assert np.array_equal(np.asarray(solutions.column("q")), paths)
    tasks = [t.worker_tasks for t in result.trace]
    assert tasks[0] == [240, 240] and any(t[0] < 240 for t in tasks), tasks
    assert moved > 0
    assert not any(item.history for item in items)
    run = [item for item in items if item.key == items[0].key]  # solve_formation's set
    assert any(item.export is not None for item in run)
    # the first superstep with new blocks carries the moved states, and the trace counts
    # their bytes: it sent that much more than the superstep before (same tasks' sizes)
    first = next(k for k, t in enumerate(tasks) if t != tasks[0])
    carried = sum(_nbytes(item.imports) for item in run
                  if item.version == first and item.imports is not None)
    assert first >= 2 and carried > 0
    trace = result.trace
    assert trace[first].sent_bytes - trace[first - 1].sent_bytes > 0.9 * carried


def test_mpirun_blocks_follow_the_costs_and_every_result_is_the_serial_one(serial_run,
                                                                          tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--problem", FACTORY, "--problem-arg",
                   f"agents={AGENTS}", "--problem-arg", f"unlimited={AGENTS // 2}", "--quiet",
                   "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["workers"] == 2
    assert data["total_cost"] == serial_run.total_cost
    assert data["phi"] == serial_run.phi.tolist()
    arrays = ocpar.load(tmp_path).dataset
    assert arrays["cost"].values.tolist() == serial_run.agent_costs.tolist()
    assert arrays["configuration"].values.tolist() == serial_run.trajectories.tolist()
    assert data["supersteps"] == serial_run.supersteps
    tasks = [t["worker_tasks"] for t in load_trace(tmp_path)]
    assert tasks[0] == [240, 240] and any(t[0] < 240 for t in tasks), tasks


def test_a_worker_killed_while_states_move_loses_nothing():
    """Dask, 2 workers: worker 1 is killed (SIGKILL) right after a superstep that returned
    moving agents' states: those reach the live worker with the next chunk, the dead
    worker's other agents are rebuilt from their history, and every value and path is the
    serial one."""
    problem = skewed()
    angles = [problem.initial_phi() + delta for delta in (0.0, 0.01, 0.02, 0.03, 0.04)]
    expected, paths = serial_reference(problem, angles)
    with open_backend("dask", workers=2) as backend:
        objective = OuterObjective(problem, backend)
        agents = objective._agents
        got = []
        victim = None
        for phi in angles:
            got.append(objective.gradient(phi))
            if agents._moving is not None and victim is None:
                victim = backend.client.run(os.getpid)[backend.addresses[1]]
                os.kill(victim, signal.SIGKILL)
                time.sleep(0.5)
        # its chunk ran again on a live worker (the one left, or the nanny's restarted one
        # if it registered in time)
        assert victim is not None and backend.lost_chunks >= 1 and agents.moved > 0
        solutions = objective.solutions(angles[-1])
    assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))
    assert np.array_equal(np.asarray(solutions.column("q")), paths)


def test_three_dask_workers_move_blocks_and_give_the_serial_run(serial_run):
    """Dask, 3 workers: the expensive first half fills the first block and half the second,
    so both boundaries move towards the start; the run is the serial one bit for bit."""
    with open_backend("dask", workers=3) as backend:
        result = solve_formation(skewed(), backend)
    assert_bitwise(result, serial_run)
    tasks = [t.worker_tasks for t in result.trace]
    assert tasks[0] == [160, 160, 160], tasks
    assert any(t[0] < 160 and sum(t) == AGENTS for t in tasks), tasks
