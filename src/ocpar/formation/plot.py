"""Pictures of a formation result: the paper's Fig. 3 (planar: starts, trajectories, final
curve) and Fig. 5 (3-D: initial grid, trajectories, final curve), each with the thrust of a
few agents over time against their limit."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ocpar.formation.keep_out.obstacles import Ellipsoid
from ocpar.formation.keep_out.separation import positions_at
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import FormationResult
from ocpar.formation.targets.slots import Slots
from ocpar.formation.targets.surface import Surface, fibonacci_directions
from ocpar.ocp.reach import thrust_limit
from ocpar.plotting import components, figure, fit, legend_below, save, subplots, subscript

#: Most agents whose paths, starts and ends a picture draws one by one; above it the paths
#: are shown as a density (:func:`path_density`) under every :func:`path_step`-th agent's
#: path, start and end, all said in the title (at 2,000 agents single lines already merge
#: into one band at 120 dpi).
MAX_PATHS_DRAWN = 1_000

#: Agents drawn one by one over the density view.
SAMPLE_PATHS = 40

#: Most path points the density view counts: above it those of every k-th agent, said in
#: the title (half a million points are binned in ~0.01 s).
DENSITY_POINTS = 500_000

#: Points the density view counts along each segment of a path.
SEGMENT_POINTS = 24

#: Bins along each axis of the density view.
DENSITY_BINS = 200


def path_step(agents: int) -> int:
    """Draw every ``path_step``-th agent one by one: 1 up to :data:`MAX_PATHS_DRAWN` agents,
    else the smallest step that draws at most :data:`SAMPLE_PATHS`."""
    return 1 if agents <= MAX_PATHS_DRAWN else -(-agents // SAMPLE_PATHS)


def _every(step: int) -> str:
    """'every agent', 'every 2nd agent', 'every 2,500th agent', ..."""
    if step == 1:
        return "every agent"
    suffix = "th" if step % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(
        step % 10, "th")
    return f"every {step:,}{suffix} agent"


def path_density(points: np.ndarray, extent: tuple[float, float, float, float],
                 bins: int = DENSITY_BINS) -> np.ndarray:
    """Counts (bins, bins), indexed [y, x], of the points (k, 2) that lie in ``extent``
    (x0, x1, y0, y1), on a regular grid; one ``bincount``, not ``histogram2d``."""
    x0, x1, y0, y1 = extent
    ix = np.floor((points[:, 0] - x0) * (bins / (x1 - x0))).astype(np.int64)
    iy = np.floor((points[:, 1] - y0) * (bins / (y1 - y0))).astype(np.int64)
    inside = (ix >= 0) & (ix < bins) & (iy >= 0) & (iy < bins)
    return np.bincount(iy[inside] * bins + ix[inside], minlength=bins * bins).reshape(
        bins, bins)


def _draw_density(ax, points: np.ndarray, extent: tuple[float, float, float, float],
                  label: str) -> None:
    """The density of ``points`` in ``extent`` on ``ax``, log-shaded, empty bins blank, with
    a legend entry ``label``."""
    counts = path_density(points, extent)
    shade = np.ma.masked_equal(np.log1p(counts), 0)
    ax.imshow(shade, origin="lower", extent=extent, cmap="Blues", vmin=-0.3 * shade.max(),
              interpolation="nearest", aspect="auto", zorder=0)
    ax.fill([], [], color="#4a90c4", label=label)


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
    """Write a PNG to ``path``: for a planar problem three panels (the whole manoeuvre; a
    close-up of the curve with the trajectories' ends; the thrust of a few agents over time
    against their limit), in 3-D a perspective view as the paper's Fig. 5 above the thrust
    panel. One legend below the panels; axes named with their units (:func:`components`)."""
    if problem.curve.dim == 3:
        return _plot_3d(problem, result, path)
    from matplotlib.collections import LineCollection

    fig, (ax_all, ax_end, ax_u) = subplots(1, 3, figsize=(15, 5.6),
                                           width_ratios=(1, 1, 1.1))
    circle, style = _target(problem, 400)
    step = path_step(result.agents)
    shown = slice(None, None, step)
    ends = problem.final_positions(result.phi[shown])
    drawn = result.positions[shown, :, :2]
    dense = step > 1
    low, high = circle.min(axis=0), circle.max(axis=0)
    margin = 0.25 * np.max(high - low)
    close = (low[0] - margin, high[0] + margin, low[1] - margin, high[1] + margin)
    if dense:   # every agent's (or every k-th agent's) path binned; the close-up as drawn
        counted, points = _path_points(result.positions[..., :2])
        whole = _frame(np.vstack([_box(points), low, high]) if len(points) else circle)
        _draw_density(ax_all, points, whole, f"path density (log shade) of {_every(counted)}")
        ax_all.set_xlim(whole[:2])
        ax_all.set_ylim(whole[2:])
    trajectories = "trajectories" if not dense else f"trajectories of {_every(step)}"
    axes = _position_labels(problem)
    for ax in (ax_all, ax_end):
        # one collection, not one line per agent; the close-up draws the whole paths too,
        # cut by its frame, none starting mid-air
        ax.add_collection(LineCollection(drawn, colors="tab:blue" if not dense else "0.1",
                                         lw=0.7 if not dense else 0.5, alpha=0.7,
                                         label=trajectories))
        if not dense:
            ax.autoscale_view()
        ax.plot(circle[:, 0], circle[:, 1], **style, label="target")
        ax.plot(ends[:, 0], ends[:, 1], "x", color="tab:red", ms=5,
                label="final positions" if not dense else f"final positions of {_every(step)}")
        ax.set_aspect("equal")
        ax.set_xlabel(axes[0].label)
        ax.set_ylabel(axes[1].label)
    starts = problem.starts[shown]
    ax_all.plot(starts[:, 0], starts[:, 1], "o", mfc="none", color="k", ms=3,
                label="start positions" if not dense else f"start positions of {_every(step)}")
    for ax in (ax_all, ax_end):
        _draw_obstacles(ax, problem)
    _mark_closest(ax_all, problem, result)
    view = (f"\nshade: path density; lines and markers: {_every(step)} "
            f"({len(range(0, result.agents, step))} drawn)" if dense else "")
    ax_all.set_title(fit(f"{result.agents} agents, {result.title()}{view}", fig, 10, 1 / 3),
                     fontsize=10)
    ax_end.set_xlim(close[:2])
    ax_end.set_ylim(close[2:])
    ax_end.set_title("final positions and the trajectories' ends"
                     + ("" if not dense else f" of {_every(step)}"), fontsize=10)
    _plot_thrust(ax_u, problem, result)
    legend_below(fig, (ax_all, ax_end, ax_u))
    return save(fig, path)


def _path_points(positions: np.ndarray) -> tuple[int, np.ndarray]:
    """Points (k, 2) along the straight segments between the nodes of the paths
    ``positions`` (n, N + 1, 2) of every ``step``-th agent: :data:`SEGMENT_POINTS` evenly
    spaced in each segment's parameter, at most :data:`DENSITY_POINTS` in all (nodes alone
    would show rings of equal time, not paths); returns (step, points)."""
    agents, segments = positions.shape[0], max(positions.shape[1] - 1, 1)
    step = max(1, -(-agents * segments * SEGMENT_POINTS // DENSITY_POINTS))
    paths = positions[::step]
    if paths.shape[1] == 1:
        points = paths.reshape(-1, 2)
    else:
        f = np.arange(SEGMENT_POINTS)[:, None] / SEGMENT_POINTS       # (per, 1)
        start, delta = paths[:, :-1, None, :], np.diff(paths, axis=1)[:, :, None, :]
        points = (start + f * delta).reshape(-1, 2)
    return step, points[np.isfinite(points).all(axis=1)]   # a failed agent's NaN left out


def _box(points: np.ndarray) -> np.ndarray:
    """The corners (2, 2) of the box of the planar ``points`` (k, 2): lowest, highest (column
    by column: ``min(axis=0)`` over a million rows takes ~30 times as long)."""
    return np.array([[points[:, k].min() for k in (0, 1)],
                     [points[:, k].max() for k in (0, 1)]])


def _frame(points: np.ndarray) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the box of the planar ``points`` (k, 2) with a 4 % margin."""
    low, high = _box(points)
    pad = 0.04 * np.maximum(high - low, 1e-9)
    return (low[0] - pad[0], high[0] + pad[0], low[1] - pad[1], high[1] + pad[1])


