"""Bad constraints, costs, obstacles and bounds from the command line: fuzzed like the problem
references (test_cli_problems.py). A user's factory builds a problem of each scheme from
``--problem-arg`` values drawn at random, valid or not; whatever is drawn, the run either gets
past validation (to the guard) when every part is valid, or stops with exit 2 and one line
``ocpar.<scheme>: error: ...`` that names the field and says ``ValueError`` (not a CasADi
error from deep inside, not a TypeError), before anything starts."""

from __future__ import annotations

import json
import math
import sys
import textwrap

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ocpar import driver
from ocpar.config import scheme_class

FACTORIES = textwrap.dedent('''
    """A user's problems whose constraints, cost, bounds and obstacles come as text."""
    import casadi as ca
    import numpy as np

    from ocpar.formation import Circle, DmocShape, FormationProblem
    from ocpar.formation.keep_out.obstacles import HalfSpace, Sphere
    from ocpar.macs import MacsProblem, Objective
    from ocpar.models import PointMass
    from ocpar.ocp.constraints import PathConstraint
    from ocpar.pursuit import PursuitProblem, SampledPlan

    from mypkg.problems import DoubleIntegrator


    def _value(text):
        """A --problem-arg string as Python (lambdas, lists, inf, nan), or None."""
        return None if text is None else eval(text, {"ca": ca, "np": np, "inf": np.inf,
                                                        "nan": np.nan})


    def _constraints(function, lower, upper):
        if function is None:
            return ()
        return (PathConstraint(_value(function), _value(lower), _value(upper), name="c"),)


    def formation(function=None, lower="-inf", upper="0.0", cost=None, bounds=None,
                  sphere=None, plane=None):
        sphere, plane = _value(sphere), _value(plane)
        starts = np.column_stack([np.linspace(-1.0, 1.0, 3), np.full(3, -3.0)])
        obstacles = ([Sphere(tuple(sphere[:-1]), sphere[-1])] if sphere is not None else []) + \\
            ([HalfSpace(tuple(plane[:-1]), plane[-1])] if plane is not None else [])
        shape = DmocShape(PointMass(dim=2, mass=1.0), 10, 1.0, solver="sqpmethod",
                          control_bounds=_value(bounds),
                          path_constraints=_constraints(function, lower, upper),
                          running_cost=_value(cost))
        return FormationProblem(name="fuzz", starts=starts, shape=shape,
                                curve=Circle(radius=2.0, center=np.zeros(2)),
                                obstacles=obstacles)


    def pursuit(function=None, lower="-inf", upper="0.0"):
        h = 0.05
        u = np.where(np.arange(80) < 40, -0.1, 0.1)
        x = [np.array([1.0, 0.0])]
        for uj in u:
            x.append(np.array([x[-1][0] + x[-1][1] * h + uj * h**2 / 2, x[-1][1] + uj * h]))
        return PursuitProblem(name="fuzz", model=DoubleIntegrator(), duration=4.0, samples=81,
                              initial_state=np.array([1.0, 0.0]), target_components=(0,),
                              target=np.array([0.0]), plan=SampledPlan(np.array(x), u[:, None]),
                              path_constraints=_constraints(function, lower, upper))


    def macs(function=None, lower="-inf", upper="0.0"):
        return MacsProblem(
            name="fuzz", model=DoubleIntegrator(),
            objectives=(Objective(mayer=lambda xf, tf: tf),
                        Objective(running=lambda x, u: u[0] ** 2)),
            initial_state=(0.0, 0.0), final_time=(2.5, 5.0), control_bounds=((-1.0, 1.0),),
            final_state={0: 1.0, 1: 0.0}, elements=2, order=2, control_order=1,
            path_constraints=_constraints(function, lower, upper))
''')

