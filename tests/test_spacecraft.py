"""Rigid spacecraft about the Sun–Earth L2 halo (the paper's second example): the inner DMOC
problem against continuous dynamics and an analytic cost, hierarchical = monolithic, and the
30-spacecraft run on two MPI ranks."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_result_contract, run_cli
from scipy.integrate import solve_ivp

from ocpar.examples.formation_halo import FINAL_ATTITUDE, START_ATTITUDE, default_halo
from ocpar.examples.formation_halo import make as halo_spacecraft_example
from ocpar.formation import FormationOptions, solve_formation
from ocpar.models.rigid_spacecraft import CORIOLIS, RelativeRigidSpacecraft, quaternion_product
from ocpar.ocp import DmocShape, dmoc_problem

ROTATION_COST = 12 * np.pi**2  # rest-to-rest rotation by π in T = 1 with unit inertia


def inner_solution(intervals: int, end_position: np.ndarray, start_attitude=START_ATTITUDE):
    """One spacecraft from the origin (attitude ``start_attitude``) to ``end_position`` (km),
    attitude −1, at rest at both ends, over T = 1 from the halo's initial state."""
    problem = halo_spacecraft_example(agents=2, intervals=intervals)
    params = np.concatenate([np.zeros(3), start_attitude, np.zeros(7),
                             end_position, FINAL_ATTITUDE, np.zeros(7)])
    solution = dmoc_problem(problem.shape).solve(params)
    assert solution.success, solution.status
    return solution


END = np.array([0.3, -0.6, 0.7])


def test_inner_cost_converges_at_second_order_in_n():
    costs = [inner_solution(n, END).cost for n in (10, 20, 40, 80)]
    steps = np.abs(np.diff(costs))
    ratios = steps[:-1] / steps[1:]
    assert np.all((ratios > 3.5) & (ratios < 4.5)), ratios


def test_rotation_part_approaches_the_rest_to_rest_optimum():
    """Position fixed at the halo point: the cost is the rotation by π alone, 12π²/T³ in the
    limit (cubic angle profile), approached at second order."""
    errors = []
    for n in (10, 20, 40):
        sol = inner_solution(n, np.zeros(3))
        assert np.abs(sol.u[:, :3]).max() < 1e-8  # no force needed to stay on the halo
        errors.append(sol.cost - ROTATION_COST)
    assert 0 < errors[-1] < 1e-3 * ROTATION_COST
    assert 3.5 < errors[0] / errors[1] < 4.5 and 3.5 < errors[1] / errors[2] < 4.5


def replay(solution, duration: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Integrate the continuous dynamics with the DMOC controls held on each interval: the
    reference halo (CRTBP), the linearised relative motion δẍ = 2Sδẋ + K(t)δx + F, and the
    rigid body ṗ = ½ p ⊗ (0, Ω), Ω̇ = τ. Returns the final position (km) and quaternion."""
    halo = default_halo()
    crtbp = halo.crtbp
    n = len(solution.u)
    h = duration / n

    def rhs(t, y):
        k = min(int(t / h), n - 1)
        force, torque = solution.u[k, :3], solution.u[k, 3:]
        ref, dx, dv, p, omega = y[:6], y[6:9], y[9:12], y[12:16], y[16:19]
        hess = crtbp.potential_hessian(ref[:3])
        acc = 2 * CORIOLIS @ dv + hess @ dx + force
        pdot = 0.5 * quaternion_product(p, np.concatenate([[0.0], omega]))
        return np.concatenate([crtbp.rhs(t, ref), dv, acc, pdot, torque])

    y0 = np.concatenate([halo.state(0.0), solution.q[0, :3], np.zeros(3), solution.q[0, 3:],
                         np.zeros(3)])
    y = y0
    for k in range(n):  # interval by interval: the controls jump at the nodes
        y = solve_ivp(rhs, (k * h, (k + 1) * h), y, method="DOP853", rtol=1e-11,
                      atol=1e-12).y[:, -1]
    return y[6:9], y[12:16]


def test_replaying_the_controls_ends_near_the_target():
    """At N = 10 the DMOC controls, replayed through the continuous linearised dynamics and
    rigid-body equations, end within 2% of the formation radius (1 km) of the target."""
    radius = 1.0
    sol = inner_solution(10, END)
    position, attitude = replay(sol)
    assert np.linalg.norm(position - END) < 0.02 * radius
    # the attitude ends near −1 (a rotation by π from the start, as DMOC's path)
    assert abs(abs(attitude[0]) - 1) < 0.02 and abs(np.linalg.norm(attitude) - 1) < 1e-8


def test_the_model_checks_its_table():
    with pytest.raises(ValueError, match="shape"):
        RelativeRigidSpacecraft.from_matrices(np.zeros((3, 2, 2)))
    model = RelativeRigidSpacecraft.from_matrices(np.zeros((5, 3, 3)))
    with pytest.raises(ValueError, match="5 intervals"):
        DmocShape(model, 10)


def test_hierarchical_equals_monolithic_for_six_spacecraft():
    problem = halo_spacecraft_example(agents=6)
    hierarchical = solve_formation(problem, options=FormationOptions(outer="sqp"))
    newton = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and newton.converged and monolithic.converged
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert newton.total_cost == pytest.approx(hierarchical.total_cost, rel=1e-10)
    assert newton.supersteps < hierarchical.supersteps
    parts = hierarchical.cost_parts
    assert parts["translational_cost"] + parts["rotational_cost"] == pytest.approx(
        hierarchical.total_cost, rel=1e-12)
    # the rotation part: six rotations by π, each close to 12π² (N = 10)
    assert parts["rotational_cost"] / 6 == pytest.approx(ROTATION_COST, rel=0.01)


def test_thirty_spacecraft_on_two_mpi_ranks(tmp_path):
    out = tmp_path / "run"
    proc = run_cli("-m", "ocpar.formation", "--problem", "crtbp-rigid", "--output", str(out),
                   "--quiet", mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    result = json.loads((out / "result.json").read_text())
    assert result["agents"] == 30 and result["workers"] == 2
    assert result["status"] == "converged"
    assert result["equidistance_error"] <= 1e-9
    assert result["translational_cost"] + result["rotational_cost"] == pytest.approx(
        result["total_cost"], rel=1e-12)
    assert (out / "formation.png").read_bytes().startswith(b"\x89PNG")
    assert_result_contract(out)
