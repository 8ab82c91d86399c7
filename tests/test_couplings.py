"""Couplings as objects (:mod:`ocpar.formation.couplings.coupling`): equal arc length with a free
shift
and a user's g(φ) = 0, hierarchical against monolithic, against independent references, the
same on every backend, and bad couplings refused before anything runs."""

from __future__ import annotations

import json
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest
from conftest import run_cli, tool, user_environment
from scipy.integrate import quad
from scipy.special import ellipe

from ocpar.bsp import open_backend
from ocpar.bsp.serial import SerialBackend
from ocpar.examples.formation_ellipse import make as make_tilted
from ocpar.formation import (
    Circle,
    DmocShape,
    Ellipse,
    EqualArcLength,
    FormationOptions,
    FormationProblem,
    PotentialCoupling,
    UserCoupling,
    solve_formation,
)
from ocpar.formation.hierarchical import OuterObjective
from ocpar.models import PointMass

A, B = 3.0, 1.5


def planar(n: int, curve, coupling) -> FormationProblem:
    """n planar unit point masses at rest on a line below ``curve`` onto it, T = 2, N = 10."""
    starts = np.column_stack([np.linspace(-6.0, 6.0, n), np.full(n, -5.0)])
    return FormationProblem(name="coupled", shape=DmocShape(PointMass(dim=2), 10, 2.0),
                            curve=curve, starts=starts, coupling=coupling)


def ellipse_arc(phi: float) -> float:
    """Arc length of the ellipse (A cos φ, B sin φ) from 0 to φ, by adaptive quadrature."""
    return quad(lambda t: np.hypot(A * np.sin(t), B * np.cos(t)), 0.0, phi, limit=200,
                epsabs=1e-13, epsrel=1e-13)[0]


def test_arc_length_matches_the_complete_elliptic_integral_and_inverts():
    curve = Ellipse(semi_axes=(A, B), center=np.zeros(2))
    assert curve.length == pytest.approx(4 * A * ellipe(1 - (B / A) ** 2), rel=1e-13)
    phi = np.array([-1.0, 0.3, 2.0, 6.0, 7.5, 20.0])
    turns = np.floor(phi / (2 * np.pi))
    reference = [t * curve.length + ellipse_arc(p - 2 * np.pi * t)
                 for p, t in zip(phi, turns, strict=True)]
    np.testing.assert_allclose(curve.arc_lengths(phi), reference, rtol=0, atol=1e-12)
    np.testing.assert_allclose(curve.arc_lengths(phi, 1),
                               np.hypot(A * np.sin(phi), B * np.cos(phi)), rtol=1e-13)
    s = np.linspace(-3.0, 30.0, 9)
    np.testing.assert_allclose(curve.arc_lengths(curve.at_arc_lengths(s)), s, atol=1e-13)


def test_equal_arc_length_hierarchical_equals_monolithic_with_the_shift_chosen_by_the_cost():
    """The issue's check: same discretisation, same coupling, hierarchical (Newton in the
    shift alone) = monolithic IPOPT to 1e-8; the final points are equally spaced in arc
    length by an independent quadrature, and the shift moved from the initial guess."""
    n = 8
    problem = planar(n, Ellipse(semi_axes=(A, B), center=np.array([1.0, 2.0])), EqualArcLength())
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and monolithic.converged
    assert hierarchical.feasible_set == "continuous"
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, rtol=0, atol=1e-8)
    assert hierarchical.outer_iterations <= 5
    arcs = np.array([ellipse_arc(p) for p in np.sort(np.mod(hierarchical.phi, 2 * np.pi))])
    gaps = np.diff(np.append(arcs, arcs[0] + problem.curve.length))
    np.testing.assert_allclose(gaps, problem.curve.length / n, rtol=0, atol=1e-10)
    initial = problem.initial_phi()
    assert np.max(np.abs(hierarchical.phi - initial)) > 1e-3
    assert hierarchical.total_cost < OuterObjective(problem, SerialBackend()).value(initial)


def test_equal_arc_length_on_a_circle_is_the_potential_formation():
    """On a circle equal arc length and the paper's potential have the same feasible set:
    the same optimum (an independent route: the circle's closed-form respacing)."""
    circle = Circle(radius=4.0, center=np.array([0.0, 2.0]))
    arc = solve_formation(planar(7, circle, EqualArcLength()))
    paper = solve_formation(planar(7, circle, PotentialCoupling()))
    assert arc.total_cost == pytest.approx(paper.total_cost, rel=1e-10)