#: Constraint functions: per scheme (rows, checked[, norm]), absent where the function is
#: invalid for the scheme (the formation's u has 2 entries, the others' 1). ``checked``: the
#: scheme evaluates it before the solve, at the starts (formation: constraints of q alone), the
#: initial state (MACS: of x alone) or agent 0's plan (pursuit: every constraint); there
#: every function here takes values in (−1, 1), 0 at the starts and the initial state.
#: ``norm``: a norm, compiled as its square where its upper bound is ≥ 0; with upper < 0 it
#: stays a norm, not differentiable at the zero controls the formation's and MACS's solves
#: start from (pursuit's plan has u = ±0.1), so refused. A constant, a row vector (of more
#: than one entry) and a sqrt that is not a norm, zero at the zero controls, are refused.
FUNCTIONS = {
    "lambda u: u[0]": {"formation": (1, False), "pursuit": (1, True), "macs": (1, False)},
    "lambda u: ca.sumsqr(u)": {"formation": (1, False), "pursuit": (1, True),
                               "macs": (1, False)},
    "lambda u: u": {"formation": (2, False), "pursuit": (1, True), "macs": (1, False)},
    "lambda u: ca.norm_2(u)": {"formation": (1, False, True), "pursuit": (1, True),
                               "macs": (1, False)},   # of one entry: |u|, derivative 0 at 0
    "lambda u: np.linalg.norm(u)": {"formation": (1, False, True), "pursuit": (1, True),
                                    "macs": (1, False)},
    "lambda u: ca.sqrt(u[0] ** 2 + ca.sumsqr(u))": {"formation": (1, False, True),
                                                    "pursuit": (1, True),
                                                    "macs": (1, False, True)},
    "lambda u: ca.sqrt(1 - ca.cos(u[0]))": {"pursuit": (1, True)},
    "lambda u: u.T": {"pursuit": (1, True), "macs": (1, False)},   # a row only where nu > 1
    "lambda u: 0 * u[0] + 0.5": {},
    "lambda u: ca.vertcat(u[0], 0.5)": {},
    "lambda q: q[1] + 3": {"formation": (1, True)},
    "lambda x: x[1]": {"pursuit": (1, True), "macs": (1, True)},
    "lambda q, v, u: ca.vertcat(v[0], u[1])": {"formation": (2, False)},
    "lambda y: y[0]": {},
    "lambda: 1.0": {},
    "lambda u: ca.DM.ones(2, 2) * u[0]": {},
    "lambda u: undefined_name": {},
    "lambda u: u[7]": {},
    "lambda u: ca.SX.sym('w') * u[0]": {},
    "'not callable'": {},
    "lambda u: ca.DM.zeros(0, 1) * u[0]": {},
}
#: Bounds as --problem-arg text and what they are: (numbers or None if not numbers).
BOUNDS = ["-inf", "-1.0", "-5.0", "inf", "1.0", "5.0", "nan", "[-1.0, -2.0]",
          "[1.0, 2.0]", "[1.0, 2.0, 3.0]", "'abc'", "[]"]
#: Running costs: a constant (1/0 is one), a norm (not differentiable at u = 0, where the
#: solves start; a cost is not rewritten) and a cost not finite there are refused.
COSTS = {"lambda u: ca.sumsqr(u)": True, "lambda q, v, u: ca.sumsqr(u) + ca.sumsqr(v)": True,
         "lambda u: u": False, "lambda z: z[0]": False, "lambda u: 1 / (u[0] - u[0])": False,
         "lambda u: ca.norm_2(u)": False, "lambda u: 0 * u[0] + 2.0": False,
         "lambda u: 1 / ca.sumsqr(u)": False, "lambda u: ca.sumsqr(u) / (1 + ca.sumsqr(u))": True}
#: Box limits: the valid ones let a unit mass reach 30/4 = 7.5 per axis from rest to rest in
#: T = 1, past the 5 the farthest target may need (with 10 the formation is refused: three
#: targets 120° apart on the circle, one is always beyond 10/4 = 2.5 of its start).
CONTROL_BOUNDS = {"[[-30.0, 30.0], [-30.0, 30.0]]": True, "[[-30.0, 30.0]]": False,
                  "[[30.0, -30.0], [-30.0, 30.0]]": False, "[[nan, 30.0], [-30.0, 30.0]]": False,
                  '"wide"': False, "[[-inf, inf], [-30.0, 30.0]]": True,
                  "[[-inf, 30.0], [-30.0, 30.0]]": True,
                  # no formation (the line above): refused in one line, "no formation lets ..."
                  "[[-10.0, 10.0], [-10.0, 10.0]]": False,
                  # too weak: from rest to rest in T = 1 a unit mass reaches 0.25 < 1
                  "[[-1.0, 1.0], [-1.0, 1.0]]": False}
#: Obstacles: a sphere (centre x, y, radius) and a half-space (normal x, y, offset).
SPHERES = {"[10.0, 10.0, 1.0]": True, "[0.0, -3.0, 0.5]": False, "[10.0, 10.0, -1.0]": False,
           "[10.0, 10.0, 10.0, 1.0]": False, "[nan, 0.0, 1.0]": False,
           "[0.0, 0.0, 2.5]": "final positions"}   # the circle's final positions are inside
PLANES = {"[0.0, -1.0, -10.0]": True, "[0.0, 0.0, 1.0]": False, "[0.0, 1.0, 0.0]": False}


def numbers(text: str) -> list[float] | None:
    """The bound ``text`` as a list of floats, or None if it is not numbers."""
    if text.startswith("'"):
        return None
    values = text.strip("[]").split(",") if text.strip("[]") else []
    return [float(v) for v in values] if text.startswith("[") else [float(text)]


