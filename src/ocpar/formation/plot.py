"""Pictures of a formation result: the paper's Fig. 3 (planar: starts, trajectories, final
curve) and Fig. 5 (3-D: initial grid, trajectories, final curve)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.formation.keep_out.obstacles import Ellipsoid
from ocpar.formation.keep_out.separation import positions_at
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import FormationResult
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import Surface, fibonacci_directions
from ocpar.plotting import figure, save, subplots, wrapped

#: Most agents a picture draws (trajectory, start and final position): above it every k-th,
#: said in the title (drawing and writing the planar picture: 10,000 paths 0.9 s, 2000 0.3 s,
#: 100,000 start and final markers another 0.3 s; 100,000 paths took ~15 s, and at 120 dpi
#: show no more than a few thousand).
MAX_PATHS_DRAWN = 2_000


def path_step(agents: int) -> int:
    """Draw every ``path_step``-th agent: 1 up to :data:`MAX_PATHS_DRAWN` agents, else the
    smallest step that draws at most that many."""
    return max(1, -(-agents // MAX_PATHS_DRAWN))


def _drawn_note(agents: int) -> str:
    step = path_step(agents)
    return "" if step == 1 else f" (every {step}th agent drawn)"


def _target(problem: FormationProblem, samples: int) -> tuple[np.ndarray, dict]:
    """Points (m, d) to draw the target by, and their style: the curve as a dashed line of
    ``samples`` points, the slots as grey dots, or ``samples`` grey dots spread over a
    surface."""
    if isinstance(problem.curve, Slots):
        return problem.curve.points, {"ls": "", "marker": ".", "color": "0.5", "ms": 3}
    if isinstance(problem.curve, Surface):   # evenly spread points of the surface
        spread = problem.curve.parameters_toward(fibonacci_directions(samples))
        return problem.curve.points(spread), {"ls": "", "marker": ".", "color": "0.6",
                                              "ms": 1.5}
    return (problem.final_positions(np.linspace(0, 2 * np.pi, samples)),
            {"ls": "--", "color": "k", "lw": 0.8})


def plot_formation(problem: FormationProblem, result: FormationResult, path: Path) -> Path:
    """Write a PNG to ``path``: for a planar problem two panels (the whole manoeuvre, and a
    close-up of the curve with the last portions of the trajectories), in 3-D one perspective
    view as the paper's Fig. 5."""
    if problem.curve.dim == 3:
        return _plot_3d(problem, result, path)
    from matplotlib.collections import LineCollection

    fig, (ax_all, ax_end) = subplots(1, 2, figsize=(12, 5.5))
    circle, style = _target(problem, 400)
    shown = slice(None, None, path_step(result.agents))
    ends = problem.final_positions(result.phi[shown])
    tail = max(2, result.positions.shape[1] // 3)
    drawn = result.positions[shown]
    for ax, paths in ((ax_all, drawn), (ax_end, drawn[:, -tail:])):
        # one collection, not one line per agent: 10,000 paths in ~1 s instead of ~1 min
        ax.add_collection(LineCollection(paths[..., :2], colors="tab:blue", lw=0.7, alpha=0.7))
        ax.autoscale_view()
        ax.plot(circle[:, 0], circle[:, 1], **style)
        ax.plot(ends[:, 0], ends[:, 1], "x", color="tab:red", ms=5, label="final positions")
        ax.set_aspect("equal")
        ax.set_xlabel("$x_1$")
        ax.set_ylabel("$x_2$")
    starts = problem.starts[shown]
    ax_all.plot(starts[:, 0], starts[:, 1], "o", mfc="none", color="k", ms=3,
                label="start positions")
    for ax in (ax_all, ax_end):
        _draw_obstacles(ax, problem)
    _mark_closest(ax_all, problem, result)
    ax_all.set_title(f"{result.agents} agents, {wrapped(result.title())}"
                     f"{_drawn_note(result.agents)}")
    ax_all.legend(loc="upper left", fontsize=8)
    low, high = circle.min(axis=0), circle.max(axis=0)
    margin = 0.25 * np.max(high - low)
    ax_end.set_xlim(low[0] - margin, high[0] + margin)
    ax_end.set_ylim(low[1] - margin, high[1] + margin)
    ax_end.set_title("final positions and last portions of the trajectories")
    return save(fig, path)


def _plot_3d(problem: FormationProblem, result: FormationResult, path: Path) -> Path:
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    fig = figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    circle, style = _target(problem, 200)
    shown = slice(None, None, path_step(result.agents))
    ends = problem.final_positions(result.phi[shown])
    drawn = result.positions[shown, :, :3]
    ax.add_collection(Line3DCollection(drawn, colors="tab:blue", lw=0.7, alpha=0.8))
    ax.plot(circle[:, 0], circle[:, 1], circle[:, 2], **style)
    starts = problem.starts[shown]
    ax.plot(starts[:, 0], starts[:, 1], starts[:, 2], "o", mfc="none",
            color="k", ms=4, ls="", label="initial positions")
    ax.plot(ends[:, 0], ends[:, 1], ends[:, 2], "x", color="tab:red", ms=6, ls="",
            label="final positions")
    ax.set_xlabel("$x_1$")
    ax.set_ylabel("$x_2$")
    ax.set_zlabel("$x_3$")
    _mark_closest(ax, problem, result)
    ax.set_title(f"{problem.name}: {result.agents} agents, {wrapped(result.title())}"
                 f"{_drawn_note(result.agents)}")
    ax.legend(loc="upper left", fontsize=8)
    return save(fig, path)


def _draw_obstacles(ax, problem: FormationProblem) -> None:
    """The planar problem's obstacles, shaded: ellipses (ellipsoids' outlines) and half-
    spaces' boundary lines (the forbidden side hatched by a short normal)."""
    from matplotlib.patches import Ellipse as EllipsePatch

    for k, obstacle in enumerate(problem.obstacles):
        label = "obstacles" if k == 0 else None
        if isinstance(obstacle, Ellipsoid):
            axis = np.asarray(obstacle.axes)[0]
            ax.add_patch(EllipsePatch(obstacle.center, 2 * obstacle.semi_axes[0],
                                      2 * obstacle.semi_axes[1],
                                      angle=np.degrees(np.arctan2(axis[1], axis[0])),
                                      color="tab:gray", alpha=0.4, label=label))
        else:
            normal = np.asarray(obstacle.normal)
            foot = normal * obstacle.offset
            along = np.array([-normal[1], normal[0]]) * 1e3
            ax.axline(foot, foot + along, color="tab:gray", lw=2, label=label)


def _mark_closest(ax, problem: FormationProblem, result: FormationResult) -> None:
    """Mark the closest pair at the time of their closest approach: their two positions, the
    segment between them and a legend entry with the agents, distance and time."""
    closest = result.separation
    if not np.isfinite(closest.distance):
        return
    where = positions_at(result.positions[list(closest.agents)], closest.time,
                         problem.common_shape.duration)
    coords = where.T[:3] if ax.name == "3d" else where.T[:2]
    i, j = closest.agents
    ax.plot(*coords, "-s", color="tab:orange", ms=6, lw=1.5, zorder=5,
            label=f"closest: agents {i}, {j}, {closest.distance:.3g} apart at "
                  f"t = {closest.time:.3g}")
