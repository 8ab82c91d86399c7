"""Models from CasADi expressions (``ocpar.models.ode_model``, ``lagrangian_model``): checked
when built, equal and hashed by content, pickled as ocpar objects; a user's module of them runs
on a Dask cluster whose workers cannot import it, bitwise as serially, for every scheme, and
under ``mpirun -n 2``; the results equal those of the hand-written models."""

from __future__ import annotations

import dataclasses
import importlib
import json
import pickle
import re
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import REPO, run_ocpar

import ocpar
from ocpar.bsp import open_backend
from ocpar.examples import pursuit_van_der_pol as van_der_pol
from ocpar.formation import Circle, FormationProblem, solve_formation
from ocpar.macs import MacsSettings, solve_macs
from ocpar.models import (
    ExpressionLagrangian,
    ExpressionOde,
    MechanicalSystem,
    OdeModel,
    PointMass,
    RelativeRigidSpacecraft,
    lagrangian_model,
    ode_model,
)
from ocpar.models.labels import model_name
from ocpar.models.ode import check_ode_model
from ocpar.ocp import DmocShape, OcpTask, solve_task
from ocpar.pursuit import PursuitSettings, solve_pursuit

#: The user's module: a van der Pol pursuit, a double-integrator MACS problem and a formation
#: of point masses, every model built from CasADi expressions (nothing to install).
USER_MODULE = '''
"""A user's problems with models written as CasADi expressions (and functions of its own:
agent 0's control law, a path constraint, MACS objectives)."""
from functools import partial

import casadi as ca
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.macs import MacsProblem, Objective
from ocpar.models import PointMass, lagrangian_model, ode_model
from ocpar.ocp.constraints import PathConstraint
from ocpar.pursuit import ControlLaw, PursuitProblem


def van_der_pol(mu=1.0, u_max=1.0):
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u")
    return ode_model(x, u, [x[1], mu * (1 - x[0] ** 2) * x[1] - x[0] + u[0]],
                     x[0] ** 2 + x[1] ** 2 + u[0] ** 2, control_bounds=(-u_max, u_max))


def flat_law(duration, t):
    s = t / duration
    x1, v, a = 1 - 3 * s**2 + 2 * s**3, 6 * (s**2 - s) / duration, 6 * (2 * s - 1) / duration**2
    return np.array([a - (1 - x1**2) * v + x1])


def speed(x):
    return x[1]


def make_pursuit(samples=41, duration=4.0):
    return PursuitProblem(
        name="van-der-pol-floor", model=van_der_pol(), duration=duration, samples=samples,
        initial_state=np.array([1.0, 0.0]), target_components=(0, 1), target=np.zeros(2),
        plan=ControlLaw(partial(flat_law, duration)), integrator="rk4",
        path_constraints=(PathConstraint(speed, lower=-0.4, upper=np.inf,
                                         name="velocity floor"),))


def make_macs(distance=1.0):
    x, u = ca.MX.sym("x", 2), ca.MX.sym("u")   # MX works too: expanded to SX
    model = ode_model(x, u, ca.vertcat(x[1], u), state_names=("position", "speed"))
    t_min = 1.02 * np.sqrt(6 * distance)
    return MacsProblem(
        name="rest-to-rest", model=model,
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=lambda x, u: u[0] ** 2, name="energy")),
        initial_state=(0.0, 0.0), final_time=(t_min, 5.0), control_bounds=((-1.0, 1.0),),
        final_state={0: distance, 1: 0.0}, elements=4, order=3, control_order=1)


def point_mass(mass=1.0):
    q, v, u = ca.SX.sym("q", 2), ca.SX.sym("v", 2), ca.SX.sym("u", 2)
    return lagrangian_model(q, v, 0.5 * mass * ca.dot(v, v), u, u)


def make_formation(agents=3, radius=2.0, builtin=False):
    x = np.linspace(-1.0, 1.0, agents)
    model = PointMass(dim=2, mass=1.0) if builtin else point_mass()
    return FormationProblem(name=f"line-{agents}", starts=np.column_stack([x, -3 + 0.2 * x**2]),
                            shape=DmocShape(model, 10, 1.0),
                            curve=Circle(radius=radius, center=np.zeros(2)))
'''
MODULE = "ocpar_test_expression_user"


