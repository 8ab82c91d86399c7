"""Pictures of a pursuit result: the state components over time (agent 0, the result, the
full-horizon MS solution) and the headline of each agent (convergence of the train)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.plotting import save, subplots, wrapped
from ocpar.pursuit.problem import PursuitProblem
from ocpar.pursuit.result import PursuitResult


def plot_trajectories(problem: PursuitProblem, result: PursuitResult, path: Path) -> Path:
    """One panel per state component x_i(t): agent 0, the result and the full-horizon MS
    solution, with the targets of the fixed final components; titled by the result's
    headline, or its status and why if it did not converge."""
    nx = problem.model.nx
    fig, axes = subplots(nx, 1, figsize=(7, 1.8 * nx + 1), sharex=True, squeeze=False)
    t = problem.grid
    label = "PBMS" if result.mode == "pbms" else "MS"
    returned = result.label(result.headline) if result.status == "converged" else result.status
    curves = [("initial feasible (agent 0)", result.initial_x, "tab:orange", "-", 1.0),
              (f"{label}: {returned}", result.x, "tab:blue", "-", 1.6)]
    if result.reference_x is not None:
        curves.append((f"MS: {result.label(result.reference_headline)}",
                       result.reference_x, "k", "--", 0.8))
    targets = dict(zip(problem.target_components, problem.target, strict=True))
    for i, ax in enumerate(axes[:, 0]):
        for name, x, colour, style, width in curves:
            ax.plot(t, np.asarray(x)[:, i], style, color=colour, lw=width, label=name)
        if i in targets:
            ax.plot(t[-1], targets[i], "o", color="tab:red", ms=4)
        ax.set_ylabel(f"x[{i}]")
        ax.grid(alpha=0.3)
    axes[0, 0].set_title(f"{problem.name}, N = {problem.samples} (dots: target set)\n"
                         f"{wrapped(result.title())}", fontsize=10)
    axes[0, 0].legend(fontsize=8)
    axes[-1, 0].set_xlabel("t")
    return save(fig, path)


def plot_convergence(result: PursuitResult, path: Path) -> Path:
    """The headline of each finished agent (agent 0 left out), with the MS reference; titled
    as :func:`plot_trajectories`."""
    fig, ax = subplots(figsize=(7, 4.5))
    values = result.headlines[1:]
    ax.plot(np.arange(1, len(values) + 1), values, "-", color="tab:blue", label="PBMS agents")
    if result.reference_headline is not None:
        ax.axhline(result.reference_headline, color="k", ls="--", lw=0.8,
                   label=f"full-horizon MS {result.label(result.reference_headline)}")
    ax.set_xscale("log")
    ax.set_xlabel("agent")
    unit = f" ({result.headline_unit})" if result.headline_unit else ""
    ax.set_ylabel(f"{result.headline_name}{unit}")
    ax.set_title(f"PBMS convergence, N_Δ = {result.window}, N_δ = {result.update}\n"
                 f"{wrapped(result.title())}", fontsize=10)
    ax.legend()
    ax.grid(alpha=0.3)
    return save(fig, path)
