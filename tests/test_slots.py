"""Formations onto given slots (k = 0: only the assignment is free): the assignment against
scipy's linear_sum_assignment on the full table of inner costs, CAPT's separation, more
slots than agents, the checks, and the same result on every backend."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import run_cli
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import pdist

import ocpar
from ocpar.bsp import open_backend
from ocpar.examples.formation_slots import make
from ocpar.formation import DmocShape, FormationOptions, FormationProblem, Slots, solve_formation
from ocpar.formation.plot import plot_formation
from ocpar.models import PointMass
from ocpar.ocp import solve_tasks
from ocpar.result_files import write_result


def full_table_optimum(problem) -> tuple[float, np.ndarray]:
    """min Σ_i Ĵ_i(slot σ(i)) by linear_sum_assignment on the whole n × m table, each entry
    an inner solve here: (total cost, slot per agent)."""
    n, m = problem.agents, problem.curve.count
    agents, slots = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
    sols = solve_tasks(problem.tasks_for(agents, slots.astype(float)))
    table = np.asarray(sols.column("cost"), float).reshape(n, m)
    rows, cols = linear_sum_assignment(table)
    return float(table[rows, cols].sum()), cols


@pytest.mark.parametrize(("agents", "slots"), [(200, 200), (60, 100)])
def test_the_assignment_is_the_full_tables_optimum(agents, slots):
    """Over each agent's candidate slots (of 200, and of 100 for 60 agents) the assignment
    equals scipy's on the full table of inner costs, and the trajectories end there."""
    problem = make(agents=agents, slots=slots)
    result = solve_formation(problem)
    expected, assignment = full_table_optimum(problem)
    assert result.status == "converged" and result.feasible_set == "discrete"
    assert result.total_cost == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(result.phi, assignment)
    np.testing.assert_allclose(result.trajectories[:, -1], problem.curve.at(assignment),
                               atol=1e-12)
    assert result.coupling_residual == 0
    assert "the optimal assignment over each agent's" in result.message


def test_capt_the_paths_keep_the_nearer_of_the_start_and_slot_spacings():
    """Identical double integrators from rest to rest: the optimal assignment is CAPT's
    (min Σ|Δ|², the squared-distance assignment), and its straight synchronised paths keep
    every pair at least min(closest starts, closest slots) apart on the continuous paths."""
    problem = make(agents=200)
    result = solve_formation(problem)
    starts = problem.positions(problem.starts)
    squared = ((starts[:, None, :] - problem.curve.points[None]) ** 2).sum(axis=2)
    np.testing.assert_array_equal(result.phi, linear_sum_assignment(squared)[1])
    bound = min(pdist(starts).min(), pdist(problem.curve.points).min())
    assert result.separation.distance >= bound * (1 - 1e-9)


def test_few_candidates_widen_until_every_agent_has_a_slot():
    """With 2 candidates per agent the candidate pairs admit no assignment of all 200 agents;
    the candidates double until they do, and the result says how many it took."""
    result = solve_formation(make(agents=200), options=FormationOptions(slot_candidates=2))
    assert result.status == "converged" and result.coupling_residual == 0
    taken = int(result.message.split("over each agent's ")[1].split()[0])
    assert taken > 2 and taken % 2 == 0


@pytest.mark.parametrize(("points", "message"), [
    (np.zeros((0, 2)), "shape"),
    (np.ones((3, 4)), "shape"),
    ([[0.0, 0.0], [np.nan, 1.0], [2.0, 2.0]], "finite"),
    ([[0.0, 0.0], [1.0, 1.0], [0.0, 0.0]], "slots 0 and 2 coincide"),
    ("lattice", "array of numbers"),
])
def test_malformed_slots_are_one_error_naming_the_field(points, message):
    with pytest.raises(ValueError, match=r"^curve: ") as info:
        Slots(points)
    assert message in str(info.value)


def test_fewer_slots_than_agents_and_the_monolithic_mode_are_refused():
    problem = make(agents=10)
    with pytest.raises(ValueError, match=r"^curve: 9 slots for 10 agents"):
        dataclasses.replace(problem, curve=Slots(problem.curve.points[:9]))
    with pytest.raises(ValueError, match="slots apply to the hierarchical mode only"):
        solve_formation(problem, options=FormationOptions(mode="monolithic"))
    with pytest.raises(ValueError, match="ordering 'optimal' does nothing onto slots"):
        solve_formation(problem, options=FormationOptions(ordering="optimal"))


def test_slots_on_mpi_and_dask_are_bitwise_the_serial_result(tmp_path):
    serial = solve_formation(make(agents=200))
    with open_backend("dask", workers=2) as backend:
        dask = solve_formation(make(agents=200), backend)
    assert dask.total_cost == serial.total_cost
    np.testing.assert_array_equal(dask.trajectories, serial.trajectories)
    proc = run_cli("-m", "ocpar.formation", "--problem", "ocpar.examples.formation_slots:make",
                   "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    mpi = json.loads((tmp_path / "result.json").read_text())
    assert mpi["total_cost"] == serial.total_cost and mpi["phi"] == serial.phi.tolist()
    assert ocpar.load(tmp_path).dataset["configuration"].values.tolist() == \
        serial.trajectories.tolist()


@pytest.mark.slow
def test_a_thousand_masses_onto_a_thousand_slots():
    """The issue's size: the assignment over 32 candidates per agent equals
    linear_sum_assignment on the full 1000 × 1000 table (10⁶ inner solves)."""
    problem = make(agents=1000)
    result = solve_formation(problem)
    expected, assignment = full_table_optimum(problem)
    assert result.total_cost == pytest.approx(expected, rel=1e-12)
    np.testing.assert_array_equal(result.phi, assignment)


def test_slots_no_agent_assignment_can_reach_fail_with_their_files_and_picture(tmp_path):
    """Two thrust-limited masses (|u_i| ≤ 4 reaches 1 in t = 1 from rest to rest), three
    slots of which only one lies within either's reach: no feasible assignment. The run fails
    saying so, and its files and picture are written (no slot: NaN end points)."""
    problem = FormationProblem(
        name="unreachable",
        shape=DmocShape(PointMass(dim=2, mass=1.0), intervals=10, duration=1.0,
                        control_bounds=((-4.0, 4.0), (-4.0, 4.0))),
        curve=Slots(np.array([[0.5, 0.0], [100.0, 0.0], [200.0, 0.0]])),
        starts=np.array([[0.0, 0.0], [1.0, 0.0]]))
    result = solve_formation(problem)
    assert result.status == "failed" and np.isnan(result.phi).all()
    assert "no assignment of every agent to a slot it can reach" in result.message
    assert np.isnan(problem.final_positions(result.phi)).all()
    plot_formation(problem, result, tmp_path / "formation.png")
    write_result(result, tmp_path)
    summary = json.loads((tmp_path / "result.json").read_text())
    assert summary["status"] == "failed" and summary["total_cost"] is None
    assert (tmp_path / "formation.png").stat().st_size > 0
