"""Pictures of a MACS result: the archive (over the reference front, when the problem has
one) and the control laws of a few archive members."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np

from ocpar.macs.local_search import STATIONARITY_TOL
from ocpar.macs.problem import MacsProblem
from ocpar.macs.result import MacsResult
from ocpar.ocp import dfet_problem
from ocpar.plotting import NONDIMENSIONAL, components, fit, legend_below, save, subplots


def plot_front(result: MacsResult, path: Path) -> Path:
    """Archive (re-simulated objectives) over the reference front: the front itself for two
    objectives, every pairwise projection (J_a, J_b) for more. After the final refinement
    the converged members (settled and stationary) are filled, those whose refinement was
    not kept crossed. Titled by the front's quality, or the run's status and why if it did
    not converge (:meth:`~ocpar.results.RunResult.title`)."""
    names, reference = result.objective_names, result.reference_front
    pairs = list(combinations(range(len(names)), 2))
    columns = min(len(pairs), 3)
    rows = -(-len(pairs) // columns)
    fig, axes = subplots(rows, columns, figsize=(6.5 * columns, 4.8 * rows), squeeze=False)
    for ax, (a, b) in zip(axes.ravel(), pairs, strict=False):
        if reference is not None:
            style = "-" if len(names) == 2 else "."
            ax.plot(reference[:, a], reference[:, b], style, color="grey", lw=1, ms=2,
                    label="reference front")
        ax.plot(result.front[:, a], result.front[:, b], "o", mfc="none", color="tab:blue",
                label=f"MACS archive ({len(result.front)})")
        if result.converged is not None:
            for members, style, label in (
                    (result.converged, dict(marker="o", color="tab:blue"),
                     f"converged (stationary to {STATIONARITY_TOL:g})"),
                    (~np.asarray(result.refined, dtype=bool),
                     dict(marker="x", color="tab:red"), "refinement not kept")):
                if np.any(members):
                    ax.plot(result.front[members, a], result.front[members, b], ls="none",
                            label=f"{label} ({int(np.sum(members))})", **style)
        ax.set_xlabel(f"{names[a]} ({NONDIMENSIONAL})")
        ax.set_ylabel(f"{names[b]} ({NONDIMENSIONAL})")
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[len(pairs):]:
        ax.set_visible(False)
    refining = (f", {result.refinement_evaluations} of them refining"
                if result.stationarity is not None else "")
    fig.suptitle(fit(f"{result.problem}: {result.title()} ({result.evaluations} "
                     f"evaluations{refining})", fig, 10), fontsize=10)
    legend_below(fig, axes.ravel()[:len(pairs)])
    return save(fig, path)


def plot_controls(problem: MacsProblem, result: MacsResult, path: Path, count: int = 4) -> Path:
    """Control laws u(t) of ``count`` archive members spread along the front (every control
    component: one panel each, with its bounds), axes named with units
    (:func:`~ocpar.plotting.components`)."""
    dfet = dfet_problem(problem.shape)
    nu = problem.model.nu
    controls = components((problem, problem.model), "control", nu, "u")
    time = components((problem, problem.model), "time", 1, "t")[0]
    fig, axes = subplots(nu, 1, figsize=(6.5, 3.6 * nu + 1.6), squeeze=False)
    picks = np.unique(np.linspace(0, len(result.decisions) - 1, count).round().astype(int))
    for i in picks:
        law = dfet.control_law(result.decisions[i])
        tf = float(result.decisions[i][-1])
        t = np.linspace(0, tf, 400)
        u = np.array([np.ravel(law(s)) for s in t])
        label = ", ".join(f"{n} = {v:.4g}" for n, v in zip(result.objective_names,
                                                            result.front[i], strict=True))
        for c in range(nu):
            axes[c, 0].plot(t, u[:, c], label=label)
    for c, (low, high) in enumerate(problem.shape.control_bounds):
        for bound in (low, high):
            axes[c, 0].axhline(bound, color="tab:red", ls="--", lw=0.9, label="control bounds")
        axes[c, 0].set_xlabel(time.label)
        axes[c, 0].set_ylabel(controls[c].label)
        axes[c, 0].grid(alpha=0.3)
    axes[0, 0].set_title(fit(f"{result.problem}: controls of archive members", fig, 10),
                         fontsize=10)
    legend_below(fig, axes[:, 0])
    return save(fig, path)
