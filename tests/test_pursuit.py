"""Pursuit-based multiple shooting on the paper's orbit transfer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_result_contract, run_cli

from ocpar.bsp import open_backend
from ocpar.pursuit import OrbitTransferProblem, PursuitSettings, solve_pursuit
from ocpar.pursuit.slp import PursuitTrain


def test_feasible_trajectory_matches_the_papers_guess():
    """Eq. 16 integrated accurately: r(T) = 12.7778 Mm, θ̇(T) = 4.4e-4 rad/s, 53.5 kg fuel."""
    x, u = OrbitTransferProblem(case=1, samples=301).feasible_trajectory()
    assert x.shape == (301, 4) and u.shape == (300, 2)
    assert x[-1, 0] == pytest.approx(12.7778, abs=1e-3)
    assert x[-1, 2] / 60 == pytest.approx(4.4e-4, abs=5e-6)
    assert (0.525 - x[-1, 3]) * 1e3 == pytest.approx(53.5, abs=0.05)
    x2, _ = OrbitTransferProblem(case=2, samples=301).feasible_trajectory()
    assert x2[-1, 0] == pytest.approx(23.642, rel=0.02)  # paper: 23.642 Mm, 103 kg
    assert (0.525 - x2[-1, 3]) * 1e3 == pytest.approx(103, rel=0.05)


@pytest.fixture(scope="module")
def converged_small():
    """N = 101 with N_Δ = 32, N_δ = 16 (the paper's setting for N = 101: 746 agents)."""
    problem = OrbitTransferProblem(case=1, samples=101)
    return solve_pursuit(problem, PursuitSettings(window=32, update=16, epsilon_kg=1e-5))


def test_pbms_converges_monotonically_to_the_ms_optimum(converged_small):
    result = converged_small
    assert result.converged, result.message
    assert result.failed_solves == 0
    assert result.final_mass_kg == pytest.approx(result.reference_final_mass_kg, abs=0.01)
    masses = np.array(result.final_masses_kg[1:])  # agent 0 does not end on S_Q
    assert np.all(np.diff(masses) >= 0), "Theorem 1: cost decreases monotonically"
    assert 200 < result.agents < 3000
    assert result.constraint_violation < 1e-10
    assert result.max_agents_in_flight == 4  # about (N-1)/(N_Δ-1) = 3.2, rounded up by the schedule


def test_pbms_bookkeeping(converged_small):
    result = converged_small
    assert result.supersteps == len(result.trace)
    assert sum(t.tasks for t in result.trace) == result.subproblem_solves  # reference not traced
    assert result.peak_rss_mb_per_worker > 10
    assert abs(result.rk_final_altitude_error_m) < 50e3


def test_every_finished_agent_ends_on_the_target_set():
    problem = OrbitTransferProblem(case=1, samples=101)
    train = PursuitTrain(problem, PursuitSettings(window=32, update=16))
    finished = []
    with open_backend("serial") as backend:
        while len(finished) < 5:
            work = train.ready()
            sols = backend.superstep("ocpar.ocp:solve_task", [task for _, task in work])
            for (agent, _), sol in zip(work, sols, strict=True):
                train.apply(agent, sol)
                if agent.done:
                    finished.append(agent)
    for agent in finished:
        np.testing.assert_allclose(agent.x[-1, :3], problem.target, atol=1e-9)
        assert not np.isnan(agent.x).any()


@pytest.mark.parametrize(
    ("window", "update", "samples", "match"),
    [(101, 16, 101, "N_Δ"), (32, 32, 101, "N_δ"), (1, 1, 101, "N_Δ")],
)
def test_bad_settings_are_refused(window, update, samples, match):
    with pytest.raises(ValueError, match=match):
        PursuitSettings(window=window, update=update).check(samples)


SHORT = ["--samples", "101", "--window", "32", "--update", "16", "--max-agents", "12",
         "--no-reference", "--quiet"]


@pytest.fixture(scope="module")
def short_serial():
    problem = OrbitTransferProblem(case=1, samples=101)
    return solve_pursuit(problem, PursuitSettings(window=32, update=16, max_agents=12),
                         reference=False)


def test_results_identical_on_dask(short_serial):
    problem = OrbitTransferProblem(case=1, samples=101)
    with open_backend("dask", workers=2) as backend:
        result = solve_pursuit(problem, PursuitSettings(window=32, update=16, max_agents=12),
                               backend, reference=False)
    assert result.final_masses_kg == short_serial.final_masses_kg  # bitwise
    np.testing.assert_array_equal(result.u, short_serial.u)


def test_results_identical_under_mpirun(short_serial, tmp_path):
    proc = run_cli("-m", "ocpar.pursuit", *SHORT, "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 1, proc.stderr  # max_agents reached: not converged
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "mpi" and data["workers"] == 2
    assert data["final_masses_kg"] == short_serial.final_masses_kg
    assert data["supersteps"] == short_serial.supersteps


def test_ms_mode_command_line_contract(tmp_path):
    proc = run_cli("-m", "ocpar.pursuit", "--mode", "ms", "--output", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["scheme"] == "pursuit" and data["mode"] == "ms"
    assert data["final_mass_kg"] == pytest.approx(523.979819, abs=0.01)
    assert data["fuel_kg"] == pytest.approx(525 - data["final_mass_kg"])
    for key in ("agents", "subproblem_solves", "failed_solves", "supersteps",
                "max_agents_in_flight"):
        assert isinstance(data[key], int)
    assert 1e3 < data["rk_final_altitude_error_m"] < 20e3  # paper, N = 301: 7.9 km
    assert (tmp_path / "pursuit.png").read_bytes().startswith(b"\x89PNG")
    assert_result_contract(tmp_path)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--window", "301"], "N_Δ"),
        (["--samples", "50", "--window", "60"], "N_Δ"),
        (["--update", "60"], "N_δ"),
        (["--case", "3"], "--case"),
        (["--epsilon", "-1"], "--epsilon"),
        (["--mode", "dms"], "--mode"),
        (["--samples", "ten"], "--samples"),
    ],
)
def test_bad_command_lines_get_one_line_and_status_2(args, needle):
    proc = run_cli("-m", "ocpar.pursuit", *args, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_paper_case_1_n301():
    """Table II: N = 301, N_Δ = 60, N_δ = 32: PBMS within 0.01 kg of MS, agent count
    comparable to the paper's 3344."""
    problem = OrbitTransferProblem(case=1, samples=301)
    result = solve_pursuit(problem, PursuitSettings(window=60, update=32, epsilon_kg=1e-5))
    assert result.converged and result.failed_solves == 0
    assert result.final_mass_kg == pytest.approx(result.reference_final_mass_kg, abs=0.01)
    assert np.all(np.diff(result.final_masses_kg[1:]) >= 0)
    assert 1500 < result.agents < 7000
