"""The inner solvers' own options (ocpar.ocp.solver_options): checked before any worker
starts, in effect in every transcription and scheme, set from Python, the command line, a
TOML configuration and the HTTP service, recorded in result.json."""

from __future__ import annotations

import json
import math

import casadi as ca
import numpy as np
import pytest
from conftest import assert_result_contract, run_cli

from ocpar.config import from_mapping
from ocpar.driver import main
from ocpar.examples.pursuit_van_der_pol import VanDerPol
from ocpar.formation.run import FormationRun
from ocpar.formation.solve import FormationOptions
from ocpar.macs.algorithm import MacsSettings
from ocpar.macs.run import MacsRun
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, MsShape, OcpTask, solve_tasks, transcription
from ocpar.ocp.solver_options import solver_options, used
from ocpar.pursuit.run import PursuitRun
from ocpar.pursuit.slp import PursuitSettings

#: van der Pol from (1, 0) to rest in 4 time units (40 Euler steps), its control far from
#: its bound: a nonlinear NLP that IPOPT, sqpmethod and Newton all solve.
VDP = VanDerPol(u_max=100.0)
VDP_PARAMS = np.array([1.0, 0.0, 0.0, 0.0])


def vdp_shape(**fields) -> MsShape:
    return MsShape(VDP, 40, 0.1, (0, 1), **fields)


@pytest.fixture(scope="module")
def vdp_optimum():
    """The default IPOPT solve (tol 1e-10)."""
    solution = transcription(vdp_shape()).solve(VDP_PARAMS)
    assert solution.success
    return solution


def ipopt_loads(linear_solver: str) -> bool:
    """Whether IPOPT, built here directly, solves a one-variable NLP with ``linear_solver``
    (an independent check of what the option check says)."""
    x = ca.SX.sym("x")
    solver = ca.nlpsol("s", "ipopt", {"x": x, "f": (x - 2) ** 2}, {
        "print_time": False, "ipopt": {"print_level": 0, "sb": "yes",
                                       "linear_solver": linear_solver}})
    solver(x0=0)
    return solver.stats()["return_status"] != "Invalid_Option"


# -- the check -----------------------------------------------------------------------------

def test_options_normalised_to_sorted_pairs():
    assert solver_options({"ipopt": {"tol": 1e-8, "linear_solver": "mumps"},
                           "newton.kkt_tol": 1e-9}) == (
        ("ipopt.linear_solver", "mumps"), ("ipopt.tol", 1e-8), ("newton.kkt_tol", 1e-9))
    assert solver_options(None) == solver_options({}) == ()


@pytest.mark.parametrize("given, message", [
    ({"ipopt.bogus": 1}, "unknown solver option ipopt.bogus (not an IPOPT option)"),
    ({"ipopt.tol": -1.0}, "solver option ipopt.tol: -1.0 is not a valid value "
                          "(expected 0 < tol <= +inf)"),
    ({"ipopt.tol": "tight"}, "solver option ipopt.tol: expected a number, got 'tight'"),
    ({"ipopt.max_iter": 2.5}, "solver option ipopt.max_iter: expected an integer, got 2.5"),
    ({"ipopt.print_level": 13}, "solver option ipopt.print_level: 13 is not a valid value "
                                "(expected 0 <= print_level <= 12)"),
    ({"ipopt.linear_solver": "nosuch"}, "solver option ipopt.linear_solver: 'nosuch' is not a "
     "valid value (expected one of ma27, ma57, ma77, ma86, ma97, pardiso, spral, mumps, "
     "custom)"),
    ({"sqpmethod.tol": 1e-8}, "unknown solver option sqpmethod.tol"),
    ({"sqpmethod.hessian_approximation": "bfgs"}, "solver option "
     "sqpmethod.hessian_approximation: 'bfgs' is not a valid value (expected one of "
     "limited-memory, exact)"),
    ({"sqpmethod.qpsol": "osqp"}, "unknown solver option sqpmethod.qpsol"),
    ({"qrqp.max_iter": -1}, "solver option qrqp.max_iter: expected a value >= 0, got -1"),
    ({"newton.kkt_tol": 0.0}, "solver option newton.kkt_tol: expected a positive value, got 0.0"),
    ({"newton.steps": 3}, "unknown solver option newton.steps; newton has kkt_tol, max_iter"),
    ({"snopt.tol": 1e-8}, "solver option 'snopt.tol': expected SOLVER.NAME with SOLVER one of "
                          "ipopt, sqpmethod, qrqp, newton"),
    ({"ipopt.tol": math.nan}, "solver option ipopt.tol: expected a finite scalar, got nan"),
])
def test_bad_options_refused_in_one_line(given, message):
    with pytest.raises(ValueError) as refused:
        solver_options(given)
    text = str(refused.value)
    assert "\n" not in text and text.startswith(message), text


