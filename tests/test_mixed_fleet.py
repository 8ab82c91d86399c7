"""A mixed fleet with thrust limits (``ocpar.examples.formation_mixed_fleet``): 12 planar point
masses of masses 0.5, 1 and 1.5 onto a circle, each with a box or a norm thrust limit that
binds at the optimum. The hierarchical scheme (outer Newton on the inner sensitivities from
the active set) against the monolithic NLP of the same discretisation, and across backends.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

from ocpar.bsp import open_backend
from ocpar.examples.formation_mixed_fleet import make
from ocpar.formation import DmocShape, FormationOptions, FormationProblem, solve_formation

U_MAX = 2.7


@pytest.fixture(scope="module")
def free():
    return solve_formation(make(limit=None))


@pytest.mark.parametrize("limit", ["box", "norm"])
def test_thrust_limited_fleet_hierarchical_equals_monolithic(limit, free):
    """Measured: box 63.2814391059 (6 supersteps), norm 63.2995712603 (5), free 63.0311212078
    (4); hierarchical and monolithic agree to ~1.6e-14, the coupling to ~2e-16."""
    problem = make(limit=limit)
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.status == monolithic.status == "converged", hierarchical.message
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-7)
    assert hierarchical.coupling_residual <= 1e-9
    assert len(hierarchical.trace) <= len(free.trace) + 3
    size = (np.max(np.abs(hierarchical.controls), axis=2) if limit == "box"
            else np.linalg.norm(hierarchical.controls, axis=2))
    assert np.max(size) <= U_MAX * (1 + 1e-9)
    binding = np.max(size, axis=1) >= U_MAX * (1 - 1e-7)
    assert binding.sum() >= 2 and not binding.all()  # the heaviest agents' limits bind
    assert free.total_cost < hierarchical.total_cost < free.total_cost * 1.01
    assert np.max(free.peak_thrust) > U_MAX  # without limits they would be broken


def test_agents_with_equal_shapes_share_a_solver_and_the_fleet_is_checked():
    problem = make(limit="box")
    assert len(set(problem.shapes)) == 3  # three masses: three compiled solvers
    with pytest.raises(ValueError, match="one DmocShape per agent: 11 shapes for 12 agents"):
        FormationProblem("short", problem.shape[:-1], problem.curve, problem.starts)
    other = DmocShape(problem.shape[0].model, intervals=10, duration=5.0)
    message = r"shape\[1\]: intervals 10 differs from shape\[0\]'s 20"
    with pytest.raises(ValueError, match=message):
        FormationProblem("mixed-N", (problem.shape[0], other, *problem.shape[2:]),
                         problem.curve, problem.starts)


def test_mixed_fleet_on_mpi_and_dask_is_bitwise_the_serial_result(tmp_path):
    serial = solve_formation(make(limit="norm"))
    with open_backend("dask", workers=2) as backend:
        dask = solve_formation(make(limit="norm"), backend)
    assert dask.total_cost == serial.total_cost
    np.testing.assert_array_equal(dask.trajectories, serial.trajectories)
    proc = run_cli("-m", "ocpar.formation", "--problem",
                   "ocpar.examples.formation_mixed_fleet:make", "--problem-arg", "limit=norm",
                   "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    mpi = json.loads((tmp_path / "result.json").read_text())
    assert mpi["total_cost"] == serial.total_cost
    assert mpi["trajectories"] == serial.trajectories.tolist()
    assert mpi["peak_thrust"] == pytest.approx(serial.peak_thrust.tolist(), rel=1e-15)
