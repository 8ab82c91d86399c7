"""Checks of a sampled trajectory: its discrete residuals, and its piecewise-constant controls
re-simulated accurately (the paper's §VI-B.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from ocpar.models.ode import ode_functions
from ocpar.ocp.batch import BufferedFunction
from ocpar.ocp.multiple_shooting import step_function
from ocpar.pursuit.problem import PursuitProblem

#: Accuracy of the re-simulation (scipy's RK45).
RESIM_RTOL, RESIM_ATOL = 1e-11, 1e-13


def discrete_residual(problem: PursuitProblem, x: np.ndarray, u: np.ndarray,
                      final_time: float | None = None) -> float:
    """max |x_{j+1} − Φ_h(x_j, u_j)|, |x_N[S] − target| and the path constraints' excess over
    their bounds along the trajectory x (N, nx), u (N−1, nu) of horizon ``final_time`` T
    (h = T/(N−1); default the problem's ``duration``), each in its own unit; NaN or a T
    outside a free final time's bounds: inf."""
    horizon = problem.horizon(final_time)
    if problem.final_time is not None and not (
            problem.final_time[0] <= horizon <= problem.final_time[1]):
        return float("inf")
    step = horizon / (problem.samples - 1)
    phi = step_function(problem.model, step, problem.integrator).map(len(u))
    gaps = x[1:] - np.asarray(phi(x[:-1].T, u.T)[0]).T
    terminal = x[-1, list(problem.target_components)] - problem.target
    return float(max(np.max(np.abs(gaps)), np.max(np.abs(terminal)),
                     problem.path_violation(x, u)))


@dataclass
class RkCheck:
    """The controls re-simulated with adaptive RK45 (rtol 1e-11) from x_I: the final state
    (nx,), the largest |x(T)[S] − target| (state units), and the problem's ``checks`` of the
    final state by key."""

    final_state: np.ndarray
    terminal_error: float
    values: dict[str, float]


def rk_check(problem: PursuitProblem, u: np.ndarray, final_time: float | None = None) -> RkCheck:
    """Re-simulate the piecewise-constant controls ``u`` (N−1, nu) from x_I, each held for
    h = T/(N−1) of real time (T: ``final_time``, default the problem's ``duration``)."""
    rhs = BufferedFunction(ode_functions(problem.model)[0])
    y = problem.initial_state.copy()
    step = problem.horizon(final_time) / len(u)
    for uj in u:
        y = solve_ivp(lambda _t, s, uj=uj: rhs(s, uj)[0], (0.0, step),
                      y, rtol=RESIM_RTOL, atol=RESIM_ATOL).y[:, -1]
    error = np.abs(y[list(problem.target_components)] - problem.target)
    return RkCheck(final_state=y, terminal_error=float(np.max(error)),
                   values={c.key: float(c.of_state(y.copy())) for c in problem.checks})