def test_linear_solver_mumps_accepted_one_not_loadable_refused():
    assert solver_options({"ipopt.linear_solver": "mumps"}) == (
        ("ipopt.linear_solver", "mumps"),)
    # HSL's MA27 is accepted exactly where IPOPT can load it (not in this project's wheels)
    if ipopt_loads("ma27"):
        assert solver_options({"ipopt.linear_solver": "ma27"})
    else:
        with pytest.raises(ValueError, match=r"^solver option ipopt.linear_solver: 'ma27' "
                                             r"cannot be loaded on this host"):
            solver_options({"ipopt.linear_solver": "ma27"})


def test_each_scheme_refuses_bad_options_as_value_error():
    for make in (lambda o: FormationOptions(solver_options=o),
                 lambda o: PursuitSettings(solver_options=o),
                 lambda o: MacsSettings(solver_options=o),
                 lambda o: DmocShape(PointMass(), solver_options=o),
                 lambda o: vdp_shape(solver_options=o)):
        with pytest.raises(ValueError, match=r"unknown solver option ipopt\.bogus"):
            make({"ipopt.bogus": 1})
    with pytest.raises(ValueError, match="MACS's local searches are solved by IPOPT alone"):
        MacsSettings(solver_options={"sqpmethod.max_iter": 3})


# -- in effect -----------------------------------------------------------------------------

def test_ipopt_tol_changes_the_iterations_and_the_cost():
    # |u| <= 1 binds: IPOPT's barrier keeps a loose solve measurably inside the bound
    def solve(**options):
        shape = MsShape(VanDerPol(), 40, 0.1, (0, 1), solver_options=options)
        return transcription(shape).solve(VDP_PARAMS)

    default, loose, tight = solve(), solve(**{"ipopt.tol": 1e-2}), solve(**{"ipopt.tol": 1e-12})
    assert default.success and loose.success and tight.success
    assert loose.iterations < default.iterations < tight.iterations
    assert loose.cost - default.cost > 1e-5      # measurably off the optimum, above it
    assert abs(tight.cost - default.cost) < 1e-8


def test_defaults_given_explicitly_are_bitwise_the_defaults(vdp_optimum):
    same = transcription(vdp_shape(solver_options={"ipopt.tol": 1e-10,
                                                   "ipopt.max_iter": 1000})).solve(VDP_PARAMS)
    assert same.cost == vdp_optimum.cost and np.array_equal(same.w, vdp_optimum.w)


def test_newton_options_take_effect(vdp_optimum):
    guess = vdp_optimum.w + 0.1
    default = transcription(vdp_shape(warm_start=True)).solve(VDP_PARAMS, guess)
    assert default.success and default.iterations == 4     # two calls of two Newton steps
    loose = transcription(vdp_shape(warm_start=True, solver_options={
        "newton.kkt_tol": 1e-2})).solve(VDP_PARAMS, guess)
    assert loose.success and loose.iterations == 2          # accepted after one call
    assert abs(loose.cost - vdp_optimum.cost) > 1e-6
    short = transcription(vdp_shape(warm_start=True, solver_options={
        "newton.max_iter": 2})).solve(VDP_PARAMS, guess)
    assert short.success and short.iterations not in (2, 4)  # Newton stopped: IPOPT's answer
    assert abs(short.cost - vdp_optimum.cost) < 1e-9


def test_sqpmethod_options_take_effect(vdp_optimum):
    guess = vdp_optimum.w + 0.1
    shape = vdp_shape(warm_start=True, local_solver="sqp",
                      solver_options={"sqpmethod.max_iter": 1})
    nlp = transcription(shape)
    assert nlp.solver_settings["sqpmethod"]["max_iter"] == 1
    solution = nlp.solve(VDP_PARAMS, guess)
    assert nlp.resolver.stats()["iter_count"] == 1 and not nlp.resolver.stats()["success"]
    assert solution.success and abs(solution.cost - vdp_optimum.cost) < 1e-9  # IPOPT's


def test_dmoc_newton_tolerance_sends_the_batch_to_ipopt():
    params = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 0.0, 0.0])
    batched = solve_tasks([OcpTask(DmocShape(PointMass()), params)])[0]
    strict = solve_tasks([OcpTask(DmocShape(PointMass(), solver_options={
        "newton.kkt_tol": 1e-300}), params)])[0]
    assert batched.attempts == 1 and strict.attempts == 2   # the KKT check failed: IPOPT
    assert strict.success and abs(strict.cost - batched.cost) < 1e-9 * batched.cost


