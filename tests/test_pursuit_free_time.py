"""A pursuit problem with a free final time (``PursuitProblem(final_time=..., time_weight=...)``),
solved by the full-horizon MS with T an NLP variable, against closed forms.

The double integrator ẋ1 = x2, ẋ2 = u, |u| ≤ 1, from (p, 0) to rest at the origin
(:mod:`ocpar.examples.pursuit_min_time`). RK4 integrates it exactly under piecewise-constant
controls, so the discrete problem differs from the continuous one only by its controls:

* minimum time (cost T): T* = 2 √|p|, u = −sign(p) then +sign(p), switching at T*/2. With N
  intervals, N even, the switch falls on a sample: the discrete optimum is T* itself, reached to
  the NLP's tolerance (1e-10; the optimum is degenerate, all controls on their bounds, so T is
  checked to 1e-8). N odd: T* ≤ T_N (piecewise-constant controls are admissible ones), and
  T_N − T* is O(1/N).
* time and energy (cost T + c ∫u²/2, the bound not reached): for a fixed T the least energy
  over controls constant on N intervals of h = T/N is a least-norm problem: the terminal
  conditions are A u = (−p, 0) with rows a1_j = h² (N − j − ½), a2_j = h, so
  Σu² = p² (AAᵀ)⁻¹₁₁ = 12 p² / (h⁴ N (N² − 1)) and the cost c h Σu²/2 = 6 c p² N² / (T³ (N² − 1)).
  Minimising T + that over T: T_N⁴ = 18 c p² N²/(N² − 1), J_N = 4 T_N/3 (the discrete
  optimum, checked to 1e-8); as N → ∞ the continuous T* = (18 c p²)^{1/4}, J* = 4 T*/3, within
  O(1/N²).
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import run_cli

import ocpar
from ocpar.__main__ import main as ocpar_main
from ocpar.bsp.columns import from_columns
from ocpar.examples.pursuit_min_time import make
from ocpar.ocp import MsShape, ms_problem
from ocpar.pursuit import PursuitSettings, solve_pursuit

SETTINGS = PursuitSettings(window=10, update=5)


def discrete_time_energy(energy: float, position: float, intervals: int) -> tuple[float, float]:
    """(T_N, J_N) of the time + energy problem on ``intervals`` N (module docstring)."""
    n2 = intervals**2
    final_time = (18 * energy * position**2 * n2 / (n2 - 1)) ** 0.25
    return final_time, 4 * final_time / 3


@pytest.fixture(scope="module")
def min_time():
    """p = 1 on N = 20 intervals (the switch on sample 10)."""
    return solve_pursuit(make(samples=21), SETTINGS, mode="ms")


def test_minimum_time_is_the_closed_form(min_time):
    """T = 2 √|p| to 1e-8, bang-bang on both sides of T/2; the answer checked in real time:
    the residuals on h = T/N and the controls re-simulated over T meet the target."""
    assert min_time.status == "converged" and min_time.free_final_time
    assert min_time.final_time == pytest.approx(2.0, abs=1e-8)
    assert min_time.headline == min_time.cost == pytest.approx(min_time.final_time, abs=1e-12)
    np.testing.assert_allclose(min_time.u[:, 0], [-1.0] * 10 + [1.0] * 10, atol=1e-6)
    assert min_time.time[-1] == min_time.final_time and len(min_time.time) == 21
    np.testing.assert_allclose(np.diff(min_time.time), min_time.final_time / 20, rtol=1e-12)
    assert min_time.constraint_violation < 1e-12 and min_time.rk_terminal_error < 1e-10


@pytest.mark.parametrize("position", [-2.25, 0.49])
def test_minimum_time_other_starts(position):
    """T* = 2 √|p| (3 and 1.4) from either side, the plan's horizon not the answer's."""
    result = solve_pursuit(make(samples=21, position=position), SETTINGS, mode="ms")
    assert result.status == "converged"
    assert result.final_time == pytest.approx(2 * np.sqrt(abs(position)), abs=1e-8)
    assert abs(result.plan_time[-1] - result.final_time) > 0.1


def test_minimum_time_off_the_grid_is_within_order_h():
    """N = 21 intervals: the switch falls between samples, T* < T_N ≤ T* (1 + 1/N)."""
    result = solve_pursuit(make(samples=22), SETTINGS, mode="ms")
    assert result.status == "converged"
    assert 2.0 + 1e-6 < result.final_time <= 2.0 * (1 + 1 / 21)


@pytest.mark.parametrize("samples", [21, 81])
def test_time_and_energy_is_the_closed_form(samples):
    """c = 4, p = 1 (largest |u| 6p/T*² = 0.71: the bound is not reached): T and J equal the
    discrete optimum to 1e-8 and the continuous one within 2/N²."""
    energy, intervals = 4.0, samples - 1
    result = solve_pursuit(make(samples=samples, energy=energy), SETTINGS, mode="ms")
    assert result.status == "converged"
    assert np.max(np.abs(result.u)) < 0.75
    final_time, cost = discrete_time_energy(energy, 1.0, intervals)
    assert result.final_time == pytest.approx(final_time, abs=1e-8)
    assert result.headline == pytest.approx(cost, abs=1e-8)
    continuous = (18 * energy) ** 0.25
    assert abs(result.final_time - continuous) <= 2 * continuous / intervals**2
    assert abs(result.headline - 4 * continuous / 3) <= 2 * continuous / intervals**2
    assert result.rk_terminal_error < 1e-10


def test_ms_shape_free_time_gradient_and_guess():
    """The transcription alone: T is w's last entry, clipped into its bounds in the default
    guess; dJ*/dp from the multipliers equals a central difference of J* in the start p."""
    model = make(energy=4.0).model
    shape = MsShape(model, 20, 0.01, (0, 1), "rk4", final_time=(1.0, 5.0), time_weight=1.0)
    ms = ms_problem(shape)
    assert ms.nw == 2 * 20 + 20 + 1 and ms.default_guess(np.zeros(4))[-1] == 1.0
    params = np.array([1.0, 0.0, 0.0, 0.0])
    sol = ms.solve(params)
    assert sol.success and sol.final_time == pytest.approx(
        discrete_time_energy(4.0, 1.0, 20)[0], abs=1e-8)
    step = 1e-5
    plus, minus = (ms.solve(params + np.array([d, 0, 0, 0]), sol.w).cost for d in (step, -step))
    assert sol.cost_gradient[0] == pytest.approx((plus - minus) / (2 * step), rel=1e-6)


def test_warm_started_newton_re_solves_move_the_final_time():
    """A ``warm_start`` free-time shape re-solves nearby starts by Newton steps on the KKT
    system (IPOPT if they fail), T included: batched bitwise as one by one, equal to cold
    IPOPT solves to 1e-8."""
    model = make(energy=4.0).model
    options = {"final_time": (1.0, 5.0), "time_weight": 1.0}
    cold = ms_problem(MsShape(model, 20, 0.15, (0, 1), "rk4", **options))
    warm = ms_problem(MsShape(model, 20, 0.15, (0, 1), "rk4", warm_start=True, **options))
    start = cold.solve(np.array([1.0, 0.0, 0.0, 0.0]))
    params = np.array([[1.0 + d, 0.0, 0.0, 0.0] for d in (0.0, 0.01, -0.02)])
    batch = from_columns(warm.solve_batch(params, [start.w] * 3, [start.lam_g] * 3))
    for p, sol in zip(params, batch, strict=True):
        assert sol.success
        assert sol.final_time == warm.solve(p, start.w, start.lam_g).final_time
        assert sol.final_time == pytest.approx(cold.solve(p).final_time, abs=1e-8)
    assert batch[1].final_time > batch[0].final_time > batch[2].final_time


def test_the_full_horizon_takes_no_window(min_time):
    """The train's window and update do not apply to the full-horizon MS: N = 21 below the
    default window (60) is solved as with a window that fits, bit for bit; the train refuses
    it in one line, from the API and the command line."""
    assert PursuitSettings().window > 21
    default = solve_pursuit(make(samples=21), mode="ms")
    assert default.status == "converged"
    assert default.final_time == min_time.final_time and default.cost == min_time.cost
    fixed = dataclasses.replace(make(samples=21), final_time=None, time_weight=0.0)
    with pytest.raises(ValueError, match=r"^window N_Δ must satisfy 2 <= N_Δ < N = 21, got 60"):
        solve_pursuit(fixed)


def test_bad_free_time_input_is_one_line():
    problem = make(samples=21)
    with pytest.raises(ValueError, match=r"^mode pbms: the pursuit train needs a fixed final"):
        solve_pursuit(problem, SETTINGS)
    with pytest.raises(ValueError, match=r"^duration: agent 0's horizon 3\.06\d* must lie "):
        dataclasses.replace(problem, final_time=(0.5, 2.0))
    with pytest.raises(ValueError, match=r"^final_time: need finite 0 < T_min <= T_max"):
        dataclasses.replace(problem, final_time=(2.0, 1.0))
    with pytest.raises(ValueError, match=r"^time_weight: applies only to a free final time"):
        dataclasses.replace(problem, final_time=None)
    with pytest.raises(ValueError, match=r"^time_weight: must be a finite number >= 0"):
        dataclasses.replace(problem, time_weight=-1.0)
    with pytest.raises(ValueError, match="time_weight applies only to a free final time"):
        MsShape(problem.model, 10, 0.1, (0, 1), time_weight=1.0)


def test_command_line_under_mpirun_gives_the_serial_answer(min_time, tmp_path):
    """``--problem min-time --mode ms`` on 2 MPI ranks: result.json reports the final time, the
    array file's time is the answer's real time (agent 0's in ``plan_time``), bitwise the
    serial API's; ``--mode pbms`` (the default) is refused in one line, exit 2."""
    args = ["-m", "ocpar.pursuit", "--problem", "min-time", "--samples", "21", "--window", "10",
            "--update", "5", "--quiet"]
    proc = run_cli(*args, "--mode", "ms", "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "mpi" and data["free_final_time"] is True
    assert data["final_time"] == min_time.final_time and data["time"] == min_time.headline
    ds, _ = ocpar.load(tmp_path)
    np.testing.assert_array_equal(ds["time"].values, min_time.time)
    np.testing.assert_array_equal(ds["control"].values, min_time.u)
    np.testing.assert_array_equal(ds["plan_time"].values, make(samples=21).grid)
    refused = run_cli(*args, "--output", str(tmp_path / "refused"))
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        "ocpar.pursuit: error: mode pbms: the pursuit train needs a fixed final time (its "
        "agents intercept each other on one clock); solve a free final time with mode ms "
        "(--mode ms)"]


def test_packaged_example_runs_as_it_is(tmp_path, capsys):
    """``ocpar run pursuit-min-time`` (N = 301, the switch on a sample) with the energy set:
    the discrete time + energy optimum to 1e-8, in result.json."""
    out = tmp_path / "run"
    assert ocpar_main(["run", "pursuit-min-time", "--set", "energy=4", "--set",
                       f"output={out}", "--set", "quiet=true"]) == 0
    capsys.readouterr()
    data = json.loads((out / "result.json").read_text())
    final_time, cost = discrete_time_energy(4.0, 1.0, 300)
    assert data["status"] == "converged" and data["mode"] == "ms"
    assert data["final_time"] == pytest.approx(final_time, abs=1e-8)
    assert data["time_and_energy"] == pytest.approx(cost, abs=1e-8)