def _position_labels(problem: FormationProblem) -> list:
    """The position axes' names and units (the configuration's first entries)."""
    model = problem.common_shape.model
    return components((problem, model), "configuration", problem.common_shape.node_size, "x")


#: Agents whose thrust the picture draws over time: those of the largest peaks.
THRUST_AGENTS = 6


def _plot_thrust(ax, problem: FormationProblem, result: FormationResult) -> None:
    """The thrust of the :data:`THRUST_AGENTS` agents of the largest peaks over time (each
    interval's control held on it) and the largest over all agents, with each thrust limit
    among them (:func:`~ocpar.ocp.reach.thrust_limit`): max_j |u_j| where every limit is a
    box, else |u|; of the model's first control group where it names them (``cost_parts``:
    the force, not the torque). Without controls in memory (written by the workers) a note
    says so."""
    from matplotlib.collections import LineCollection

    shape = problem.common_shape
    time = components((problem, shape.model), "time", 1, "t")[0]
    control = components((problem, shape.model), "control", shape.model.nu, "u")
    ax.set_xlabel(time.label)
    if result.controls is None:
        ax.set_title("thrust: controls are in the workers' array files", fontsize=10)
        ax.set_axis_off()
        return
    u = np.asarray(result.controls, float)
    parts = getattr(shape.model, "cost_parts", None)   # e.g. force, then torque entries
    group, (first, last) = next(iter(parts.items())) if parts else ("", (0, u.shape[2]))
    u = u[..., first:last]
    units = {c.unit for c in control[first:last]}   # one norm over entries of one unit
    limits = {thrust_limit(s) for s in problem.agents_by_shape()} - {None}
    fraction = np.repeat(np.linspace(0.0, 1.0, u.shape[1] + 1), 2)[1:-1]
    durations = _durations(problem, result)
    if len(units) > 1:
        _plot_entries(ax, u, control[first:last], fraction, durations)
        _draw_limits(ax, limits, np.abs(u).max(initial=0.0))
        return
    force = units.pop()
    entries = "" if not parts else f"{subscript(first + 1)}…{subscript(last)}"
    box = bool(limits) and all(kind == "box" for kind, _ in limits)
    size = np.max(np.abs(u), axis=2) if box else np.linalg.norm(u, axis=2)   # (n, N)
    name = f"maxⱼ |uⱼ|{entries}" if box else f"|u{entries}|"
    peaks = size.max(axis=1)
    top = np.argpartition(-peaks, min(THRUST_AGENTS, len(peaks)) - 1)[:THRUST_AGENTS]
    top = top[np.argsort(-peaks[top])]        # largest first, O(n) over the fleet
    lines = [np.column_stack([fraction * durations[i], np.repeat(size[i], 2)]) for i in top]
    ax.add_collection(LineCollection(lines, colors="tab:blue", lw=0.9, alpha=0.8,
                                     label=f"{name}: {len(top)} agents of the largest peaks"))
    if result.agents > len(top) and np.all(durations == durations[0]):   # one time axis
        ax.plot(fraction * durations[0], np.repeat(size.max(axis=0), 2), color="k", lw=0.6,
                ls=":",
                label=f"{name}: largest over all agents")
    _draw_limits(ax, limits, size.max(initial=0.0))
    ax.set_ylabel(f"{name} ({force})")
    ax.set_title(f"{group.removesuffix('_cost')} thrust over time".lstrip(), fontsize=10)


