"""A run's three files (result.json, result.nc, trace.json) and ``ocpar.load``: every scheme's
arrays come back bitwise as the run returned them, with units a unit library (pint) parses,
time coordinates and named components; the summary keeps its contract."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pint
import pytest
import xarray as xr
from conftest import REPO, assert_result_contract

import ocpar
from ocpar.driver import main
from ocpar.examples import formation_point_masses, macs_double_integrator
from ocpar.examples.pursuit_orbit_transfer import make as make_transfer
from ocpar.formation import Circle, DmocShape, FormationProblem, solve_formation
from ocpar.formation.run import FormationRun
from ocpar.formation.verify import verify_formation
from ocpar.macs import MacsSettings, solve_macs
from ocpar.models import PointMass
from ocpar.models.labels import derived
from ocpar.pursuit import PursuitSettings, solve_pursuit
from ocpar.result_files import (
    ARRAYS_FILE,
    SUMMARY_FILE,
    TRACE_FILE,
    load_trace,
    write_result,
    write_summary,
    write_timings,
)

UNITS = pint.UnitRegistry()


def written(result, directory):
    """``result`` written into ``directory`` and loaded back, after the common checks: three
    files, named by the summary; every variable with units and a long name; one trace record
    per superstep; the file's Dataset identical to the result's own."""
    paths = write_result(result, directory)
    assert [p.name for p in paths] == [SUMMARY_FILE, ARRAYS_FILE, TRACE_FILE]
    assert_result_contract(directory)
    ds, summary = ocpar.load(directory)
    assert summary["arrays"] == ARRAYS_FILE and summary["trace_file"] == TRACE_FILE
    assert summary["title"] == result.title() == ds.attrs["title"]
    assert "trace" not in summary
    assert ds.attrs["Conventions"] == "CF-1.10"
    for name, variable in ds.variables.items():
        assert variable.attrs["long_name"], name
        if "units_by_component" in variable.attrs:   # entries of different units
            units = ds[variable.attrs["units_by_component"]]
            assert units.dims == variable.dims[-1:], name
            assert "units" not in variable.attrs, name
            for unit in units.values:
                UNITS.parse_units(str(unit))
        else:
            UNITS.parse_units(variable.attrs["units"])   # raises unless pint parses it
        if name in ds.dims:   # a dimension's coordinate is 1-D, along it
            assert variable.dims == (name,), name
    trace = load_trace(directory)
    assert trace == json.loads(json.dumps([t.to_dict() for t in result.trace]))
    assert len(trace) == summary["supersteps"] == result.supersteps > 0
    assert [t["index"] for t in trace] == [t.index for t in result.trace]
    xr.testing.assert_identical(ds, result.dataset())
    return ds, summary


def test_formation_arrays_are_the_returned_paths_and_end_on_the_circle(tmp_path):
    problem = formation_point_masses.make(agents=12)
    result = solve_formation(problem)
    assert result.converged
    ds, summary = written(result, tmp_path)
    q = ds["configuration"].values
    assert q.tobytes() == np.asarray(result.trajectories).tobytes()   # bitwise
    assert ds["control"].values.tobytes() == np.asarray(result.controls).tobytes()
    assert ds["cost"].values.tobytes() == result.agent_costs.tobytes()
    assert summary["phi"] == ds["phi"].values.tolist() == result.phi.tolist()
    assert "trajectories" not in summary and "agent_costs" not in summary
    # the end points on the circle of radius 10 about (100, 100) at φ, from the formula
    phi = ds["phi"].values
    circle = np.column_stack([100 + 10 * np.cos(phi), 100 + 10 * np.sin(phi)])
    np.testing.assert_allclose(q[:, -1], circle, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ds["target"].values, circle, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ds["target"].sel(axis="y").values, ds["target"].values[:, 1])
    # time grid T = 1, N = 10; velocities the node differences over h = 0.1
    np.testing.assert_array_equal(ds["time"].values, np.linspace(0, 1, 11))
    np.testing.assert_allclose(ds["velocity"].values, np.diff(q, axis=1) / 0.1, rtol=1e-15)
    assert ds["velocity"].dims == ("agent", "interval_time", "q_component")
    assert list(ds["q_component"].values) == ["x", "y"]
    # time coordinates: the node at t = 0.5 is node 5; interval_time the intervals' starts,
    # so the control in force at t = 0.55 is u_5 (on [0.5, 0.6])
    np.testing.assert_array_equal(ds["configuration"].sel(time=0.52, method="nearest").values,
                                  q[:, 5])
    np.testing.assert_allclose(ds["interval_time"].values, np.arange(10) / 10, rtol=1e-15)
    np.testing.assert_array_equal(ds["control"].sel(interval_time=0.55, method="ffill").values,
                                  result.controls[:, 5])
    # per-agent and per-node variables apart: each table has one row per point of its own dims
    groups = ocpar.by_dimensions(ds)
    assert set(groups[("agent",)].data_vars) >= {"cost", "phi", "mass", "peak_thrust"}
    assert groups[("agent",)].to_dataframe().shape[0] == 12
    assert groups[("agent", "time", "q_component")].to_dataframe().shape[0] == 12 * 11 * 2
    assert ds["mass"].values.tolist() == [1.0] * 12
    assert ds["model_name"].values.tolist() == ["PointMass"]
    assert ds["solver_status_name"].values[ds["solver_status"].values].tolist() == \
        ["Solve_Succeeded"] * 12   # the batched Newton kernel's status
    assert np.all(ds["solver_iterations"].values >= 1)
    assert np.all(ds["constraint_violation"].values <= 1e-7)
    assert ds["configuration"].attrs["units"] == ds["control"].attrs["units"] == "1"


def test_the_timings_rewritten_after_the_plots_leave_the_rest_of_the_summary(tmp_path):
    """write_timings (the driver's second write, after the plots) gives the summary that
    write_summary would write with the new timings, the other fields as written before."""
    result = solve_formation(formation_point_masses.make(agents=5))
    write_result(result, tmp_path)
    before = json.loads((tmp_path / SUMMARY_FILE).read_text())
    result.timings |= {"picture_s": 0.25, "total_s": 1.5}
    write_timings(result, tmp_path)
    after = json.loads((tmp_path / SUMMARY_FILE).read_text())
    assert after["timings"] == result.all_timings() != before["timings"]
    assert after["timings"]["picture_s"] == 0.25 and list(after["timings"])[-1] == "total_s"
    assert {k: v for k, v in after.items() if k != "timings"} == \
        {k: v for k, v in before.items() if k != "timings"}
    write_summary(result, tmp_path)   # encoded whole: the same file
    assert json.loads((tmp_path / SUMMARY_FILE).read_text()) == after
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_a_dimensional_fleet_s_arrays_carry_its_si_units(tmp_path):
    """Point masses in m, kg and s: the configuration in m, the velocity in m/s, the control
    a force (N), the cost ∫|u|² dt in N² s, time in s: checked by conversion with pint."""
    problem = formation_point_masses.make(agents=4).with_shapes(lambda s: dataclasses.replace(
        s, model=PointMass(2, 1.0, length_unit="m", mass_unit="kg", time_unit="s")))
    ds, _ = written(solve_formation(problem), tmp_path)
    quantity = UNITS.Quantity
    for name, unit in (("configuration", "m"), ("velocity", "m/s"), ("control", "N"),
                       ("peak_thrust", "N"), ("cost", "N**2*s"), ("time", "s"),
                       ("interval_time", "s"), ("mass", "kg")):
        assert quantity(1.0, ds[name].attrs["units"]).to(unit).magnitude == \
            pytest.approx(1.0, rel=1e-15), name
    assert ds["q_component_units"].values.tolist() == ["m", "m"]


@pytest.mark.parametrize("factors", [
    (("m", 1), ("s", -1)), (("m", 1), ("s", -2)), (("kg", 1), ("m", 1), ("s", -2)),
    (("kg*m/s**2", 2), ("s", 1)), (("rad", 1), ("min", -1)), (("1", 1), ("s", -1)),
    (("Mm/min", 1), ("min", -1)), (("N*m", 1), ("rad", -1), ("s", -2)), (("1", 3), ("1", -1)),
])
def test_a_derived_unit_is_the_product_of_powers_pint_computes(factors):
    """``derived`` writes the product of powers of its factors as a string that pint parses
    to what pint's own arithmetic on the factors gives."""
    expected = UNITS.parse_units("1")
    for unit, exponent in factors:
        expected *= UNITS.parse_units(unit) ** exponent
    got = UNITS.parse_units(derived(*factors))
    assert UNITS.Quantity(1.0, got).to(expected).magnitude == pytest.approx(1.0, rel=1e-15)
    assert got.dimensionality == expected.dimensionality


@dataclasses.dataclass(frozen=True)
class Unicycle:
    """A planar rigid body: position (m, m) and heading (rad), pushed by a force (N, N) and
    turned by a torque (N*m), time in s; L = ½ m |ẋ|² + ½ I θ̇² with m = 1 kg, I = 1 kg m²."""

    nq: int = 3
    nu: int = 3
    state_names: tuple[str, ...] = ("x", "y", "heading")
    state_units: tuple[str, ...] = ("m", "m", "rad")
    control_units: tuple[str, ...] = ("N", "N", "N*m")
    time_unit: str = "s"
    position_indices: tuple[int, ...] = (0, 1)

    def lagrangian(self, q, qdot, interval=0):
        return 0.5 * (qdot.T @ qdot)

    def generalized_force(self, q, u):
        return u


def test_a_mixed_unit_fleet_s_velocity_is_each_entry_per_second(tmp_path):
    """A unicycle-like model in (m, m, rad) over s: its velocity entries are m/s, m/s and
    rad/s (each entry's unit over the time's, not the configuration's units copied), so
    pint converts the heading rate to deg/s as 180/π times the node differences over h."""
    problem = FormationProblem(
        name="unicycles", shape=DmocShape(Unicycle(), intervals=10, duration=2.0),
        curve=Circle(radius=10.0, center=np.array([100.0, 100.0])),
        starts=np.column_stack([np.linspace(-30.0, 30.0, 4), np.zeros(4), np.zeros(4)]),
        final_attitude=np.array([0.5]))
    result = solve_formation(problem)
    assert result.converged
    ds, _ = written(result, tmp_path)
    assert ds["q_component_units"].values.tolist() == ["m", "m", "rad"]
    assert ds["configuration"].attrs["units_by_component"] == "q_component_units"
    velocity = ds["velocity"]
    assert velocity.attrs["units_by_component"] == "velocity_units"
    assert ds["velocity_units"].dims == ("q_component",)
    assert ds["velocity_units"].values.tolist() == ["m/s", "m/s", "rad/s"]
    assert ds["u_component_units"].values.tolist() == ["N", "N", "N*m"]
    heading = result.trajectories[:, :, 2]
    unit = ds["velocity_units"].sel(q_component="heading").item()
    rate = UNITS.Quantity(velocity.sel(q_component="heading").values, unit).to("deg/s")
    np.testing.assert_allclose(rate.magnitude, np.degrees(np.diff(heading, axis=1) / 0.2),
                               rtol=1e-12)
    assert np.abs(rate.magnitude).max() > 1.0   # the heading turns by 0.5 rad
    speed = UNITS.Quantity(velocity.sel(q_component="x").values,
                           ds["velocity_units"].sel(q_component="x").item()).to("km/h")
    np.testing.assert_allclose(speed.magnitude, 3.6 * np.diff(result.trajectories[:, :, 0],
                                                              axis=1) / 0.2, rtol=1e-12)


def test_the_per_agent_violation_is_the_perturbed_agents_momentum_residual():
    """Agent 3's first free node moved by 1e-3: its violation is DMOC's first boundary
    momentum equation m v0 − m (q1 − q0)/h + h/2 u0 (relative to 1 + Σ |terms|), computed here
    from the formula; the other agents' stay at rounding."""
    problem = formation_point_masses.make(agents=8)
    result = solve_formation(problem)
    q, u = result.trajectories.copy(), result.controls
    q[3, 1, 0] += 1e-3
    violation = verify_formation(problem, q, u, result.phi).agent_violation
    h, v0 = 0.1, np.zeros(2)
    terms = [v0, -(q[3, 1] - q[3, 0]) / h, h / 2 * u[3, 0]]
    expected = np.linalg.norm(sum(terms)) / (1 + sum(np.linalg.norm(t) for t in terms))
    assert violation[3] == pytest.approx(expected, rel=1e-9)
    assert expected > 1e-5   # far above the check's tolerance 1e-7
    assert np.max(np.delete(violation, 3)) < 1e-12


def test_a_formation_run_from_the_command_line_writes_the_three_files(tmp_path, capsys):
    assert main(FormationRun, ["--agents", "6", "--quiet", "--output", str(tmp_path)]) == 0
    assert {SUMMARY_FILE, ARRAYS_FILE, TRACE_FILE} <= {p.name for p in tmp_path.iterdir()}
    assert_result_contract(tmp_path)
    reference = solve_formation(formation_point_masses.make(agents=6))
    for path in (tmp_path, tmp_path / SUMMARY_FILE, tmp_path / ARRAYS_FILE):
        ds, summary = ocpar.load(path)
        assert ds["configuration"].values.tobytes() == reference.trajectories.tobytes()
        assert summary["total_cost"] == reference.total_cost
    with pytest.raises(FileNotFoundError, match="nowhere: no such run"):
        ocpar.load(tmp_path / "nowhere")


def test_pursuit_arrays_are_the_returned_trajectory(tmp_path):
    result = solve_pursuit(make_transfer(case=1, samples=101),
                           PursuitSettings(window=32, update=16, max_agents=12,
                                           certify_samples=0), reference=False)
    ds, summary = written(result, tmp_path)
    assert ds["state"].values.tobytes() == np.asarray(result.x, float).tobytes()
    assert ds["control"].values.tobytes() == np.asarray(result.u, float).tobytes()
    assert ds["agent_headline"].values.tolist() == result.headlines
    assert len(result.headlines) == 13   # agent 0 and its 12 pursuers
    np.testing.assert_allclose(ds["time"].values, np.linspace(0, 300, 101), rtol=1e-15)
    assert "states" not in summary and "controls" not in summary
    assert ds["agent_headline"].attrs["units"] == "kg"
    # named entries in the model's units (Mm, t, min); the mixed units of the state by entry
    assert ds["state_component"].values.tolist() == ["r", "r_dot", "theta_dot", "mass"]
    assert ds["control_component"].values.tolist() == ["u1", "u2"]
    assert ds["state"].attrs["units_by_component"] == "state_component_units"
    assert UNITS.Quantity(1.0, ds["state_component_units"].sel(state_component="mass").item()
                          ).to("kg").magnitude == pytest.approx(1000.0, rel=1e-15)
    assert ds["time"].attrs["units"] == "min" and ds["time"].attrs["standard_name"] == "time"
    # t = 150 min is sample 50 (h = 3 min); interval_time the intervals' starts
    np.testing.assert_array_equal(ds["state"].sel(time=151.0, method="nearest").values,
                                  np.asarray(result.x)[50])
    np.testing.assert_array_equal(ds["interval_time"].values, ds["time"].values[:-1])
    # the initial state x_I (9.6 Mm, at rest radially, 0.525 t); agent 0's path beside it
    initial = ds["initial_state"]
    assert initial.dims == ("state_component",)
    assert initial.sel(state_component="r").item() == 9.6
    assert initial.sel(state_component="mass").item() == 0.525
    assert initial.sel(state_component="r_dot").item() == 0.0
    assert ds["plan_state"].dims == ("time", "state_component")
    np.testing.assert_array_equal(ds["plan_state"].values[0], initial.values)


def test_macs_arrays_are_the_front_decisions_and_trajectories(tmp_path):
    problem = macs_double_integrator.make()
    result = solve_macs(problem, MacsSettings(max_evaluations=150, archive_size=5, seed=1))
    assert len(result.front)
    ds, summary = written(result, tmp_path)
    assert ds["front"].values.tolist() == summary["front"] == result.front.tolist()
    assert ds["objective"].values.tolist() == summary["objectives"]
    assert ds["decision"].values.tobytes() == result.decisions.tobytes()
    assert ds["decision"].dims == ("member", "decision_entry")
    assert "decisions" not in summary
    # the controls: the decision's control nodes (all but t_f), element by element, at the
    # elements' Gauss-Legendre nodes (4 elements, controls of order 1: 2 nodes each) as
    # fractions of t_f
    control = ds["control"]
    k = len(result.front)
    assert (problem.elements, problem.control_order) == (4, 1)
    assert control.dims == ("member", "control_fraction", "control_component")
    np.testing.assert_array_equal(control.values.reshape(k, -1), result.decisions[:, :-1])
    nodes = (np.array([-1, 1]) / np.sqrt(3) + 1) / 2
    fractions = ((np.arange(4)[:, None] + nodes) / 4).ravel()
    np.testing.assert_allclose(ds["control_fraction"].values, fractions, rtol=1e-14)
    np.testing.assert_allclose(ds["control_time"].values,
                               result.decisions[:, -1:] * fractions, rtol=1e-14)
    near = int(np.argmin(np.abs(fractions - 0.5)))
    np.testing.assert_array_equal(control.sel(control_fraction=0.5, method="nearest").values,
                                  control.values[:, near])
    np.testing.assert_array_equal(ds["final_time"].values, result.decisions[:, -1])
    # one member's controls by its own time: t_f times the fraction
    first = control.isel(member=0).swap_dims(control_fraction="control_time")
    np.testing.assert_array_equal(
        first.sel(control_time=0.5 * result.decisions[0, -1], method="nearest").values,
        control.values[0, near])
    # each trajectory starts at x_0 and ends where the transcription's final state is, at t_f
    states, times = ds["state"].values, ds["state_time"].values
    assert states.shape[0] == times.shape[0] == k
    np.testing.assert_allclose(states[:, 0], np.broadcast_to(
        problem.shape.initial_state, (k, len(problem.shape.initial_state))), atol=1e-9)
    np.testing.assert_allclose(times[:, -1], result.decisions[:, -1], rtol=1e-14)
    # the states by normalised time, as the controls: the state nodes are each element's
    # Gauss-Lobatto nodes (order l = 3: its ends and ±1/sqrt(5)), right-continuous at the
    # elements' ends, t_f the last element's end; each element's own end beside them
    order, n = problem.order, problem.elements
    assert ds["state"].dims == ("member", "state_fraction", "state_component")
    assert ds["state_time"].dims == ("member", "state_fraction")
    assert order == 3
    lobatto = (np.array([-1, -1 / np.sqrt(5), 1 / np.sqrt(5), 1]) + 1) / 2
    expected = np.append(((np.arange(n)[:, None] + lobatto[:-1]) / n).ravel(), 1.0)
    np.testing.assert_allclose(ds["state_fraction"].values, expected, rtol=0, atol=1e-15)
    np.testing.assert_allclose(times, result.decisions[:, -1:] * expected, rtol=1e-14)
    nodes = np.asarray(result.states)   # (k, N, l+1, nx): element by element
    mid = ds["state"].sel(state_fraction=0.49, method="nearest")   # t_f/2: element 2's start
    np.testing.assert_array_equal(mid.values, nodes[:, n // 2, 0])
    np.testing.assert_array_equal(ds["state"].sel(state_fraction=1.0).values, nodes[:, -1, -1])
    np.testing.assert_array_equal(ds["element_end_state"].values, nodes[:, :, -1])
    np.testing.assert_allclose(ds["element_end_fraction"].values, (np.arange(n) + 1) / n)
    np.testing.assert_allclose(result.state_times[:, 1, 1],
                               result.decisions[:, -1] * (1 + lobatto[1]) / n, rtol=1e-14)
    # the discontinuity at the elements' ends: small, but there (the states are DFET's)
    jump = np.abs(ds["state"].values[:, order:-1:order] - nodes[:, :-1, -1]).max()
    assert 0 < jump < 1e-2
    assert ds["refined"].values.tolist() == np.asarray(result.refined, int).tolist()
    assert ds["stationarity"].values.tobytes() == np.asarray(result.stationarity,
                                                               float).tobytes()
    json.loads((tmp_path / TRACE_FILE).read_text())


def test_a_directory_without_a_result_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"no result\.json at"):
        ocpar.load(tmp_path)


def test_a_large_run_s_workers_write_their_agents_and_load_joins_them(tmp_path, monkeypatch):
    """Above PARTS_MIN_AGENTS (lowered here) the workers write their agents' variables
    themselves: 2 Dask workers write 2 parts beside result.nc, which holds the run's own
    variables and names them; ``ocpar.load`` joins them into the Dataset the serial run's
    one file holds, bit for bit (the solver statuses' names merged in agent order), and
    the summary names the parts. An array file whose parts are not beside it is refused
    with their names."""
    from ocpar.bsp import open_backend
    from ocpar.formation import finish

    monkeypatch.setattr(finish, "PARTS_MIN_AGENTS", 100)
    problem = formation_point_masses.make(agents=300)
    single = solve_formation(problem, output=tmp_path / "single")   # one worker: one file
    assert not single.parts
    write_result(single, tmp_path / "single")
    with open_backend("dask", workers=2) as backend:
        parted = solve_formation(problem, backend, output=tmp_path / "parts")
    assert len(parted.parts) == 2 and parted.trajectories is None
    assert parted.total_cost == single.total_cost and parted.phi.tolist() == single.phi.tolist()
    assert parted.verification.to_dict() == single.verification.to_dict()
    paths = write_result(parted, tmp_path / "parts")
    assert [p.name for p in paths] == [SUMMARY_FILE, ARRAYS_FILE, *parted.parts, TRACE_FILE]
    ds, summary = ocpar.load(tmp_path / "parts")
    assert summary["array_parts"] == parted.parts
    xr.testing.assert_identical(ds, ocpar.load(tmp_path / "single").dataset)
    for name in ds.variables:
        assert ds[name].dtype == ocpar.load(tmp_path / "single").dataset[name].dtype, name
    (tmp_path / "parts" / parted.parts[1]).unlink()
    with pytest.raises(FileNotFoundError, match=parted.parts[1]):
        ocpar.load(tmp_path / "parts" / ARRAYS_FILE)


def test_a_model_s_names_and_units_are_checked_with_the_problem():
    """Names that do not fit the model's entries, or repeat, and a unit that is not a string
    are refused in one line naming the member, when the problem is built."""
    from ocpar.models import OrbitTransfer
    from ocpar.models.ode import check_ode_model

    @dataclasses.dataclass(frozen=True)
    class Short(OrbitTransfer):
        state_names = ("r", "r_dot", "theta_dot")

    @dataclasses.dataclass(frozen=True)
    class Twice(OrbitTransfer):
        control_names = ("u", "u")

    @dataclasses.dataclass(frozen=True)
    class Timeless(OrbitTransfer):
        time_unit = ""

    for model, message in ((Short(), r"model: Short.state_names: need 4 non-empty strings"),
                           (Twice(), r"model: Twice.control_names: names repeat"),
                           (Timeless(), r"model: Timeless.time_unit: need a unit string")):
        with pytest.raises(ValueError, match=message) as error:
            check_ode_model(model)
        assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match=r"MacsProblem.model: Short.state_names"):
        dataclasses.replace(macs_double_integrator.make(), model=Short())


def documented_statuses() -> dict[str, set[str]]:
    """docs/faults.md's table of what each status guarantees: scheme name → status words
    (rows for "all" schemes added to each)."""
    text = (REPO / "docs" / "faults.md").read_text()
    rows: dict[str, set[str]] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[1].startswith("`"):
            rows.setdefault(cells[0].lower(), set()).update(re.findall(r"`([a-z_]+)`", cells[1]))
    common = rows.pop("all")
    return {scheme: words | common for scheme, words in rows.items()}


def test_every_status_a_scheme_can_end_with_is_defined_in_the_docs_and_no_other():
    from ocpar.formation.result import FormationResult
    from ocpar.macs.result import MacsResult
    from ocpar.pursuit.result import PursuitResult

    documented = documented_statuses()
    for cls in (FormationResult, PursuitResult, MacsResult):
        assert set(cls.statuses) == documented[cls.scheme], cls.scheme
    fields = {f.name: None for f in dataclasses.fields(MacsResult) if f.init}
    with pytest.raises(ValueError, match="macs run's status 'separation_not_met'"):
        MacsResult(**(fields | {"status": "separation_not_met"}))