def valid_bounds(lower: str, upper: str, rows: int, checked: bool, norm: bool = False) -> bool:
    """The rule of ``PathConstraint`` bounds: numbers, one or ``rows`` each, no NaN,
    lower ≤ upper row by row, lower < inf and upper > −inf (else no value meets the row);
    and where the scheme checks the function's values (``checked``, all in (−1, 1)),
    lower ≤ −1 and upper ≥ 1 (the bounds drawn are ±1, ±5 and ±inf); a ``norm`` checked at
    zero controls needs upper ≥ 0 (to be compiled as its square)."""
    lo, hi = numbers(lower), numbers(upper)
    if lo is None or hi is None or len(lo) not in (1, rows) or len(hi) not in (1, rows):
        return False
    lo, hi = lo * (rows // len(lo)), hi * (rows // len(hi))
    if any(math.isnan(v) for v in lo + hi) or any(a > b for a, b in zip(lo, hi, strict=True)):
        return False
    if max(lo) == math.inf or min(hi) == -math.inf:
        return False
    if norm and min(hi) < 0:
        return False
    return not checked or (max(lo) <= -1.0 and min(hi) >= 1.0)


@pytest.fixture(scope="module")
def package(tmp_path_factory, user_package):
    """fuzzpkg.problems importable (with the user package mypkg it builds on)."""
    site = tmp_path_factory.mktemp("fuzz_site")
    (site / "fuzzpkg").mkdir()
    (site / "fuzzpkg" / "__init__.py").write_text("")
    (site / "fuzzpkg" / "problems.py").write_text(FACTORIES)
    sys.path[:0] = [str(site), str(user_package)]
    yield
    sys.path.remove(str(site))
    sys.path.remove(str(user_package))
    for name in [m for m in sys.modules if m.startswith(("fuzzpkg", "mypkg"))]:
        del sys.modules[name]


@pytest.fixture
def guarded(package, monkeypatch):
    """Starting a backend or solving fails the test with "passed validation"."""
    def called(*args, **kwargs):
        raise AssertionError("run_on_backend called: the input passed validation")
    monkeypatch.setattr(driver, "run_on_backend", called)


def outcome(scheme: str, args: dict[str, str], capsys) -> str | None:
    """Run ``--problem fuzzpkg.problems:<scheme>`` with ``args``: None if it got past
    validation, else its one error line (asserting exit 2, nothing on stdout, one line)."""
    argv = ["--problem", f"fuzzpkg.problems:{scheme}", "--quiet"]
    for key, value in args.items():
        argv += ["--problem-arg", f"{key}={json.dumps(value)}"]   # a TOML string
    capsys.readouterr()
    try:
        driver.main(scheme_class(scheme), argv)
    except AssertionError as exc:
        assert "passed validation" in str(exc)
        return None
    except SystemExit as exc:
        out, err = capsys.readouterr()
        assert exc.code == 2 and out == "" and "Traceback" not in err, (args, err)
        # the error is one line (ocpar's warnings before it are one line each, e.g. a norm
        # solved as its square)
        lines = [line for line in err.splitlines()
                 if not line.startswith(f"ocpar.{scheme}: warning: ")]
        assert len(lines) == 1 and lines[0].startswith(f"ocpar.{scheme}: error: "), (args, err)
        return lines[0]
    raise AssertionError(f"{args}: neither refused nor passed")


def expect(args: dict[str, str], line: str | None, fields: list[str]) -> None:
    """Valid input (no ``fields`` at fault) gets past validation; invalid input is one line
    naming one of the ``fields``: a ValueError of the factory's problem, or of the checks
    before the run (the final positions of the initial angles)."""
    if not fields:
        assert line is None, (args, line)
    else:
        assert line is not None, f"{args} passed validation"
        assert ("raised ValueError: " in line or "final positions" in fields
                or "no formation lets" in line) \
            and any(f in line for f in fields), (args, line)


@pytest.mark.parametrize("scheme", ["formation", "pursuit", "macs"])
@settings(max_examples=90, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(function=st.sampled_from(sorted(FUNCTIONS)), lower=st.sampled_from(BOUNDS),
       upper=st.sampled_from(BOUNDS))
def test_fuzzed_path_constraints(scheme, function, lower, upper, guarded, capsys):
    known = FUNCTIONS[function].get(scheme)
    args = {"function": function, "lower": lower, "upper": upper}
    line = outcome(scheme, args, capsys)
    valid = known is not None and valid_bounds(lower, upper, *known)
    expect(args, line, [] if valid else ["path_constraints"])


@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cost=st.sampled_from([None, *sorted(COSTS)]),
       bounds=st.sampled_from([None, *sorted(CONTROL_BOUNDS)]),
       sphere=st.sampled_from([None, *sorted(SPHERES)]),
       plane=st.sampled_from([None, *sorted(PLANES)]))
def test_fuzzed_formation_costs_bounds_and_obstacles(cost, bounds, sphere, plane, guarded,
                                                     capsys):
    """A running cost, control bounds, a sphere and a half-space, each valid or not; a cost
    is checked, with its gradient, at each agent's start with zero controls."""
    args = {key: value for key, value in (("cost", cost), ("bounds", bounds),
                                          ("sphere", sphere), ("plane", plane)) if value}
    line = outcome("formation", args, capsys)
    parts = [("running_cost", cost, COSTS), ("control_bounds", bounds, CONTROL_BOUNDS),
             ("obstacle", sphere, SPHERES), ("obstacle", plane, PLANES)]
    invalid = [table[value] if isinstance(table[value], str) else field
               for field, value, table in parts if value is not None and table[value] is not True]
    expect(args, line, invalid)
