"""Pictures of a pursuit result: trajectories around the Earth (the paper's Fig. 4) and the
final mass of each agent (convergence of the train)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.plotting import pyplot, save
from ocpar.pursuit.problem import OrbitTransferProblem
from ocpar.pursuit.result import PursuitResult
from ocpar.pursuit.validate import longitude

EARTH_RADIUS_MM = 6.378


def plot_trajectories(problem: OrbitTransferProblem, result: PursuitResult, path: Path) -> Path:
    """Initial (agent 0), PBMS and full-horizon MS trajectories in the orbit plane (Mm)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 6.5))
    ring = np.linspace(0, 2 * np.pi, 400)
    ax.fill(EARTH_RADIUS_MM * np.cos(ring), EARTH_RADIUS_MM * np.sin(ring), color="lightsteelblue",
            label="Earth")
    for radius, style in ((problem.initial_radius, ":"), (problem.target_radius, "--")):
        ax.plot(radius * np.cos(ring), radius * np.sin(ring), style, color="grey", lw=0.7)
    curves = [("initial feasible (agent 0)", result.initial_x, "tab:orange", 1.0)]
    label = "PBMS" if result.mode == "pbms" else "MS"
    curves.append((f"{label}: {result.final_mass_kg:.6f} kg", result.x, "tab:blue", 1.6))
    if result.reference_x is not None:
        curves.append((f"MS: {result.reference_final_mass_kg:.6f} kg", result.reference_x,
                       "k", 0.8))
    for name, x, colour, width in curves:
        theta = longitude(problem, x)
        ax.plot(x[:, 0] * np.cos(theta), x[:, 0] * np.sin(theta), color=colour, lw=width,
                label=name, ls="--" if colour == "k" else "-")
    ax.set_aspect("equal")
    ax.set_xlabel("x (10³ km)")
    ax.set_ylabel("y (10³ km)")
    ax.set_title(f"orbit transfer case {problem.case}, N = {problem.samples}")
    ax.legend(loc="lower left", fontsize=8)
    return save(fig, path)


def plot_convergence(result: PursuitResult, path: Path) -> Path:
    """Final mass of each finished agent (agent 0 left out), with the MS reference."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    masses = result.final_masses_kg[1:]
    ax.plot(np.arange(1, len(masses) + 1), masses, "-", color="tab:blue", label="PBMS agents")
    if result.reference_final_mass_kg is not None:
        ax.axhline(result.reference_final_mass_kg, color="k", ls="--", lw=0.8,
                   label=f"full-horizon MS {result.reference_final_mass_kg:.6f} kg")
    ax.set_xscale("log")
    ax.set_xlabel("agent")
    ax.set_ylabel("final mass (kg)")
    ax.set_title(f"PBMS convergence, N_Δ = {result.window}, N_δ = {result.update}")
    ax.legend()
    ax.grid(alpha=0.3)
    return save(fig, path)
