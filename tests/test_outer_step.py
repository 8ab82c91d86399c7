"""The formation's outer step on the workers (ocpar.formation.outer_step, the engine's
reductions in ocpar.bsp.resident): the sums the workers return are the coordinator-side
arithmetic's, bit for bit where every agent is its own unit, and the same bits on any number
of workers of either backend where units hold several agents; a superstep's replies carry a
few numbers per unit, not an outcome per agent."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from ocpar.bsp import open_backend
from ocpar.bsp.backend import Backend
from ocpar.bsp.columns import to_columns
from ocpar.bsp.kernel import run_packed_chunk
from ocpar.bsp.partition import MIN_UNITS, unit_blocks, unit_size
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import DmocShape, Ellipse, EqualArcLength, FormationProblem, solve_formation
from ocpar.formation.hierarchical import OuterObjective
from ocpar.models import PointMass

#: Enough agents for units of 4 (4,100 // 1024), not a multiple of 4: the last unit is short.
MANY = 4_100


def coordinator_terms(objective: OuterObjective, family, theta: float) -> tuple[float, ...]:
    """J, dJ/dθ, Σ|g φ′| and d²J/dθ² the coordinator-side way: every agent's outcome
    gathered, the terms summed over all agents at once."""
    phi, along, bend = family.angles(theta)
    g = objective.gradient(phi)
    return (objective.value(phi), float(np.sum(g * along)), float(np.sum(np.abs(g * along))),
            float(np.sum(objective.hessian_diagonal(phi) * along**2 + g * bend)))


def equal_arc_length(n: int) -> FormationProblem:
    """n planar point masses on a line onto an ellipse, equally spaced in arc length: the
    shift's map inverts the arc length, agent by agent."""
    starts = np.column_stack([np.linspace(-6.0, 6.0, n), np.full(n, -5.0)])
    return FormationProblem(name="arc", shape=DmocShape(PointMass(dim=2), 10, 2.0),
                            curve=Ellipse(semi_axes=(3.0, 1.5), center=np.zeros(2)),
                            starts=starts, coupling=EqualArcLength())


@pytest.mark.parametrize("problem", [paper_example(60), equal_arc_length(9)],
                         ids=["circle", "equal-arc-length"])
def test_worker_sums_are_the_coordinator_arithmetic_bit_for_bit(problem):
    """Below 2 MIN_UNITS agents every agent is its own unit: the workers' sums are the
    coordinator-side sums of the same per-agent terms, bit for bit, at several shifts."""
    assert unit_size(problem.agents) == 1
    family = problem.coupling.family(problem.initial_phi(), problem.curve)
    with open_backend("serial") as serial:
        shifted, plain = OuterObjective(problem, serial), OuterObjective(problem, serial)
        for theta in (0.0, 0.013, -0.2):
            at = shifted.shifted(family, theta)
            assert (at.value, at.slope, at.scale, at.curvature) == \
                coordinator_terms(plain, family, theta)
        # the solutions left on the workers are those at the last shift's angles
        phi = family.angles(-0.2)[0]
        assert np.array_equal(shifted.last_phi, phi)
        assert np.array_equal(np.asarray(shifted.solutions(phi).column("q")),
                              np.asarray(plain.solutions(phi).column("q")))


class SimulatedWorkers(Backend):
    """P workers simulated in this process, one after the other: the engine's blocks,
    units and reductions as on P real ones (their states apart by slot)."""

    name = "simulated"

    def _run_chunks(self, name, chunks):
        return [run_packed_chunk(name, to_columns(chunk)) for chunk in chunks]


@pytest.fixture(scope="module")
def many_serial():
    return solve_formation(paper_example(MANY))


def assert_same(result, reference) -> None:
    assert result.total_cost == reference.total_cost
    assert np.array_equal(result.phi, reference.phi)
    assert np.array_equal(result.trajectories, reference.trajectories)
    assert np.array_equal(result.agent_costs, reference.agent_costs)


@pytest.mark.parametrize("workers", [2, 3, 16])
def test_the_same_bits_on_any_number_of_workers(many_serial, workers):
    """Units of 4 agents (the last of 0): the blocks of 2, 3 and 16 workers cut the agents
    differently, always between units, and the run is the serial one bit for bit (also
    with blocks moved by measured costs)."""
    backend = SimulatedWorkers(workers)
    blocks = unit_blocks(MANY, workers)
    assert all(b.start % unit_size(MANY) == 0 for b in blocks) and blocks[-1].stop == MANY
    assert_same(solve_formation(paper_example(MANY), backend), many_serial)


def test_mpirun_ranks_and_dask_workers_give_the_serial_bits(many_serial, tmp_path):
    """The same on real processes: mpirun -n 2 and -n 4, and 2 Dask workers. Each reply of
    a solve superstep after the first carries the units' sums: under 40 bytes per agent of
    its block, where an outcome per agent would be ~60 (cost, gradient, Hessian block,
    status)."""
    for ranks in (2, 4):
        out = tmp_path / f"mpi{ranks}"
        proc = run_cli("-m", "ocpar.formation", "--agents", str(MANY), "--quiet",
                       "--resident-blocks", "fixed", "--output", str(out), mpi_ranks=ranks)
        assert proc.returncode == 0, proc.stderr
        data = json.loads((out / "result.json").read_text())
        assert data["total_cost"] == many_serial.total_cost
        assert data["phi"] == many_serial.phi.tolist()
        solves = json.loads((out / "trace.json").read_text())[1:]
        per_agent = [r / t for s in solves
                     for r, t in zip(s["worker_received_bytes"][1:], s["worker_tasks"][1:],
                                     strict=True)]
        assert max(per_agent) < 40, per_agent
    with open_backend("dask", workers=2) as dask:
        assert_same(solve_formation(paper_example(MANY), dask), many_serial)


def test_units_depend_on_the_number_of_agents_alone():
    assert [unit_size(n) for n in (1, 60, 2 * MIN_UNITS - 1, 2 * MIN_UNITS, 10_000,
                                   10**6)] == [1, 1, 1, 2, 9, 256]
    for workers in (1, 2, 7):
        blocks = unit_blocks(10_001, workers)
        assert [b.start % 9 for b in blocks] == [0] * workers
        assert sum(len(b) for b in blocks) == 10_001
