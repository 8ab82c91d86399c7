"""The pictures are fit for a report: every text inside the figure and off the data, the
legends off the data, units on every axis, controls or thrust with their bounds, the pursuit
answer named by its source. Checked on the artists' bounding boxes in display coordinates
after drawing, on the paper examples and the mixed fleet at small sizes."""

from __future__ import annotations

import dataclasses
import warnings

import casadi as ca
import numpy as np
import pytest
from matplotlib.collections import LineCollection
from matplotlib.lines import Line2D

import ocpar.formation.plot
import ocpar.macs.plot
import ocpar.plotting
import ocpar.pursuit.plot
from ocpar.examples import (
    formation_halo,
    formation_mixed_fleet,
    formation_point_masses,
    formation_unicycles,
    macs_goddard,
    pursuit_orbit_transfer,
    pursuit_van_der_pol,
)
from ocpar.formation import DmocShape, FormationProblem, PlaneCurve, solve_formation
from ocpar.macs import MacsSettings, solve_macs
from ocpar.models import PointMass
from ocpar.models.labels import time_unit
from ocpar.pursuit import PursuitSettings, solve_pursuit


@pytest.fixture
def drawn(monkeypatch):
    """The figures the plot modules save, drawn (their layout done)."""
    figures = []
    save = ocpar.plotting.save

    def keeping(fig, path):
        figures.append(fig)
        return save(fig, path)

    for module in (ocpar.formation.plot, ocpar.pursuit.plot, ocpar.macs.plot):
        monkeypatch.setattr(module, "save", keeping)
    return figures


@pytest.fixture(scope="module")
def van_der_pol():
    """The van der Pol example (N = 41) and its default PBMS run: one agent and the
    full-horizon finish."""
    problem = pursuit_van_der_pol.make()
    return problem, solve_pursuit(problem, PursuitSettings(window=21, update=10))


def data_points(ax, renderer) -> np.ndarray:
    """Display coordinates (k, 2) of the data of a 2-D axes' lines and line collections that
    lie within its frame (horizontal bound lines across the frame included)."""
    points = []
    for artist in ax.get_children():
        if isinstance(artist, Line2D) and artist.get_visible():
            xy = artist.get_transform().transform(artist.get_xydata())
        elif isinstance(artist, LineCollection):
            segments = artist.get_segments()
            if not segments:
                continue
            xy = artist.get_transform().transform(np.concatenate(segments))
        else:
            continue
        points.append(xy)
    if not points:
        return np.empty((0, 2))
    xy = np.concatenate(points)
    frame = ax.get_window_extent(renderer)
    inside = ((xy[:, 0] >= frame.x0) & (xy[:, 0] <= frame.x1)
              & (xy[:, 1] >= frame.y0) & (xy[:, 1] <= frame.y1))
    return xy[inside]


def covers(extent, points: np.ndarray) -> int:
    """How many of the display points (k, 2) lie strictly inside the box ``extent``."""
    return int(np.sum((points[:, 0] > extent.x0) & (points[:, 0] < extent.x1)
                      & (points[:, 1] > extent.y0) & (points[:, 1] < extent.y1)))