def paired(n: int):
    """A user's coupling with two free directions: pairs (0, 1), (2, 3), (4, 5) each a sixth
    of a turn apart in φ, and pair (2, 3) a third of a turn after pair (0, 1)."""
    def g(phi):
        return ca.vertcat(*[phi[i + 1] - phi[i] - 2 * np.pi / n for i in range(0, n - 1, 2)],
                          phi[3] - phi[1] - 4 * np.pi / n)
    return g


def test_a_users_coupling_hierarchical_equals_monolithic_and_sqp():
    n = 6
    problem = planar(n, Ellipse(semi_axes=(A, B), center=np.array([1.0, 2.0])),
                     UserCoupling(paired(n)))
    newton = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    sqp = solve_formation(problem, options=FormationOptions(outer="sqp", outer_tol=1e-14))
    assert newton.converged and monolithic.converged and sqp.converged
    assert newton.feasible_set == "continuous" and newton.coupling_residual < 1e-12
    assert newton.total_cost == pytest.approx(monolithic.total_cost, rel=1e-10)
    np.testing.assert_allclose(newton.phi, monolithic.phi, rtol=0, atol=1e-8)
    assert sqp.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)


def test_a_users_isolated_coupling_is_projected_and_reported_discrete():
    """n rows fix the formation: the outer solve is the projection, reported discrete."""
    n = 4
    problem = planar(n, Ellipse(semi_axes=(A, B), center=np.zeros(2)),
                     UserCoupling(lambda phi: phi - np.arange(n) * 2 * np.pi / n - 0.1))
    result = solve_formation(problem)
    assert result.converged and result.feasible_set == "discrete"
    np.testing.assert_allclose(result.phi, np.arange(n) * 2 * np.pi / n + 0.1, atol=1e-14)
    assert "user coupling's isolated solutions" in result.message


@pytest.mark.parametrize("g, words", [
    (lambda phi: ca.vertcat(phi, phi[0]), "coupling: g(phi) must be a column of 1 to 4 rows"),
    (lambda phi: phi.no_such_method(), "coupling: g(phi) does not evaluate"),
    (lambda phi: ca.log(-1 - phi[0] ** 2), "coupling: g(phi) is not finite"),
    (lambda phi: phi[0] ** 2 + 1, "coupling: no solution of g(phi) = 0 found"),
])
def test_bad_couplings_are_refused_in_one_line(g, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)")):
        solve_formation(planar(4, Ellipse(semi_axes=(A, B), center=np.zeros(2)),
                               UserCoupling(g)))


def test_the_arc_length_formation_is_the_same_on_every_backend(tmp_path):
    """12 masses onto the tilted ellipse, equal arc length: serial, 2 Dask workers and
    mpirun -n 2 (through the command line) bit for bit."""
    serial = solve_formation(make_tilted(agents=12, coupling="equal-arc-length"))
    assert serial.converged and serial.feasible_set == "continuous"
    with open_backend("dask", workers=2) as backend:
        dask = solve_formation(make_tilted(agents=12, coupling="equal-arc-length"), backend)
    assert dask.total_cost == serial.total_cost
    np.testing.assert_array_equal(dask.phi, serial.phi)
    proc = run_cli("-m", "ocpar.formation", "--problem",
                   "ocpar.examples.formation_ellipse:make", "--problem-arg", "agents=12",
                   "--problem-arg", 'coupling="equal-arc-length"', "--output", str(tmp_path),
                   mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    mpi = json.loads((tmp_path / "result.json").read_text())
    assert mpi["total_cost"] == serial.total_cost and mpi["phi"] == serial.phi.tolist()
    assert mpi["feasible_set"] == "continuous"


USER_MODULE = '''
import dataclasses

from ocpar.examples.formation_ellipse import make as tilted
from ocpar.formation import UserCoupling


def unreachable(agents: int = 6):
    """g(phi) = phi_0^2 + 1 = 0 has no real solution."""
    return dataclasses.replace(tilted(agents=agents),
                               coupling=UserCoupling(lambda phi: phi[0] ** 2 + 1))
'''


def test_a_coupling_without_a_solution_exits_2_before_any_worker(tmp_path):
    """Through the command line on mpirun -n 2: one line naming the coupling, exit 2, no
    result written."""
    (tmp_path / "coupkg.py").write_text(USER_MODULE)
    proc = subprocess.run([tool("mpirun"), "-n", "2", sys.executable, "-m", "ocpar.formation",
                           "--problem", "coupkg:unreachable", "--output", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=300,
                          env=user_environment(tmp_path))
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines()[-1].startswith(
        "ocpar.formation: error: coupling: no solution of g(phi) = 0 found from the initial "
        "guess")
    assert not (tmp_path / "out" / "result.json").exists()
