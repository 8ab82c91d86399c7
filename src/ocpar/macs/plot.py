"""Pictures of a MACS result: the archive over the reference front, and the control laws of a
few archive members."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.macs.problems import MacsProblem
from ocpar.macs.reference import reference_front
from ocpar.macs.result import MacsResult
from ocpar.ocp import dfet_problem
from ocpar.plotting import pyplot, save


def plot_front(result: MacsResult, path: Path) -> Path:
    """Archive (re-simulated objectives) over the reference front."""
    plt = pyplot()
    reference = reference_front(result.problem)
    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    ax.plot(reference[:, 0], reference[:, 1], "-", color="grey", lw=1, label="reference front")
    ax.plot(result.front[:, 0], result.front[:, 1], "o", mfc="none", color="tab:blue",
            label=f"MACS archive ({len(result.front)})")
    ax.set_xlabel("J1 = t_f")
    ax.set_ylabel("J2")
    ax.set_title(f"{result.problem}: GD {result.gd:.2e}, IGD {result.igd:.2e}, "
                 f"HV {result.hv:.4f} ({result.evaluations} evaluations)")
    ax.legend()
    ax.grid(alpha=0.3)
    return save(fig, path)


def plot_controls(problem: MacsProblem, result: MacsResult, path: Path, count: int = 4) -> Path:
    """Control laws u(t) of ``count`` archive members spread along the front."""
    plt = pyplot()
    dfet = dfet_problem(problem.shape)
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    picks = np.unique(np.linspace(0, len(result.decisions) - 1, count).round().astype(int))
    for i in picks:
        law = dfet.control_law(result.decisions[i])
        tf = float(result.decisions[i][-1])
        t = np.linspace(0, tf, 400)
        ax.plot(t, [float(np.ravel(law(s))[0]) for s in t],
                label=f"t_f = {tf:.2f}, J2 = {result.front[i, 1]:.4f}")
    ax.set_xlabel("t")
    ax.set_ylabel("u (rad)")
    ax.set_title(f"{result.problem}: controls of archive members")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return save(fig, path)