def check_layout(fig) -> None:
    """Every axes' drawn extent (ticks, labels, title), every legend and the figure's title
    lie inside the figure; no title, axis label or legend covers a data point of a 2-D
    axes, nor does a legend cover a 3-D axes; every axis says its unit."""
    renderer = fig.canvas.get_renderer()
    box = fig.bbox
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    assert legends
    suptitle = [fig.get_suptitle()] if fig.get_suptitle() else []
    extents = ([(f"axes {ax.get_title()!r}", ax.get_tightbbox(renderer)) for ax in fig.axes
                if ax.get_visible()]
               + [("legend", legend.get_window_extent(renderer)) for legend in legends]
               + [(f"title {t!r}", fig._suptitle.get_window_extent(renderer)) for t in suptitle])
    for what, extent in extents:
        assert (extent.x0 >= box.x0 - 1 and extent.x1 <= box.x1 + 1 and extent.y0 >= box.y0 - 1
                and extent.y1 <= box.y1 + 1), f"{what} leaves the figure"
    flat = [ax for ax in fig.axes if ax.name != "3d" and ax.axison]
    points = np.concatenate([data_points(ax, renderer) for ax in flat] + [np.empty((0, 2))])
    texts = [t for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label)
             if t.get_visible() and t.get_text()]
    texts += [fig._suptitle] if suptitle else []
    for text in texts:
        covered = covers(text.get_window_extent(renderer), points)
        assert not covered, f"{text.get_text()!r} covers {covered} data points"
    for legend in legends:
        extent = legend.get_window_extent(renderer)
        covered = covers(extent, points)
        assert not covered, f"the legend covers {covered} data points"
        for ax in fig.axes:
            if ax.name == "3d":
                assert not extent.overlaps(ax.get_window_extent(renderer))
    shown = [ax for ax in fig.axes if ax.axison]
    assert all(ax.get_ylabel() for ax in shown) and any(ax.get_xlabel() for ax in shown)
    for ax in shown:   # axes sharing x name it once, below
        labels = [ax.get_xlabel(), ax.get_ylabel()]
        labels += [ax.get_zlabel()] if ax.name == "3d" else []
        for label in filter(None, labels):
            assert label.endswith(")") and "(" in label, f"no unit in {label!r}"


def test_a_figure_waits_for_the_warm_up_and_draws_after_it(tmp_path):
    """The warm-up thread (Matplotlib imported, one figure rendered beside a solve) is done
    before the first figure is made, and a picture drawn after it is a whole PNG."""
    ocpar.plotting.warm_up()
    (thread,) = ocpar.plotting._warming
    fig, ax = ocpar.plotting.subplots(1, 1, figsize=(3, 2))
    assert not thread.is_alive()
    ax.plot([0, 1], [1, 0])
    path = ocpar.plotting.save(fig, tmp_path / "after.png")
    from PIL import Image

    with Image.open(path) as image:
        assert image.size == (3 * ocpar.plotting.DPI, 2 * ocpar.plotting.DPI)


def test_components_default_to_nondimensional_and_read_a_models_names():
    class Named:
        state_names = ("r", "v")
        state_units = ("Mm", "Mm/min")
        time_unit = "min"

    assert [c.label for c in ocpar.plotting.components(object(), "state", 2, "x")] == [
        "x₁ (nondimensional)", "x₂ (nondimensional)"]
    assert [c.label for c in ocpar.plotting.components(Named(), "state", 2, "x")] == [
        "r (Mm)", "v (Mm/min)"]
    assert ocpar.plotting.components(Named(), "time", 1, "t")[0].label == "t (min)"
    # the members the result files read, and only those: the axes say what the files say
    time = ocpar.plotting.components(Named(), "time", 1, "t")[0]
    assert time_unit(Named()) == "min" == time.unit
    plural = type("Plural", (), {"time_units": "min"})()
    assert time_unit(plural) == "1"
    assert ocpar.plotting.components(plural, "time", 1, "t")[0].unit == "nondimensional"
    # a problem's names and units come first, the model's fill in what it lacks
    problem = type("Problem", (), {"state_units": "km"})()
    assert [c.label for c in ocpar.plotting.components((problem, Named()), "state", 2, "x")
            ] == ["r (km)", "v (km)"]


def lobes_tutorial() -> FormationProblem:
    """The formation tutorial's problem: 2 × 3 point masses onto three lobes about (20, 0)."""
    def lobes(phi):
        r = 5.0 * (1 + 0.2 * ca.cos(3 * phi))
        return r * ca.cos(phi), r * ca.sin(phi)

    x, y = np.meshgrid(np.arange(3) * 2.0, np.arange(2) * 2.0)
    return FormationProblem(name="three-lobes",
                            shape=DmocShape(PointMass(dim=2, mass=1.0), 10, 2.0),
                            curve=PlaneCurve(lobes, center=np.array([20.0, 0.0])),
                            starts=np.column_stack([x.ravel(), y.ravel()]))


@pytest.mark.parametrize("example", ["point-masses", "lobes", "mixed-fleet", "mixed-norm",
                                     "halo", "unicycles"])