def _draw_limits(ax, limits: set[tuple[str, float]], largest: float) -> None:
    """Each thrust limit (kind, value) as a dashed line, the y axis from 0 to above the
    ``largest`` value drawn and every limit, a grid."""
    for kind, value in sorted(limits):
        ax.axhline(value, color="tab:red", ls="--", lw=1, label=f"{kind} thrust limit {value:g}")
    ax.autoscale_view()
    ax.set_ylim(0, 1.08 * max([largest] + [v for _, v in limits]) or 1.0)
    ax.grid(alpha=0.3)


def _plot_entries(ax, u: np.ndarray, entries: list, fraction: np.ndarray,
                  durations: np.ndarray) -> None:
    """Controls ``u`` (n, N, k) whose entries have different units (no norm over them): each
    entry's magnitude |u_j| over time, held on each interval, named with its unit
    (``entries``: :class:`~ocpar.plotting.Component`); the largest over all agents where
    they share one horizon, else the agent of the entry's largest peak over its own."""
    one_axis = bool(np.all(durations == durations[0]))
    for j, entry in enumerate(entries):
        size = np.abs(u[..., j])                      # (n, N)
        if one_axis:
            agent, curve, who = 0, size.max(axis=0), "largest over all agents"
        else:
            agent = int(np.argmax(size.max(axis=1)))
            curve, who = size[agent], f"agent {agent}, of the largest peak"
        ax.plot(fraction * durations[agent], np.repeat(curve, 2), lw=1.2,
                label=f"|{entry.name}| ({entry.unit}): {who}")
    ax.set_ylabel("|uⱼ| (each entry's unit: see the legend)")
    ax.set_title("control entries over time (no thrust norm: their units differ)",
                 fontsize=10)