@pytest.fixture(scope="module")
def user_site(tmp_path_factory) -> Path:
    """A directory holding the user's module (on no worker's path)."""
    site = tmp_path_factory.mktemp("expression-user")
    (site / f"{MODULE}.py").write_text(USER_MODULE)
    return site


@pytest.fixture(scope="module")
def user(user_site):
    """The user's module, imported in this process only."""
    sys.path.insert(0, str(user_site))
    try:
        yield importlib.import_module(MODULE)
    finally:
        sys.path.remove(str(user_site))
        sys.modules.pop(MODULE, None)


def symbols(nx: int = 2, nu: int = 1) -> tuple[ca.SX, ca.SX]:
    return ca.SX.sym("x", nx), ca.SX.sym("u", nu)


# --- the models themselves ------------------------------------------------------------------

def test_an_ode_model_is_an_odemodel_equal_by_content_and_pickles():
    x, u = symbols()
    model = ode_model(x, u, [x[1], -x[0] + u], x[0] ** 2 + u**2, state_bounds=(-5, [5, 6]),
                      control_bounds=(-1, 1), state_names=("p", "v"), state_units=("m", "m/s"))
    assert isinstance(model, ExpressionOde) and isinstance(model, OdeModel)
    check_ode_model(model)
    np.testing.assert_array_equal(np.asarray(model.rhs([1.0, 2.0], 3.0)).ravel(), [2.0, 2.0])
    assert float(model.running_cost([1.0, 2.0], 3.0)) == 10.0
    np.testing.assert_array_equal(model.state_bounds()[1], [5.0, 6.0])
    y, w = symbols()   # new symbols of the same names: the same content
    again = ode_model(y, w, [y[1], -y[0] + w], y[0] ** 2 + w**2, state_bounds=(-5, [5, 6]),
                      control_bounds=(-1, 1), state_names=("p", "v"), state_units=("m", "m/s"))
    assert again == model and hash(again) == hash(model)
    copy = pickle.loads(pickle.dumps(model))
    assert copy == model and hash(copy) == hash(model)
    assert ode_model(x, u, [x[1], -x[0] + 2 * u]) != ode_model(x, u, [x[1], -x[0] + u])
    # the cache key: equal shapes of equal content are one transcription
    shape = DmocShape(point_mass(), 10)
    assert shape == DmocShape(point_mass(), 10) == pickle.loads(pickle.dumps(shape))
    assert hash(shape) == hash(pickle.loads(pickle.dumps(shape)))


def point_mass() -> ExpressionLagrangian:
    q, v, u = ca.SX.sym("q", 2), ca.SX.sym("v", 2), ca.SX.sym("u", 2)
    return lagrangian_model(q, v, 0.5 * ca.dot(v, v), u, u)


def test_mx_and_function_terms_give_the_sx_model():
    x, u = symbols()
    expected = ode_model(x, u, [x[1], ca.sin(x[0]) * u], u**2)
    xm, um = ca.MX.sym("x", 2), ca.MX.sym("u")
    from_mx = ode_model(xm, um, ca.vertcat(xm[1], ca.sin(xm[0]) * um), um**2)
    f = ca.Function("f", [x, u], [ca.vertcat(x[1], ca.sin(x[0]) * u)])
    from_function = ode_model(x, u, f, ca.Function("g", [x, u], [u**2]))
    for model in (from_mx, from_function):
        for point in ([0.3, -1.2], [2.0, 0.5]):
            np.testing.assert_array_equal(np.asarray(model.rhs(point, 0.7)),
                                          np.asarray(expected.rhs(point, 0.7)))
            assert float(model.running_cost(point, 0.7)) == float(expected.running_cost(point,
                                                                                      0.7))