def test_formation_pictures_keep_text_off_the_data_and_draw_thrust_with_its_limit(
        example, drawn, tmp_path):
    problem = {"point-masses": lambda: formation_point_masses.make(agents=12),
               "mixed-fleet": lambda: formation_mixed_fleet.make(agents=9),
               "mixed-norm": lambda: formation_mixed_fleet.make(agents=6, limit="norm"),
               "halo": lambda: formation_halo.make(agents=6),
               "unicycles": lambda: formation_unicycles.make(agents=4),
               "lobes": lobes_tutorial}[example]()
    result = solve_formation(problem)
    ocpar.formation.plot.plot_formation(problem, result, tmp_path / "formation.png")
    (fig,) = drawn
    check_layout(fig)
    thrust = fig.axes[-1]
    assert "thrust" in thrust.get_title()
    u = np.asarray(result.controls)
    if example == "unicycles":   # a and ω: no norm over entries of different units
        entries = ocpar.plotting.components((problem, problem.common_shape.model), "control",
                                            2, "u")
        assert len({c.unit for c in entries}) == 2
        lines = thrust.get_lines()
        assert [line.get_label() for line in lines] == [
            f"|{c.name}| ({c.unit}): largest over all agents" for c in entries]
        for j, line in enumerate(lines):
            assert np.array_equal(line.get_ydata()[::2], np.abs(u[..., j]).max(axis=0))
        assert not [c for c in thrust.collections if isinstance(c, LineCollection)]
        return
    if example == "halo":   # the force entries (cost_parts' first group), not the torque
        u = u[..., :3]
    size = (np.abs(u).max(axis=2) if example == "mixed-fleet" else np.linalg.norm(u, axis=2))
    peaks = sorted(size.max(axis=1))[::-1][:ocpar.formation.plot.THRUST_AGENTS]
    (agents,) = [c for c in thrust.collections if isinstance(c, LineCollection)]
    drawn_peaks = sorted((s[:, 1].max() for s in agents.get_segments()), reverse=True)
    assert drawn_peaks == pytest.approx(peaks, rel=1e-12)
    limits = [line.get_ydata()[0] for line in thrust.get_lines()
              if "thrust limit" in line.get_label()]
    assert limits == ([2.7] if example.startswith("mixed") else [])
    if example == "mixed-fleet":   # the limit binds: the largest peak is at it
        assert max(peaks) == pytest.approx(2.7, rel=1e-6)
    elif example == "mixed-norm":
        assert max(peaks) <= 2.7 * (1 + 1e-6)


@pytest.mark.parametrize("example", ["van-der-pol", "orbit-transfer"])
def test_pursuit_pictures_name_the_states_the_answer_and_show_one_agent(example, van_der_pol,
                                                                        drawn,
                                                                        tmp_path):
    if example == "van-der-pol":
        problem, result = van_der_pol
    else:
        problem = pursuit_orbit_transfer.make(case=1, samples=61)
        result = solve_pursuit(problem, PursuitSettings(window=24, update=12))
    assert len(result.headlines) == 2   # agent 0 and one agent: one point to show
    ocpar.pursuit.plot.plot_trajectories(problem, result, tmp_path / "pursuit.png")
    ocpar.pursuit.plot.plot_convergence(result, tmp_path / "convergence.png")
    trajectories, convergence = drawn
    for fig in drawn:
        check_layout(fig)
    nx = problem.model.nx
    labels = [ax.get_ylabel() for ax in trajectories.axes]
    if example == "orbit-transfer":
        assert labels[:nx] == ["r (Mm)", "r_dot (Mm/min)", "theta_dot (rad/min)", "mass (t)"]
        assert trajectories.axes[-1].get_xlabel() == "t (min)"
    else:
        assert labels == ["x₁ (nondimensional)", "x₂ (nondimensional)",
                          "u (nondimensional)"]
    # the controls drawn are the answer's, held on each interval, with the model's bounds
    for j, ax in enumerate(trajectories.axes[nx:]):
        line = ax.get_lines()[0]
        assert np.array_equal(line.get_ydata()[::2], np.asarray(result.u)[:, j])
    bounds = sorted(line.get_ydata()[0] for ax in trajectories.axes[nx:]
                    for line in ax.get_lines() if line.get_label() == "control bounds")
    assert bounds == ([-1.0, 1.0] if example == "van-der-pol" else [])
    source = {"full_horizon": "full-horizon MS from the train's answer",
              "train": "PBMS train's last agent"}[result.result_source]
    legend = [t.get_text() for t in trajectories.legends[0].get_texts()]
    assert any(t.startswith(f"answer, {source}") for t in legend)
    assert not any("PBMS:" in t for t in legend)
    # one agent: a marker on a linear axis
    ax = convergence.axes[0]
    (agents,) = [line for line in ax.get_lines() if line.get_label().startswith("PBMS agents")]
    assert ax.get_xscale() == "linear" and agents.get_marker() == "o"
    assert agents.get_ydata().tolist() == [result.headlines[1]]