def _plot_3d(problem: FormationProblem, result: FormationResult, path: Path) -> Path:
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    fig = figure(figsize=(8, 9.5))
    grid = fig.add_gridspec(2, 1, height_ratios=(3, 1))
    ax = fig.add_subplot(grid[0], projection="3d")
    ax_u = fig.add_subplot(grid[1])
    circle, style = _target(problem, 200)
    step = path_step(result.agents)
    shown = slice(None, None, step)
    ends = problem.final_positions(result.phi[shown])
    drawn = result.positions[shown, :, :3]
    ax.add_collection(Line3DCollection(drawn, colors="tab:blue", lw=0.7, alpha=0.8,
                                       label="trajectories"))
    ax.plot(circle[:, 0], circle[:, 1], circle[:, 2], **style, label="target")
    starts = problem.starts[shown]
    ax.plot(starts[:, 0], starts[:, 1], starts[:, 2], "o", mfc="none",
            color="k", ms=4, ls="", label="initial positions")
    ax.plot(ends[:, 0], ends[:, 1], ends[:, 2], "x", color="tab:red", ms=6, ls="",
            label="final positions")
    axes = _position_labels(problem)
    ax.set_xlabel(axes[0].label)
    ax.set_ylabel(axes[1].label)
    ax.set_zlabel(axes[2].label)
    _mark_closest(ax, problem, result)
    note = "" if step == 1 else f" ({_every(step)} drawn)"
    ax.set_title(fit(f"{problem.name}: {result.agents} agents, {result.title()}{note}", fig,
                     10), fontsize=10)
    _plot_thrust(ax_u, problem, result)
    legend_below(fig, (ax, ax_u))
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


def _durations(problem: FormationProblem, result: FormationResult) -> np.ndarray:
    """Each agent's horizon (n,): its own where each chose one (``result.durations``), else
    the run's T (its fleet's: a free or minimum final time sets it), else the problem's."""
    if result.durations is not None:
        return np.asarray(result.durations, float)
    duration = (result.fleet.duration if result.fleet is not None
                else problem.common_shape.duration)
    return np.full(result.agents, duration)


def _mark_closest(ax, problem: FormationProblem, result: FormationResult) -> None:
    """Mark the closest pair at the time of their closest approach: their two positions, the
    segment between them and a legend entry with the agents, distance and time."""
    closest = result.separation
    if not np.isfinite(closest.distance):
        return
    durations = _durations(problem, result)
    where = np.vstack([positions_at(result.positions[[a]], closest.time, durations[a])
                       for a in closest.agents])
    coords = where.T[:3] if ax.name == "3d" else where.T[:2]
    i, j = closest.agents
    ax.plot(*coords, "-s", color="tab:orange", ms=6, lw=1.5, zorder=5,
            label=f"closest: agents {i}, {j}, {closest.distance:.3g} apart at "
                  f"t = {closest.time:.3g}")