# -- the command line, configurations, result.json -------------------------------------------

@pytest.mark.parametrize("scheme, argv", [
    (FormationRun, ["--agents", "4"]), (PursuitRun, []), (MacsRun, [])])
@pytest.mark.parametrize("option, message", [
    ("ipopt.bogus=1", "unknown solver option ipopt.bogus (not an IPOPT option)"),
    ("ipopt.tol=-1", "solver option ipopt.tol: -1 is not a valid value")])
def test_command_line_refuses_in_one_line(scheme, argv, option, message, capsys):
    with pytest.raises(SystemExit) as exited:
        main(scheme, [*argv, "--solver-option", option])
    out, err = capsys.readouterr()
    assert exited.value.code == 2 and out == ""
    assert err.splitlines() == [f"{scheme.prog}: error: {err.split('error: ')[1].strip()}"]
    assert message in err


def test_toml_table_is_the_repeated_flag():
    flat = from_mapping({"scheme": "pursuit", "solver_options": {
        "ipopt.tol": 1e-8, "ipopt.linear_solver": "mumps"}}, "run.toml")
    nested = from_mapping({"scheme": "pursuit", "solver_options": {
        "ipopt": {"tol": 1e-8, "linear_solver": "mumps"}}}, "run.toml")
    assert flat.argv() == nested.argv() == [
        "--solver-option=ipopt.tol=1e-08", "--solver-option=ipopt.linear_solver=\"mumps\""]


def test_print_level_shows_ipopt_on_the_solving_process_and_result_records_options(tmp_path):
    out = tmp_path / "run"
    proc = run_cli("-m", "ocpar.formation", "--agents", "4", "--inner-solver", "ipopt",
                   "--solver-option", "ipopt.print_level=5", "--solver-option",
                   "ipopt.linear_solver=mumps", "--output", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "result.json").read_text())
    # serially, every inner solve is an IPOPT call of this process: one banner each
    assert proc.stdout.count("This is Ipopt version") == summary["inner_solves"] >= 4
    assert "iter    objective    inf_pr" in proc.stdout
    assert summary["solver_options"]["given"] == {"ipopt.linear_solver": "mumps",
                                                  "ipopt.print_level": 5}
    assert summary["solver_options"]["used"]["dmoc"]["ipopt"]["ipopt"] == {
        "print_level": 5, "sb": "yes", "tol": 1e-12, "max_iter": 500,
        "linear_solver": "mumps"}
    assert_result_contract(out)
    quiet = run_cli("-m", "ocpar.formation", "--agents", "4", "--inner-solver", "ipopt",
                    "--quiet")
    assert quiet.returncode == 0 and "Ipopt" not in quiet.stdout


@pytest.mark.parametrize("example, fields", [
    ("formation_point_masses", {"agents": 3}),                 # DMOC, newton
    ("formation_minimum_time", {"agents": 3}),                 # DMOC with |u| limited: sqpmethod
    ("formation_unicycles", {"agents": 3, "acceleration_limit": 1.0}),   # ODE agents, limited
    ("formation_unicycles", {"agents": 4, "mixed": True})])   # dmoc[0] and ms[1]
def test_formation_record_is_the_transcriptions_without_building_them(example, fields):
    import importlib

    from ocpar.formation.solve import solver_record

    problem = importlib.import_module(f"ocpar.examples.{example}").make(**fields)
    options = FormationOptions(solver_options={"ipopt.max_iter": 300})
    calls = transcription.cache_info()
    record = solver_record(problem, options)
    after = transcription.cache_info()
    assert (after.hits, after.misses) == (calls.hits, calls.misses)   # nothing built
    shapes = list(problem.agents_by_shape())
    built = {f"{'dmoc' if isinstance(s, DmocShape) else 'ms'}"
             f"{'' if len(shapes) == 1 else f'[{k}]'}": transcription(s).solver_settings
             for k, s in enumerate(shapes)}
    assert record == used(solver_options(options.solver_options), built)
    assert len(record["used"]) == len(shapes)


