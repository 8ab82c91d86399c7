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
        # the archive's hollow rings on top of the status marks inside them (zorder)
        ax.plot(result.front[:, a], result.front[:, b], "o", mfc="none", color="tab:blue",
                ms=8, mew=1.2, zorder=4, label=f"MACS archive ({len(result.front)})")
        if result.converged is not None:
            for members, style, label in (
                    (result.converged, dict(marker="o", color="tab:green", ms=4, zorder=3),
                     f"converged (stationary to {STATIONARITY_TOL:g})"),
                    (~np.asarray(result.refined, dtype=bool),
                     dict(marker="x", color="tab:red", ms=5, zorder=3),
                     "refinement not kept")):
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


#: Points per element at which a control polynomial is drawn.
ELEMENT_POINTS = 40


def plot_controls(problem: MacsProblem, result: MacsResult, path: Path, count: int = 4) -> Path:
    """Control laws u(t) of ``count`` archive members spread along the front (every control
    component: one panel each, with its bounds), as DFET defines them: each element's
    polynomial drawn on its own element (a break between elements) through its control nodes
    (dots), where the NLP imposes the bounds; where a polynomial leaves the bounds between its
    nodes the panel's title says how far. Axes named with units
    (:func:`~ocpar.plotting.components`)."""
    dfet = dfet_problem(problem.shape)
    nu, elements = problem.model.nu, dfet.n
    m1 = problem.shape.control_order + 1
    controls = components((problem, problem.model), "control", nu, "u")
    time = components((problem, problem.model), "time", 1, "t")[0]
    fig, axes = subplots(nu, 1, figsize=(6.5, 3.6 * nu + 1.6), squeeze=False)
    axes = axes[:, 0]
    picks = np.unique(np.linspace(0, len(result.decisions) - 1, count).round().astype(int))
    # within each element (the last point just inside it), a NaN between elements
    inside = np.append(np.linspace(0.0, 1.0 - 1e-9, ELEMENT_POINTS), np.nan)
    reach = np.full((nu, 2), [np.inf, -np.inf])
    for i in picks:
        p = dfet.decision(result.decisions[i])
        law, step = dfet.control_law(p), p[-1] / elements
        t = ((np.arange(elements)[:, None] + inside) * step).ravel()
        u = np.array([np.ravel(law(s)) if np.isfinite(s) else np.full(nu, np.nan) for s in t])
        node_t = ((np.arange(elements)[:, None] + (dfet.control_nodes + 1) / 2) * step).ravel()
        nodes = p[:-1].reshape(elements * m1, nu)
        reach[:, 0] = np.minimum(reach[:, 0], np.nanmin(u, axis=0))
        reach[:, 1] = np.maximum(reach[:, 1], np.nanmax(u, axis=0))
        label = ", ".join(f"{n} = {v:.4g}" for n, v in zip(result.objective_names,
                                                            result.front[i], strict=True))
        for c, ax in enumerate(axes):
            (line,) = ax.plot(t, u[:, c], label=label)
            ax.plot(node_t, nodes[:, c], ".", color=line.get_color(), ms=4,
                    label="control nodes (bounds imposed)")
    titles = [f"{result.problem}: controls of archive members"] + [""] * (nu - 1)
    for c, ((low, high), ax) in enumerate(zip(problem.shape.control_bounds, axes, strict=True)):
        for bound in (low, high):
            ax.axhline(bound, color="tab:red", ls="--", lw=0.9, label="control bounds")
        if reach[c, 0] < low or reach[c, 1] > high:
            titles[c] = "\n".join(filter(None, (titles[c], (
                f"{controls[c].name}: the bounds hold at the control nodes; between them the "
                f"element polynomials reach {reach[c, 0]:.3g} … {reach[c, 1]:.3g}"))))
        if titles[c]:
            ax.set_title(fit(titles[c], fig, 10), fontsize=10)
        ax.set_xlabel(time.label)
        ax.set_ylabel(controls[c].label)
        ax.grid(alpha=0.3)
    legend_below(fig, axes)
    return save(fig, path)
