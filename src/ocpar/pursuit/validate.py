"""Checks of a sampled orbit-transfer trajectory: discrete residuals and an accurate
re-simulation of its piecewise-constant controls (the paper's §VI-B.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from ocpar.models.orbit_transfer import M_PER_MM
from ocpar.pursuit.problem import TARGET_COMPONENTS, OrbitTransferProblem


def longitude(problem: OrbitTransferProblem, x: np.ndarray) -> np.ndarray:
    """θ at the samples (rad), θ_0 = 0, integrated from θ̇ by the same Euler rule as the
    states (θ_{j+1} = θ_j + h θ̇_j)."""
    return np.concatenate([[0.0], np.cumsum(problem.step * x[:-1, 2])])


def euler_residual(problem: OrbitTransferProblem, x: np.ndarray, u: np.ndarray) -> float:
    """max |x_{j+1} − x_j − h f(x_j, u_j)| and |x_N[r, ṙ, θ̇] − target| over the trajectory
    (Mm, Mm/min, rad/min, t mixed: each component in its own unit)."""
    f = np.array([problem.model.rhs_numpy(x[j], u[j]) for j in range(len(u))])
    gaps = x[1:] - x[:-1] - problem.step * f
    terminal = x[-1, list(TARGET_COMPONENTS)] - problem.target
    return float(max(np.max(np.abs(gaps)), np.max(np.abs(terminal))))


@dataclass
class RkCheck:
    """The controls re-simulated with adaptive RK45 (rtol 1e-11): final altitude error
    r(T) − R_T (m), final radial velocity (m/s), distance between the planned and the
    re-simulated final positions (m), and the re-simulated final mass (kg)."""

    final_altitude_error_m: float
    final_radial_velocity_mps: float
    final_position_error_m: float
    final_mass_kg: float


def rk_check(problem: OrbitTransferProblem, x: np.ndarray, u: np.ndarray) -> RkCheck:
    """Re-simulate the piecewise-constant controls ``u`` (N−1, 2) from x_I."""
    model, h = problem.model, problem.step

    def rhs(_t: float, y: np.ndarray, uj: np.ndarray) -> np.ndarray:
        return np.append(model.rhs_numpy(y[:4], uj), y[2])  # y = (r, ṙ, θ̇, μ, θ)

    y = np.append(problem.initial_state, 0.0)
    for uj in u:
        y = solve_ivp(rhs, (0.0, h), y, args=(uj,), rtol=1e-11, atol=1e-13).y[:, -1]
    r_plan, th_plan = x[-1, 0], longitude(problem, x)[-1]
    plan = r_plan * np.array([np.cos(th_plan), np.sin(th_plan)])
    sim = y[0] * np.array([np.cos(y[4]), np.sin(y[4])])
    return RkCheck(
        final_altitude_error_m=float((y[0] - problem.target_radius) * M_PER_MM),
        final_radial_velocity_mps=float(y[1] * M_PER_MM / 60.0),
        final_position_error_m=float(np.linalg.norm(sim - plan) * M_PER_MM),
        final_mass_kg=float(y[3] * 1e3),
    )