def test_pursuit_loose_tol_changes_the_full_horizon_answer():
    from ocpar.examples.pursuit_van_der_pol import make
    from ocpar.pursuit.solve import solve_pursuit

    problem = make()
    settings = {"window": 20, "update": 10}
    default = solve_pursuit(problem, PursuitSettings(**settings), mode="ms")
    loose = solve_pursuit(problem, PursuitSettings(**settings, solver_options={
        "ipopt.tol": 1e-2}), mode="ms")
    # the loose run stops not converged: its cost is withheld, its last iterate's kept
    assert default.status == "converged" and loose.status == "not_converged"
    assert np.isnan(loose.cost) and abs(loose.last_iterate["cost"] - default.cost) > 1e-5
    assert loose.to_dict()["solver_options"]["used"]["full_horizon"]["ipopt"]["ipopt"][
        "tol"] == 1e-2
    assert default.to_dict()["solver_options"] == {"given": {}, "used": {"full_horizon": {
        "ipopt": {"print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-10,
                                                 "max_iter": 1000,
                                                 "bound_relax_factor": 0.0}}}}}


# -- the service ---------------------------------------------------------------------------

def test_service_refuses_bad_and_disallowed_options(tmp_path):
    from fastapi.testclient import TestClient

    from ocpar.service.web.app import create_app
    from ocpar.service.web.runner import Settings
    from ocpar.service.web.store import Store, Token
    from ocpar.service.web.tokens import issue

    def server(settings: Settings, token: Token | None = None):
        secret = issue(Store(settings.state_dir), token or Token("alice"))
        client = TestClient(create_app(settings))   # no lifespan: no job starts

        def submit(options: dict) -> tuple[int, str]:
            response = client.post("/jobs", headers={"Authorization": f"Bearer {secret}"},
                                   json={"config": {"scheme": "formation", "agents": 4,
                                                    "solver_options": options}})
            return response.status_code, response.json().get("detail", "")

        return submit

    submit = server(Settings(state_dir=tmp_path / "a"))
    assert submit({"ipopt": {"tol": 1e-8}})[0] == 201
    assert submit({"ipopt.bogus": 1}) == (
        422, "unknown solver option ipopt.bogus (not an IPOPT option)")
    assert submit({"ipopt.output_file": "/tmp/x.txt"}) == (
        422, "solver_options: ipopt.output_file is not allowed on this server (the operator "
        "allows solver options with ocpar serve --allow-solver-option)")
    strict = server(Settings(state_dir=tmp_path / "b", allow_solver_option=("ipopt.*tol",)))
    assert strict({"ipopt.tol": 1e-8})[0] == 201
    status, detail = strict({"ipopt.print_level": 5})
    assert status == 422 and detail.startswith("solver_options: ipopt.print_level is not allowed")
    # a token's own list, within the server's
    bob = server(Settings(state_dir=tmp_path / "c"), Token("bob", solver_options=("ipopt.tol",)))
    assert bob({"ipopt.tol": 1e-8})[0] == 201
    assert bob({"ipopt.max_iter": 10}) == (
        422, "solver_options: ipopt.max_iter is not allowed to this token (ocpar serve token "
        "add --allow-solver-option)")
    assert Store(tmp_path / "c").token("bob").solver_options == ("ipopt.tol",)


def test_dfet_ocp_takes_ipopt_options():
    from test_dfet import final_time
    from test_transcriptions import DoubleIntegrator

    from ocpar.ocp import DfetOcpShape, solve_task

    def solve(**options):
        shape = DfetOcpShape(DoubleIntegrator(), 4, 2, 0, ((-1.0, 1.0),), (0.5, 5.0), (0, 1),
                             terminal_cost=final_time, running_cost=False,
                             solver_options=options)
        return solve_task(OcpTask(shape, np.array([0.0, 0.0, 1.0, 0.0])))

    default, capped = solve(), solve(**{"ipopt.max_iter": 2})
    assert default.success and default.final_time == pytest.approx(2.0, abs=1e-7)
    assert not capped.success and "Maximum_Iterations_Exceeded" in capped.status


def test_macs_searches_take_ipopt_options():
    from ocpar.macs.local_search import SearchTask, run_search
    from ocpar.macs.problems import make_problem
    from ocpar.ocp import dfet_problem

    problem = make_problem("double-integrator")
    dfet = dfet_problem(problem.shape)
    middle = (dfet.p_lower + dfet.p_upper) / 2
    default = run_search(SearchTask(problem, "restore", p0=middle))
    capped = run_search(SearchTask(problem, "restore", p0=middle,
                                   solver_options=solver_options({"ipopt.max_iter": 1})))
    assert default.feasible and default.iterations > 1
    assert not capped.feasible and capped.status == "Maximum_Iterations_Exceeded"
    assert capped.iterations == 1