def test_macs_pictures_keep_the_title_and_legends_in_and_draw_the_control_bounds(
        drawn, tmp_path):
    problem = macs_goddard.make()
    result = solve_macs(problem, MacsSettings(max_evaluations=150, archive_size=6, seed=0,
                                              no_refine=True))
    ocpar.macs.plot.plot_front(result, tmp_path / "front.png")
    ocpar.macs.plot.plot_controls(problem, result, tmp_path / "controls.png")
    for fig in drawn:
        check_layout(fig)
    front, controls = drawn
    assert front.get_suptitle().startswith(result.problem)
    bounds = sorted(line.get_ydata()[0] for line in controls.axes[0].get_lines()
                    if line.get_label() == "control bounds")
    assert bounds == sorted(np.ravel(problem.control_bounds))
    assert controls.axes[0].get_ylabel() == "thrust_angle (rad)"   # the model's name
    # the archive's rings are drawn over every other mark
    (archive,) = [line for line in front.axes[0].get_lines()
                  if line.get_label().startswith("MACS archive")]
    others = [line for line in front.axes[0].get_lines() if line is not archive]
    assert archive.get_markerfacecolor() == "none"
    assert all(archive.get_zorder() > line.get_zorder() for line in others)
    # the control nodes, where the NLP imposes the bounds, lie within them; the curves
    # between them are the element polynomials, and the title says how far they reach
    ax = controls.axes[0]
    (low, high), = problem.control_bounds
    nodes = [line for line in ax.get_lines() if line.get_label().startswith("control nodes")]
    curves = [line for line in ax.get_lines() if line.get_marker() == "None"
              and line.get_label() != "control bounds"]
    assert len(nodes) == len(curves) >= 2
    for line in nodes:
        assert np.all((line.get_ydata() >= low - 1e-6) & (line.get_ydata() <= high + 1e-6))
    reach = (min(np.nanmin(c.get_ydata()) for c in curves),
             max(np.nanmax(c.get_ydata()) for c in curves))
    beyond = reach[0] < low or reach[1] > high
    title = ax.get_title().replace("\n", " ")
    assert beyond == ("between them the element polynomials reach" in title)
    if beyond:
        assert f"reach {reach[0]:.3g} … {reach[1]:.3g}" in title
    # each element's polynomial on its own element: a break between elements
    assert sum(np.isnan(curves[0].get_ydata())) == problem.elements


def test_a_picture_on_a_small_figure_keeps_its_text_inside(van_der_pol, drawn, tmp_path,
                                                           monkeypatch):
    """Long titles and legend labels wrap to a figure of half the width."""
    problem, result = van_der_pol
    result = dataclasses.replace(result, status="not_converged", message="x " * 200)
    small = ocpar.plotting.subplots

    def halved(*grid, figsize=None, **kwargs):
        return small(*grid, figsize=(figsize[0] / 2, figsize[1]), **kwargs)

    monkeypatch.setattr(ocpar.pursuit.plot, "subplots", halved)
    ocpar.pursuit.plot.plot_trajectories(problem, result, tmp_path / "pursuit.png")
    ocpar.pursuit.plot.plot_convergence(result, tmp_path / "convergence.png")
    for fig in drawn:
        check_layout(fig)


def test_without_controls_in_memory_the_thrust_panel_says_where_they_are(drawn, tmp_path):
    """A run whose workers wrote the agents' arrays keeps no controls on the coordinator."""
    problem = formation_point_masses.make(agents=4)
    result = dataclasses.replace(solve_formation(problem), controls=None)
    ocpar.formation.plot.plot_formation(problem, result, tmp_path / "formation.png")
    (fig,) = drawn
    check_layout(fig)
    assert not fig.axes[-1].axison
    assert fig.axes[-1].get_title() == "thrust: controls are in the workers' array files"