def test_a_tabulated_mx_model_keeps_its_table():
    """An MX interpolant (tabulated data) stays a call inside the SX function: the model
    evaluates it, on numbers and on SX symbols, after a pickle too."""
    x, u = ca.MX.sym("x", 2), ca.MX.sym("u")
    table = ca.interpolant("drag", "linear", [[0.0, 1.0, 2.0, 3.0]], [0.0, 1.0, 4.0, 9.0])
    model = pickle.loads(pickle.dumps(ode_model(x, u, ca.vertcat(x[1], -table(x[1]) + u))))
    check_ode_model(model)
    np.testing.assert_allclose(np.asarray(model.rhs([0.0, 1.5], 1.0)).ravel(), [1.5, -1.5],
                               rtol=1e-15)
    xs, us = symbols()
    slope = ca.Function("slope", [xs, us], [ca.jacobian(model.rhs(xs, us)[1], xs)])
    np.testing.assert_allclose(np.asarray(slope([0.0, 2.5], 0.0)).ravel(), [0.0, -5.0])


@pytest.mark.parametrize(("build", "message"), [
    (lambda x, u: ode_model(x * 2, u, [x[1], u]), "x: must be a column of CasADi symbols"),
    (lambda x, u: ode_model(x, u, [x[1]]), r"rhs: shape \(1, 1\), expected \(2, 1\)"),
    (lambda x, u: ode_model(x, u, [x[1], u], ca.vertcat(u, u)), "cost: shape"),
    (lambda x, u: ode_model(x, u, [x[1], ca.SX.sym("w")]),
     "rhs: depends on symbols other than x, u: w"),
    (lambda x, u: ode_model(x, u, "u"), "rhs: not a CasADi expression"),
    (lambda x, u: ode_model(ca.MX.sym("x", 2), u, [x[1], u]), "mix SX and MX"),
    (lambda x, u: ode_model(x, u, [x[1], u], state_bounds=(1, 0)), "state_bounds: need lower"),
    (lambda x, u: ode_model(x, u, [x[1], u], control_bounds=(0, [1, 2])), "control_bounds"),
    (lambda x, u: ode_model(x, u, [x[1], u], state_names=("p",)), "state_names"),
    (lambda x, u: ode_model(x, u, [x[1], u], position_indices=(2,)), "position_indices"),
    (lambda x, u: lagrangian_model(x, ca.SX.sym("v", 3), x[0], u, x), "qdot: 3 entries"),
    (lambda x, u: lagrangian_model(x, ca.SX.sym("v", 2), u, u, x),
     "L: depends on symbols other than q, qdot: u"),
    (lambda x, u: lagrangian_model(x, ca.SX.sym("v", 2), x[0], u, x, cost_parts={"a": (0, 2)}),
     "cost_parts"),
])
def test_bad_input_is_one_line_naming_the_argument(build, message):
    with pytest.raises(ValueError, match=message) as exc:
        build(*symbols())
    assert "\n" not in str(exc.value)


def test_a_lagrangian_model_solves_as_the_class_it_is_written_from():
    """The rigid spacecraft's own L, F and c(q) (a unit quaternion) as expressions: the same
    DMOC solve to 1e-12 (with the same K on every interval), and the projection of the
    initial guess onto c(q) = 0."""
    rigid = RelativeRigidSpacecraft(((0.5, 0.1, 0.0, 0.1, -1.0, 0.0, 0.0, 0.0, 0.3),) * 8)
    q, v, u = ca.SX.sym("q", rigid.nq), ca.SX.sym("v", rigid.nq), ca.SX.sym("u", rigid.nu)
    model = lagrangian_model(q, v, rigid.lagrangian(q, v), u, rigid.generalized_force(q, u),
                             constraints=rigid.constraints(q),
                             position_indices=rigid.position_indices,
                             cost_parts=rigid.cost_parts)
    assert isinstance(model, MechanicalSystem) and model.n_constraints == 1
    assert model.cost_parts == rigid.cost_parts
    rows = np.random.default_rng(3).standard_normal((5, rigid.nq))
    np.testing.assert_allclose(model.project(rows), rigid.project(rows), atol=1e-12)
    start = np.r_[0.1, -0.2, 0.3, 1.0, 0.0, 0.0, 0.0]
    end = np.r_[0.5, 0.4, -0.1, np.cos(0.2), np.sin(0.2), 0.0, 0.0]
    params = np.r_[start, np.zeros(7), end, np.zeros(7)]
    ours, theirs = (solve_task(OcpTask(DmocShape(m, 8, 1.0, solver="ipopt"), params))
                    for m in (model, rigid))
    assert ours.success and theirs.success
    assert ours.cost == pytest.approx(theirs.cost, rel=1e-12)
    np.testing.assert_allclose(ours.q, theirs.q, atol=1e-10)


