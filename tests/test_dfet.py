"""DFET on the MACS paper's Goddard ascent and orbit raising: the weak-form states of a fixed
control law converge to an accurate integration of that law, and the paper's sizes; the DFET
optimal control transcription's Mayer term and free final time (the contract's shared suite
is in test_transcriptions.py)."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from test_transcriptions import DoubleIntegrator

from ocpar.models import GoddardAscent, OrbitRaising
from ocpar.ocp import DfetOcpShape, DfetShape, OcpTask, dfet_ocp_problem, dfet_problem, solve_task

GODDARD_START = (0.0, 0.0, 0.0, 0.0)
ORBIT_START = (1.1, 0.0, 0.0, 1 / math.sqrt(1.1))


def goddard(elements: int, order: int, final: tuple[int, ...] = (),
            values: tuple[float, ...] = ()) -> DfetShape:
    return DfetShape(GoddardAscent(), elements, order, order, ((-math.pi / 2, math.pi / 2),),
                     (100.0, 250.0), GODDARD_START, final, values)


def orbit(elements: int, order: int) -> DfetShape:
    return DfetShape(OrbitRaising(), elements, order, order, ((-math.pi, math.pi),),
                     (20.0, 80.0), ORBIT_START)


def goddard_law(t: float) -> np.ndarray:
    """Linear-tangent steering, tan u = c1 + c2 t."""
    return np.array([math.atan(1.0 - 0.01 * t)])


def orbit_law(t: float) -> np.ndarray:
    return np.array([0.5 + 0.01 * t])


def final_state_error(shape: DfetShape, law, t_f: float) -> tuple[float, float]:
    """max |x_f(DFET) − x(t_f)| and max nodal state error, against the same (interpolated)
    control law integrated with rtol 1e-12."""
    problem = dfet_problem(shape)
    p = problem.sample_controls(law, t_f)
    z, ok = problem.solve_states(p)
    assert ok
    np.testing.assert_array_equal(z[problem.decision_slice], p)  # controls and t_f stay fixed
    final = float(np.max(np.abs(problem.final_state(z) - problem.simulate(p, rtol=1e-12))))
    exact_nodes = problem.state_nodes_of(problem.guess_from_decision(p))
    nodes = float(np.max(np.abs(problem.state_nodes_of(z) - exact_nodes)))
    return final, nodes


def test_goddard_states_converge_to_the_integrated_control_law():
    # measured: x_f errors 2.4e-7 (4 el., order 1), 3.8e-9 (8, 1), 5.7e-10 (4, 2), 2.4e-12
    # (8, 2); nodal errors 1.7e-2 (4, 2), 2.2e-3 (8, 2)
    err = {(n, order): final_state_error(goddard(n, order), goddard_law, 150.0)
           for n in (4, 8) for order in (1, 2)}
    assert err[8, 1][0] < err[4, 1][0] / 16  # elements doubled (x_f superconverges, ~64x)
    assert err[8, 2][0] < err[4, 2][0] / 16
    assert err[4, 2][0] < err[4, 1][0] / 50  # order raised (~400x)
    assert err[8, 2][1] < err[4, 2][1] / 5  # nodes: ~h^{l+1}, 8x
    assert err[8, 2][0] < 1e-10


def test_orbit_raising_states_converge_to_the_integrated_control_law():
    # 5.5 revolutions in t_f = 40: few elements are pre-asymptotic. Measured x_f errors:
    # 3.3e-3 (8 el., order 2), 3.2e-4 (8, 3), 1.1e-6 (16, 3), 6.9e-6 (8, 4), 2.9e-8 (16, 4)
    err = {(n, order): final_state_error(orbit(n, order), orbit_law, 40.0)[0]
           for n, order in ((8, 2), (8, 3), (16, 3), (8, 4), (16, 4))}
    assert err[16, 3] < err[8, 3] / 16  # elements doubled (~290x)
    assert err[16, 4] < err[8, 4] / 16  # (~240x)
    assert err[8, 3] < err[8, 2] / 3  # order raised (~10x, then ~46x)
    assert err[8, 4] < err[8, 3] / 10
    assert err[16, 4] < 1e-6


def test_paper_settings_build_with_the_paper_search_space():
    problem = dfet_problem(goddard(4, 6, (2, 3), (10.0, 0.0)))
    assert problem.p_lower.size == 29  # 4 elements × 7 control nodes + t_f
    assert problem.decision_slice.stop == problem.nz
    assert problem.nz == 4 * 7 * 4 + 4 + 29
    assert problem.ng == (4 * 7 + 1) * 4 + 2
    assert dfet_problem(goddard(4, 6, (2, 3), (10.0, 0.0))) is problem
    np.testing.assert_allclose(problem.p_upper[:-1], math.pi / 2)
    assert (problem.p_lower[-1], problem.p_upper[-1]) == (100.0, 250.0)
    np.testing.assert_array_equal(problem.lbz[: problem.decision_slice.start], -np.inf)

    # the final conditions are the last rows of g(z); x_f and t_f also come out symbolically
    p = problem.sample_controls(goddard_law, 150.0)
    z = problem.guess_from_decision(p)
    g = ca.Function("g", [problem.z], [problem.constraints])
    residual = np.asarray(g(z)).ravel()
    np.testing.assert_allclose(residual[-2:], problem.final_state(z)[2:] - [10.0, 0.0])
    assert np.max(np.abs(residual[:-2])) < 1e-6  # an accurate integration nearly solves them
    objectives = ca.Function("J", [problem.z], [problem.final_time(problem.z),
                                                -problem.final_state(problem.z)[1]])
    assert float(objectives(z)[0]) == problem.final_time(z) == 150.0
    assert float(objectives(z)[1]) == -problem.final_state(z)[1]

    raising = dfet_problem(orbit(30, 1))
    assert raising.p_lower.size == 61  # 30 elements × 2 control nodes + t_f
    assert raising.lbz[0] == 0.1 and raising.lbz[4 * 60] == 0.1  # r ≥ 0.1, nodes and x_f


def test_control_law_is_the_polynomial_the_nlp_uses():
    problem = dfet_problem(goddard(4, 2))
    law = problem.control_law(problem.sample_controls(lambda t: np.array([0.01 * t - 1]), 200))
    for t in (0.0, 13.0, 50.0, 133.3, 200.0):  # degree ≤ m is reproduced exactly
        assert law(t)[0] == pytest.approx(0.01 * t - 1)
    # not clipped between nodes: a re-simulation must use the control the NLP optimised
    quadratic = problem.control_law(np.append(np.tile([-1.5, 1.5, -1.5], 4), 100.0))
    assert abs(quadratic(0.0)[0]) > math.pi / 2
    with pytest.raises(ValueError, match="expected z"):
        problem.control_law(np.zeros(3))


@pytest.mark.parametrize(("change", "message"), [
    ({"elements": 0}, "element"),
    ({"order": 0}, "state order"),
    ({"control_order": -1}, "control order"),
    ({"control_bounds": ((-1.0, 1.0), (-1.0, 1.0))}, "control_bounds"),
    ({"control_bounds": ((1.0, -1.0),)}, "control_bounds"),
    ({"duration_bounds": (0.0, 10.0)}, "duration_bounds"),
    ({"duration_bounds": (20.0, 10.0)}, "duration_bounds"),
    ({"initial_state": (0.0, 0.0)}, "initial_state"),
    ({"final_components": (4,), "final_values": (1.0,)}, "final_components"),
    ({"final_components": (2, 2), "final_values": (1.0, 1.0)}, "final_components"),
    ({"final_components": (2, 3), "final_values": (1.0,)}, "final_values"),
])
def test_bad_shapes_are_refused(change, message):
    fields = {"model": GoddardAscent(), "elements": 4, "order": 2, "control_order": 2,
              "control_bounds": ((-1.0, 1.0),), "duration_bounds": (100.0, 250.0),
              "initial_state": GODDARD_START}
    with pytest.raises(ValueError, match=message):
        DfetShape(**(fields | change))


def final_time(x_f: ca.SX, t_f: ca.SX) -> ca.SX:
    """Mayer term of the minimum-time problem."""
    return t_f


def test_dfet_ocp_finds_the_bang_bang_minimum_time():
    """q̈ = u, |u| ≤ 1, from rest to rest over d = 1 in the least time: t_f = 2√d, u = +1
    then −1 (an even number of elements with constant controls represents it exactly)."""
    shape = DfetOcpShape(DoubleIntegrator(), 4, 2, 0, ((-1.0, 1.0),), (0.5, 5.0), (0, 1),
                         terminal_cost=final_time, running_cost=False)
    sol = solve_task(OcpTask(shape, np.array([0.0, 0.0, 1.0, 0.0])))
    assert sol.success, sol.status
    assert sol.final_time == pytest.approx(2.0, abs=1e-7)
    assert sol.cost == pytest.approx(sol.final_time, rel=1e-12)
    np.testing.assert_allclose(sol.final_state, [1.0, 0.0], atol=1e-8)
    controls = sol.z[dfet_ocp_problem(shape).dfet.decision_slice][:-1]
    np.testing.assert_allclose(controls, [1, 1, -1, -1], atol=1e-6)


def test_dfet_ocp_needs_a_cost():
    with pytest.raises(ValueError, match="needs a cost"):
        DfetOcpShape(DoubleIntegrator(), 4, 2, 0, ((-1.0, 1.0),), (0.5, 5.0), (0, 1),
                     running_cost=False)
    with pytest.raises(ValueError, match="final_components"):
        DfetOcpShape(DoubleIntegrator(), 4, 2, 0, ((-1.0, 1.0),), (0.5, 5.0), (2,))
