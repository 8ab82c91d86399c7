"""Pictures of a pursuit result: the state components and the controls over time (agent 0,
the answer, the full-horizon MS reference; the controls' bounds), and the headline of each
agent (convergence of the train)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.models.ode import control_bounds
from ocpar.plotting import components, fit, legend_below, save, subplots
from ocpar.pursuit.problem import PursuitProblem
from ocpar.pursuit.result import PursuitResult

#: Agents up to which the convergence plot's agent axis is linear, with markers (log above).
LINEAR_AGENTS = 10


def answer_source(result: PursuitResult) -> str:
    """Where the returned answer came from, for legends: the full-horizon MS run (mode
    ``ms``), the PBMS train's last agent, or the full-horizon MS solve from the train's answer
    (its certificate, when at least as good)."""
    if result.mode == "ms":
        return "full-horizon MS from agent 0's plan"
    if result.result_source == "full_horizon":
        return "full-horizon MS from the train's answer"
    return "PBMS train's last agent"


def plot_trajectories(problem: PursuitProblem, result: PursuitResult, path: Path) -> Path:
    """One panel per state component x_i(t) (agent 0, the answer labelled by its source,
    the full-horizon MS reference; the targets of the fixed final components) and per
    control component u_j(t) of the answer (held on each interval) with its finite bounds;
    axes named with units (:func:`~ocpar.plotting.components`); titled by the result's
    headline, or its status and why if it did not converge."""
    model = problem.model
    nx, nu = model.nx, model.nu
    states = components((problem, model), "state", nx, "x")
    controls = components((problem, model), "control", nu, "u")
    time = components((problem, model), "time", 1, "t")[0]
    fig, axes = subplots(nx + nu, 1, figsize=(7.5, 1.55 * (nx + nu) + 2.2), sharex=True,
                         squeeze=False)
    axes = axes[:, 0]
    # real time: the answer's (a free final time's T found), agent 0's its plan's
    t, t_plan = np.asarray(result.time, float), np.asarray(problem.grid, float)
    returned = (result.label(result.headline) + result.final_time_text()
                if result.status == "converged" else result.status)
    answer = f"answer, {answer_source(result)}: {returned}"
    curves = [("agent 0's plan (initial feasible)", t_plan, result.initial_x, "tab:orange",
               "-", 1.0),
              (answer, t, result.x, "tab:blue", "-", 1.6)]
    if result.reference_x is not None:
        curves.append((f"reference: full-horizon MS from agent 0's plan: "
                       f"{result.label(result.reference_headline)}",
                       t, result.reference_x, "k", "--", 0.8))
    targets = dict(zip(problem.target_components, problem.target, strict=True))
    for i, ax in enumerate(axes[:nx]):
        for name, times, x, colour, style, width in curves:
            ax.plot(times, np.asarray(x)[:, i], style, color=colour, lw=width, label=name)
        if i in targets:
            ax.plot(t[-1], targets[i], "o", color="tab:red", ms=4, label="target set")
        ax.set_ylabel(states[i].label, fontsize=9)
    lower, upper = control_bounds(model)
    u = np.asarray(result.u, float)
    steps_t = np.repeat(t, 2)[1:-1]
    for j, ax in enumerate(axes[nx:]):
        ax.plot(steps_t, np.repeat(u[:, j], 2), color="tab:blue", lw=1.2)
        for bound in (lower[j], upper[j]):
            if np.isfinite(bound):
                ax.axhline(bound, color="tab:red", ls="--", lw=0.9, label="control bounds")
        ax.set_ylabel(controls[j].label, fontsize=9)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].set_title(fit(f"{problem.name}, N = {problem.samples}\n{result.title()}", fig, 10),
                      fontsize=10)
    axes[-1].set_xlabel(time.label)
    legend_below(fig, axes)
    return save(fig, path)


def plot_convergence(result: PursuitResult, path: Path) -> Path:
    """The headline of each finished agent (agent 0 left out; markers and a linear axis up
    to :data:`LINEAR_AGENTS` agents, a log axis above), with the answer's and the MS
    reference's; titled as :func:`plot_trajectories`."""
    fig, ax = subplots(figsize=(7, 5))
    values = np.asarray(result.headlines[1:], float)
    agents = np.arange(1, len(values) + 1)
    few = len(values) <= LINEAR_AGENTS
    ax.plot(agents, values, "o-" if few else "-", color="tab:blue", ms=5,
            label=f"PBMS agents ({len(values)})")
    if result.status == "converged" and result.result_source == "full_horizon":
        ax.axhline(result.headline, color="tab:green", lw=1,
                   label=f"answer, {answer_source(result)}: {result.label(result.headline)}")
    if result.reference_headline is not None:
        ax.axhline(result.reference_headline, color="k", ls="--", lw=0.8,
                   label=f"reference: full-horizon MS from agent 0's plan: "
                         f"{result.label(result.reference_headline)}")
    if few:
        ax.set_xlim(0.5, max(len(values), 1) + 0.5)
        ax.set_xticks(agents)
    else:
        ax.set_xscale("log")
    if not len(values):
        ax.text(0.5, 0.5, "no agent finished", transform=ax.transAxes, ha="center")
    ax.set_xlabel("agent (index)")
    unit = result.headline_unit or "nondimensional"
    ax.set_ylabel(f"{result.headline_name} ({unit})")
    ax.set_title(fit(f"PBMS convergence, N_Δ = {result.window}, N_δ = {result.update}\n"
                     f"{result.title()}", fig, 10), fontsize=10)
    ax.grid(alpha=0.3)
    legend_below(fig, [ax])
    return save(fig, path)