# --- a user's module of them, everywhere ----------------------------------------------------

@pytest.fixture(scope="module")
def serial_results(user):
    """Each scheme's serial result of the user's problems."""
    return {
        "pursuit": solve_pursuit(user.make_pursuit(), PURSUIT, reference=False),
        "macs": solve_macs(user.make_macs(), MACS),
        "formation": solve_formation(user.make_formation()),
    }


PURSUIT = PursuitSettings(window=21, update=10, epsilon=1e-4)
MACS = MacsSettings(max_evaluations=300, seed=1)


def test_results_equal_the_hand_written_models(serial_results, user):
    """Van der Pol with its speed floor as the packaged example's class gives the same
    pursuit to 1e-12; the Lagrangian point mass the built-in PointMass's formation."""
    example = solve_pursuit(van_der_pol.make_speed_limited(), PURSUIT, reference=False)
    ours = serial_results["pursuit"]
    assert ours.stop_reason == example.stop_reason == "certified_within_epsilon"
    assert ours.cost == pytest.approx(example.cost, rel=1e-12)
    np.testing.assert_allclose(ours.u, example.u, atol=1e-10)
    assert ours.x[:, 1].min() == pytest.approx(-0.4, abs=1e-8)   # the floor is active
    builtin = solve_formation(user.make_formation(builtin=True))
    formation = serial_results["formation"]
    assert formation.converged and builtin.converged
    assert formation.total_cost == pytest.approx(builtin.total_cost, rel=1e-12)
    np.testing.assert_allclose(formation.phi, builtin.phi, atol=1e-10)
    assert len(serial_results["macs"].front) >= 5


def test_on_a_dask_cluster_whose_workers_cannot_import_the_module(dask_cluster, user,
                                                                  serial_results):
    """The workers lack the user's module (checked), yet every scheme's run of its problems
    is bitwise the serial run: the models travel as ocpar objects, and a worker builds a
    shape's transcription once however often its model arrives."""
    from distributed import Client

    with Client(dask_cluster) as client, pytest.raises(ModuleNotFoundError, match=MODULE):
        client.run(importlib.import_module, MODULE)
    with open_backend("dask", workers=2, scheduler=dask_cluster) as backend:
        pursuit = solve_pursuit(user.make_pursuit(), PURSUIT, backend, reference=False)
        macs = solve_macs(user.make_macs(), MACS, backend)
        formation = solve_formation(user.make_formation(), backend)
        busy = np.sum([t.worker_tasks for t in backend.traces], axis=0)
        # a second run's shapes arrive as new objects of equal content: nothing is rebuilt
        before = backend.superstep("ocpar.ocp:cache_report", [None, None])
        again = solve_pursuit(user.make_pursuit(), PURSUIT, backend, reference=False)
        after = backend.superstep("ocpar.ocp:cache_report", [None, None])
    assert [a["builds"] for a in after] == [b["builds"] for b in before]
    assert sum(a["hits"] for a in after) > sum(b["hits"] for b in before)
    np.testing.assert_array_equal(again.u, pursuit.u)
    assert len(busy) == 2 and np.all(busy > 0)   # both workers solved inner problems
    serial = serial_results
    assert pursuit.headlines == serial["pursuit"].headlines
    np.testing.assert_array_equal(pursuit.u, serial["pursuit"].u)
    np.testing.assert_array_equal(macs.front, serial["macs"].front)
    assert macs.evaluations == serial["macs"].evaluations
    assert formation.total_cost == serial["formation"].total_cost
    np.testing.assert_array_equal(formation.phi, serial["formation"].phi)