def test_the_path_density_counts_as_numpys_histogram():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(5000, 2))
    extent = (-2.0, 3.0, -1.5, 2.5)
    counts = ocpar.formation.plot.path_density(points, extent, bins=37)
    expected, _, _ = np.histogram2d(points[:, 1], points[:, 0], bins=37,
                                    range=[extent[2:], extent[:2]])
    assert np.array_equal(counts, expected)


def artists(fig) -> int:
    """Every artist of the figure's axes and legends (their children, recursively)."""
    def count(artist) -> int:
        return 1 + sum(count(child) for child in artist.get_children())

    return sum(count(ax) for ax in fig.axes) + sum(count(legend) for legend in fig.legends)


@pytest.mark.parametrize("agents", [300, 2_000, 10_000,
                                    pytest.param(100_000, marks=pytest.mark.slow)])
def test_a_large_formation_is_drawn_as_a_path_density_under_a_sample_of_paths(
        agents, drawn, tmp_path):
    """Above MAX_PATHS_DRAWN agents the paths are a density (said in the title and legend)
    under every k-th agent's path: the figure's artists do not grow with the fleet."""
    problem = formation_point_masses.make(agents=agents)
    result = solve_formation(problem)
    ocpar.formation.plot.plot_formation(problem, result, tmp_path / "formation.png")
    (fig,) = drawn
    check_layout(fig)
    ax_all, ax_end, _ = fig.axes
    step = ocpar.formation.plot.path_step(agents)
    (paths,) = [c for c in ax_all.collections if isinstance(c, LineCollection)]
    assert len(paths.get_segments()) == len(range(0, agents, step))
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    dense = agents > ocpar.formation.plot.MAX_PATHS_DRAWN
    assert (len(ax_all.images), len(ax_end.images)) == ((1, 0) if dense else (0, 0))
    assert ("shade: path density" in ax_all.get_title()) == dense
    assert any(t.startswith("path density") for t in legend) == dense
    if dense:
        assert len(paths.get_segments()) <= ocpar.formation.plot.SAMPLE_PATHS
        assert f"every {step:,}th agent" in ax_all.get_title().replace("\n", " ")
        assert f"trajectories of every {step:,}th agent" in legend
        # the shade counts path points: the agents' starts lie in it, nothing far away
        image = ax_all.images[0]
        x0, x1, y0, y1 = image.get_extent()
        shade = image.get_array()
        bins = shade.shape[0]
        ix = ((problem.starts[:, 0] - x0) / (x1 - x0) * bins).astype(int).clip(0, bins - 1)
        iy = ((problem.starts[:, 1] - y0) / (y1 - y0) * bins).astype(int).clip(0, bins - 1)
        assert not np.any(np.ma.getmaskarray(shade)[iy, ix])
        assert np.ma.getmaskarray(shade).any()
        # what the paths' panels hold is independent of the fleet's size: the sampled
        # paths, starts and ends, the 400-point target, the closest pair
        nodes = result.positions.shape[1]
        sample = ocpar.formation.plot.SAMPLE_PATHS
        for ax in (ax_all, ax_end):
            held = sum(len(line.get_xdata()) for line in ax.get_lines()) + sum(
                len(segment) for c in ax.collections if isinstance(c, LineCollection)
                for segment in c.get_segments())
            assert held <= sample * nodes + 2 * sample + 400 + 2
        assert artists(fig) <= 700


def test_the_density_view_leaves_out_an_agent_without_a_path(drawn, tmp_path):
    """A failed agent's NaN positions are not binned (nor warned about)."""
    problem = formation_point_masses.make(agents=1_200)
    result = solve_formation(problem)
    positions = np.array(result.positions)
    positions[7] = np.nan
    with_gap = dataclasses.replace(result, positions=positions)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ocpar.formation.plot.plot_formation(problem, with_gap, tmp_path / "formation.png")
    (image,) = drawn[0].axes[0].images
    assert np.all(np.isfinite(image.get_extent())) and image.get_array().count() > 0