def test_problems_with_such_models_unpickle_without_the_module(user, tmp_path):
    """The formation and MACS problems and the pursuit's model, pickled as Dask does
    (cloudpickle: the formation's curve holds a lambda), unpickle in a process that cannot
    import the user's module, into equal (hashable) models."""
    import cloudpickle

    blob = tmp_path / "problems.pickle"
    problems = (user.make_formation(), user.make_macs(), user.make_pursuit().model)
    blob.write_bytes(cloudpickle.dumps(problems))
    script = (f"import importlib.util, pickle; from pathlib import Path\n"
              f"assert importlib.util.find_spec({MODULE!r}) is None\n"
              f"a, b = (pickle.loads(Path({str(blob)!r}).read_bytes()) for _ in range(2))\n"
              "print(*(type(m).__name__ for m in (a[0].shape.model, a[1].model, a[2])), "
              "a[0].shape == b[0].shape and hash(a[0].shape) == hash(b[0].shape), "
              "a[1] == b[1] and hash(a[1]) == hash(b[1]), a[2] == b[2])\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["ExpressionLagrangian", "ExpressionOde", "ExpressionOde",
                                   "True", "True", "True"]


@pytest.mark.parametrize("backend", ["mpi", "dask"])
def test_by_reference_on_two_workers(backend, user_site, serial_results, dask_cluster,
                                     tmp_path):
    """``ocpar run`` of the user's formation by reference on two MPI ranks (each imports the
    reference) and on the Dask cluster (only the coordinator can import it): the serial run's
    total cost and angles."""
    config = tmp_path / "mine.toml"
    config.write_text(f'scheme = "formation"\nproblem = "{MODULE}:make_formation"\n'
                      f'quiet = true\n')
    where = ({"mpi_ranks": 2}, ()) if backend == "mpi" else \
        ({}, ("--backend", "dask", "--scheduler", dask_cluster))
    proc = run_ocpar(user_site, tmp_path, "run", str(config), "--output", str(tmp_path / "out"),
                     *where[1], **where[0])
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "out" / "result.json").read_text())
    assert data["workers"] == 2 and data["backend"] == backend
    assert data["total_cost"] == serial_results["formation"].total_cost
    assert data["phi"] == serial_results["formation"].phi.tolist()


def test_the_pages_example_runs():
    """docs/user-problems.md's "A model in a few lines" as written: its oscillator is an
    OdeModel and its formation of 80 kg masses costs what PointMass(mass=80)'s does."""
    text = (REPO / "docs" / "user-problems.md").read_text()
    section = text[text.index("### A model in a few lines"):text.index("### Names and units")]
    page: dict = {}
    exec(re.search(r"```python\n(.*?)```", section, re.S).group(1), page)
    check_ode_model(page["oscillator"])
    problem = page["make"]()
    builtin = dataclasses.replace(problem, shape=DmocShape(PointMass(dim=2, mass=80.0), 10, 1.0))
    ours, theirs = solve_formation(problem), solve_formation(builtin)
    assert ours.converged and theirs.converged
    assert ours.total_cost == pytest.approx(theirs.total_cost, rel=1e-12)


def test_a_named_model_is_named_in_the_results(tmp_path):
    """``name=`` names the model in the array file (``model_name``), so that two models from
    expressions in one fleet are told apart; without it, the class's name."""
    q, v, u = ca.SX.sym("q", 2), ca.SX.sym("v", 2), ca.SX.sym("u", 2)
    light = lagrangian_model(q, v, 0.5 * ca.dot(v, v), u, u, name="light")
    heavy = lagrangian_model(q, v, ca.dot(v, v), u, u, name="heavy")
    shapes = tuple(DmocShape(m, 10, 1.0) for m in (light, heavy, light))
    problem = FormationProblem(name="named", shape=shapes, curve=Circle(radius=2.0),
                               starts=np.array([[-1.0, -3.0], [0.0, -3.0], [1.0, -3.0]]))
    result = solve_formation(problem)
    assert result.status == "converged"
    result.write(tmp_path)
    ds, _ = ocpar.load(tmp_path)
    assert ds["model_name"].values.tolist() == ["light", "heavy"]
    assert ds["model"].values.tolist() == [0, 1, 0]
    assert model_name(point_mass()) == "ExpressionLagrangian"
    with pytest.raises(ValueError, match=r"^name: must be a string, got 3"):
        ode_model(*symbols(), [0, 0], name=3)
