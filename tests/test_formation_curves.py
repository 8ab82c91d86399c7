"""Formations on any closed curve: the curves, the coupling on them, the problem's checks and the
worked example (3-D point masses onto an ellipse in a tilted plane)."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import ellipe

from ocpar.bsp import open_backend
from ocpar.examples import formation_ellipse, formation_halo
from ocpar.formation import (
    Circle,
    Curve,
    DmocShape,
    Ellipse,
    FormationOptions,
    FormationProblem,
    ParametricCurve,
    PlaneCurve,
    solve_formation,
)
from ocpar.formation.couplings import potential
from ocpar.formation.couplings.potential import (
    coupling,
    coupling_expr,
    coupling_hessp,
    coupling_jacobian,
    relax,
)
from ocpar.formation.hierarchical import OuterObjective, solve_outer_offset
from ocpar.formation.ordering import optimal_ordering
from ocpar.formation.solve import check_applicable
from ocpar.models import PointMass

TILT = np.pi / 6
#: The example's ellipse, written out here independently of ocpar's curves.
CENTRE, A, B = np.array([0.0, 0.0, 10.0]), 6.0, 3.0
E1, E2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, np.cos(TILT), np.sin(TILT)])


def knot(phi):
    """A non-planar closed curve in 3-D (a (2, 3) torus knot)."""
    r = 2 + ca.cos(3 * phi)
    return ca.vertcat(r * ca.cos(2 * phi), r * ca.sin(2 * phi), ca.sin(3 * phi))


@pytest.fixture(scope="module")
def ellipse_runs():
    problem = formation_ellipse.make(agents=10, tilt=TILT)
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    return problem, hierarchical, monolithic


def test_ellipse_hierarchical_equals_monolithic(ellipse_runs):
    """The paper's equivalence theorem (§IV-B) on a curve that is not a circle."""
    _, hierarchical, monolithic = ellipse_runs
    assert hierarchical.converged, hierarchical.message
    assert monolithic.converged, monolithic.message
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-7)
    np.testing.assert_allclose(hierarchical.agent_costs, monolithic.agent_costs, rtol=1e-6)


def test_ellipse_coupling_is_met(ellipse_runs):
    """g(φ) = 0 to 1e-9 as the result reports it (scaled by ℓ²/n³), and against G and ℓ built
    here independently: the ellipse by hand, dG/dφ by CasADi, ℓ = 4a E(1 − b²/a²)."""
    _, hierarchical, monolithic = ellipse_runs
    n = 10
    phi = ca.SX.sym("phi", n)
    z = [CENTRE + A * ca.cos(phi[i]) * E1 + B * ca.sin(phi[i]) * E2 for i in range(n)]
    g = ca.gradient(sum(1 / ca.sumsqr(z[i] - z[j]) for i in range(n) for j in range(n)
                        if i != j), phi)
    scale = (4 * A * ellipe(1 - B**2 / A**2) / (2 * np.pi)) ** 2 / n**3
    for result in (hierarchical, monolithic):
        assert result.coupling_residual <= 1e-9
        independent = scale * np.abs(np.asarray(ca.Function("g", [phi], [g])(result.phi)))
        assert independent.max() <= 1e-9
        assert independent.max() == pytest.approx(result.coupling_residual, abs=1e-14)
        # the agents end on the ellipse, in its tilted plane, at rest
        ends = result.trajectories[:, -1] - CENTRE
        np.testing.assert_allclose((ends @ E1 / A) ** 2 + (ends @ E2 / B) ** 2, 1, atol=1e-12)
        np.testing.assert_allclose(ends @ np.cross(E1, E2), 0, atol=1e-12)
    data = hierarchical.to_dict()
    assert data["coupling_residual"] <= 1e-9 and data["equidistance_error"] is None
    # without the coupling the cheapest ends would differ: it is active
    unconstrained = scale * np.abs(np.asarray(ca.Function("g", [phi], [g])(
        hierarchical.phi + 0.05 * np.sin(np.arange(n)))))
    assert unconstrained.max() > 1e-4


def test_ellipse_outer_gradient_from_sensitivities_matches_finite_differences(ellipse_runs):
    """dĴ_i/dφ_i = dJ*_i/dq_N · z′(φ_i) on the tilted ellipse."""
    problem, _, _ = ellipse_runs
    phi = problem.initial_phi() + 0.1 * np.random.default_rng(1).standard_normal(10)
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        grad = objective.gradient(phi)
        step = 1e-6
        fd = np.array([(objective.value(phi + step * e) - objective.value(phi - step * e))
                       / (2 * step) for e in np.eye(10)])
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_ellipse_outer_hessian_diagonal_matches_central_differences(ellipse_runs):
    """d²J/dφ_i² = z′ᵀ H_pos z′ + ∇_pos J* · z″ on the tilted ellipse (z″ ≠ 0 along z′)."""
    problem, _, _ = ellipse_runs
    phi = problem.initial_phi() + 0.1 * np.random.default_rng(6).standard_normal(10)
    step = 1e-5
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        hessian = objective.hessian_diagonal(phi)
        fd = np.array([(objective.gradient(phi + step * e)[i]
                        - objective.gradient(phi - step * e)[i]) / (2 * step)
                       for i, e in enumerate(np.eye(10))])
    np.testing.assert_allclose(hessian, fd, rtol=1e-6)


def test_ellipse_newton_projects_by_relaxing_and_matches_sqp(ellipse_runs):
    """Off a circle c(φ) = 0 has isolated solutions: from the unrelaxed spread guess, the
    default outer solver's projection (relax) and one superstep reach the point SLSQP
    reaches in several, the same as from the relaxed initial guess."""
    problem, hierarchical, _ = ellipse_runs
    # one superstep of solves (none gathers the paths)
    assert hierarchical.supersteps == 1 and hierarchical.outer_iterations == 0
    spread = problem.curve.spread(1.5 * np.pi, (np.arange(10) - 4.5) / 10)
    assert np.max(np.abs(coupling(spread, problem.curve))) > 1e-6
    newton = solve_formation(problem, phi0=spread)
    sqp = solve_formation(problem, phi0=spread, options=FormationOptions(outer="sqp"))
    assert newton.converged and sqp.converged, (newton.message, sqp.message)
    assert newton.supersteps == 1 < sqp.supersteps
    assert newton.total_cost == pytest.approx(sqp.total_cost, rel=1e-10)
    assert newton.total_cost == pytest.approx(hierarchical.total_cost, rel=1e-10)
    np.testing.assert_allclose(newton.phi, sqp.phi, atol=1e-8)
    assert newton.coupling_residual <= 1e-12


def test_hessian_vector_product_of_the_potential_equals_the_dense_jacobian():
    phi = np.random.default_rng(7).uniform(0, 2 * np.pi, 40)
    v = np.random.default_rng(8).standard_normal(40)
    curve = formation_ellipse.make(agents=2, tilt=TILT).curve
    dense = coupling_jacobian(phi, curve) @ v
    np.testing.assert_allclose(coupling_hessp(phi, curve, v), dense,
                               atol=1e-12 * np.max(np.abs(dense)))


def test_relax_for_many_agents_reaches_the_dense_methods_potential(monkeypatch):
    """Newton with preconditioned CG (used above DENSE_RELAX_AGENTS) and trust-exact on the
    dense Hessian, from the same spread on the ellipse with 160 agents: c = 0 and the same G.
    (The smallest eigenvalue of dc/dφ, along a quasi-rotation, falls from 2e-4 at 20 agents
    to 2e-9 at 60 and below rounding at 150: the angles can differ along that mode.)"""
    n = 160
    problem = formation_ellipse.make(agents=n, tilt=TILT)
    spread = problem.curve.spread(1.5 * np.pi, (np.arange(n) - (n - 1) / 2) / n)
    dense = relax(spread, problem.curve)
    monkeypatch.setattr(potential, "DENSE_RELAX_AGENTS", 0)
    banded = relax(spread, problem.curve)
    assert np.max(np.abs(coupling(banded, problem.curve))) <= 1e-12
    assert np.all(np.diff(banded) > 0)
    assert potential.potential(banded, problem.curve) == pytest.approx(
        potential.potential(dense, problem.curve), rel=1e-12)


def test_sixty_agents_on_the_ellipse_in_one_superstep():
    result = solve_formation(formation_ellipse.make(agents=60, tilt=TILT))
    assert result.converged and result.supersteps == 1
    assert result.coupling_residual <= 1e-9


def test_ellipse_initial_guess_is_the_nearest_minimum_of_the_potential(ellipse_runs):
    """Starts along x1 seen from below the ellipse's centre: θ_c = −π/2 in its plane, the
    point there is φ_c = 3π/2 (to the sampling's 2π/1024); agents sorted by x1 are spread
    counter-clockwise, equidistant in arc length (to the interpolation's accuracy), then
    relaxed to a minimum of G: g = 0 with a positive definite Hessian, order kept."""
    problem, _, _ = ellipse_runs
    curve = problem.curve
    assert curve.parameter_at(-np.pi / 2) == pytest.approx(1.5 * np.pi, abs=np.pi / 1024)
    spread = curve.spread(1.5 * np.pi, (np.arange(10) - 4.5) / 10)
    arcs = [quad(lambda p: np.hypot(A * np.sin(p), B * np.cos(p)), a, b, epsabs=1e-12)[0]
            for a, b in zip(spread, np.append(spread[1:], spread[0] + 2 * np.pi), strict=True)]
    np.testing.assert_allclose(arcs, 4 * A * ellipe(1 - B**2 / A**2) / 10, rtol=1e-4)
    phi0 = problem.initial_phi()
    assert np.all(np.diff(phi0) > 0) and phi0[-1] - phi0[0] < 2 * np.pi
    assert np.max(np.abs(coupling(phi0, curve))) <= 1e-12
    assert np.min(np.linalg.eigvalsh(coupling_jacobian(phi0, curve))) > 0
    np.testing.assert_allclose(phi0, spread, atol=0.05)  # the spread was close already


@pytest.mark.parametrize("curve", [
    Ellipse(semi_axes=(A, B), center=CENTRE, axes=np.array([E1, E2])),
    ParametricCurve(knot, name="knot"),
    PlaneCurve(lambda p: (ca.cos(p) * (1 + 0.5 * ca.cos(p)), ca.sin(p)), np.array([1.0, 2.0])),
])
def test_closed_form_coupling_equals_automatic_differentiation(curve):
    phi = np.random.default_rng(3).uniform(0, 2 * np.pi, 7)
    sym = ca.SX.sym("phi", 7)
    expr = coupling_expr(sym, curve)
    value, jacobian = (np.asarray(v) for v in ca.Function("c", [sym], [expr, ca.jacobian(
        expr, sym)])(phi))
    assert value.shape == (7, 1)  # not a circle: all n equations are kept
    np.testing.assert_allclose(coupling(phi, curve), value.ravel(), rtol=1e-11, atol=1e-14)
    np.testing.assert_allclose(coupling_jacobian(phi, curve), jacobian, rtol=1e-10,
                               atol=1e-13 * np.abs(jacobian).max())


def test_curves_from_a_casadi_function_and_a_python_function_agree():
    phi = ca.SX.sym("phi")
    function = ca.Function("z", [phi], [CENTRE + A * ca.cos(phi) * E1 + B * ca.sin(phi) * E2])
    angles = np.linspace(0, 2 * np.pi, 9)
    ellipse = Ellipse(semi_axes=(A, B), center=CENTRE, axes=np.array([E1, E2]))
    for curve in (ParametricCurve(function), ParametricCurve(lambda p: function(p))):
        np.testing.assert_allclose(curve.points(angles), ellipse.points(angles), atol=1e-14)
        np.testing.assert_allclose(curve.tangents(angles), ellipse.tangents(angles), atol=1e-14)
        assert curve.length_scale == pytest.approx(ellipse.length_scale, rel=1e-13)
    assert ellipse.length_scale == pytest.approx(4 * A * ellipe(1 - B**2 / A**2) / (2 * np.pi),
                                                 rel=1e-13)
    assert Circle(radius=2.5).length_scale == 2.5


def test_circle_shortcuts_are_refused_on_other_curves(ellipse_runs):
    """``offset`` is a circle's; ``optimal`` ordering elsewhere is the search over critical
    sets (tests/test_critical_sets.py), no longer refused."""
    problem, hierarchical, _ = ellipse_runs
    with pytest.raises(ValueError, match="only applies to a formation on a Circle"):
        solve_formation(problem, options=FormationOptions(outer="offset"))
    check_applicable(problem, FormationOptions(ordering="optimal"))
    with pytest.raises(ValueError, match="outer 'offset'"):
        check_applicable(problem, FormationOptions(outer="offset"))
    check_applicable(problem, FormationOptions(mode="monolithic", outer="offset"))  # unused
    check_applicable(formation_halo.make(agents=2), FormationOptions(outer="offset"))
    with open_backend("serial") as backend:
        with pytest.raises(ValueError, match="Circle"):
            optimal_ordering(problem, backend)
        with pytest.raises(ValueError, match="Circle"):
            solve_outer_offset(OuterObjective(problem, backend), hierarchical.phi, 1e-12, 10)


def test_per_agent_final_velocities_hierarchical_equals_monolithic():
    """Final velocities given per agent (n, nq), on a circle."""
    n = 4
    problem = FormationProblem(
        name="moving", shape=DmocShape(PointMass(dim=2), 10, 1.0),
        curve=Circle(radius=3.0, center=np.array([10.0, 0.0])),
        starts=np.column_stack([np.linspace(-2, 2, n), np.zeros(n)]),
        final_velocity=np.column_stack([np.zeros(n), np.linspace(1, 2, n)]))
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and monolithic.converged
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert hierarchical.coupling_residual <= 1e-9


class BrokenForce(PointMass):
    def generalized_force(self, q, u):
        return u @ q  # (2, 1) @ (2, 1): does not evaluate


class WrongForce(PointMass):
    def generalized_force(self, q, u):
        return ca.sum1(u)


def _point_masses(**changes):
    fields = {"name": "bad", "shape": DmocShape(PointMass(dim=2), 10, 1.0),
              "curve": Circle(radius=1.0), "starts": np.zeros((3, 2))} | changes
    return FormationProblem(**fields)


@pytest.mark.parametrize(("build", "field"), [
    (lambda: ParametricCurve(lambda p: ca.vertcat(p, ca.sin(p))), "not closed"),
    (lambda: ParametricCurve(lambda p: ca.vertcat(ca.cos(p), "x")), "does not evaluate"),
    (lambda: ParametricCurve(lambda p: ca.vertcat(ca.cos(p), ca.sqrt(ca.sin(p)))),
     "not finite"),
    (lambda: ParametricCurve(lambda p: ca.vertcat(ca.cos(p), ca.sin(p), p * 0, p * 0)),
     "2-D or 3-D"),
    (lambda: ParametricCurve(lambda p: ca.vertcat(1.0, 2.0) + 0 * p), "single point"),
    (lambda: ParametricCurve(3.0), "callable"),
    (lambda: Circle(radius=-1.0), "radius"),
    (lambda: Circle(radius="ten"), "radius"),
    (lambda: Ellipse(semi_axes=("a", 1.0)), "semi_axes"),
    (lambda: Circle(center="origin"), "center"),
    (lambda: Ellipse(semi_axes=(1.0, np.inf)), "semi_axes"),
    (lambda: Circle(radius=1.0, center=np.array([0.0, np.nan])), "center"),
    (lambda: Circle(radius=1.0, center=np.zeros(3), axes=np.array([[1.0, 0, 0], [1.0, 0, 0]])),
     "axes"),
    (lambda: _point_masses(starts=np.zeros((1, 2))), "starts: a formation needs at least 2"),
    (lambda: _point_masses(starts=np.zeros(2)), "starts: must have shape"),
    (lambda: _point_masses(starts=np.zeros((3, 3))), "starts: must have shape"),
    (lambda: _point_masses(start_velocities=np.full((3, 2), np.nan)), "start_velocities"),
    (lambda: _point_masses(final_velocity=np.zeros(3)), "final_velocity"),
    (lambda: _point_masses(curve="circle"), "curve: must be a Curve"),
    (lambda: _point_masses(curve=Circle(radius=1.0, center=np.zeros(3))), "curve: lies in 3-D"),
    (lambda: _point_masses(shape="dmoc"), "shape"),
    (lambda: _point_masses(final_attitude=np.zeros(1)), "final_attitude"),
    (lambda: _point_masses(shape=DmocShape(BrokenForce(), 10, 1.0)), "shape: the model's"),
    (lambda: _point_masses(shape=DmocShape(WrongForce(), 10, 1.0)), "column of 2"),
])
def test_malformed_curves_and_problems_are_refused_naming_the_field(build, field):
    with pytest.raises(ValueError, match=field) as info:
        build()
    assert "\n" not in str(info.value)


def test_rigid_bodies_need_an_attitude_that_satisfies_their_constraints():
    halo = formation_halo.make(agents=2)
    fields = {"name": "rigid", "shape": halo.shape, "curve": halo.curve, "starts": halo.starts}
    with pytest.raises(ValueError, match="final_attitude: required"):
        FormationProblem(**fields)
    with pytest.raises(ValueError, match="final_attitude: violates"):
        FormationProblem(**fields, final_attitude=np.array([0.5, 0.0, 0.0, 0.0]))
    bad_starts = halo.starts.copy()
    bad_starts[0, 3:] = 0.0
    with pytest.raises(ValueError, match="starts: violates"):
        FormationProblem(**fields | {"starts": bad_starts}, final_attitude=halo.final_attitude)


def test_a_users_own_curve_subclass_is_checked_and_solved():
    """A Curve subclass written by a user: a limaçon-like closed curve, then an open one."""

    class Bean(Curve):
        dim = 2

        def point(self, phi):
            r = 10 + 2 * ca.cos(phi)
            return ca.vertcat(100 + r * ca.cos(phi), 100 + r * ca.sin(phi))

    class Open(Bean):
        def point(self, phi):
            return super().point(phi / 2)

    fields = {"name": "bean", "shape": DmocShape(PointMass(dim=2), 10, 1.0),
              "starts": np.column_stack([np.linspace(-30, 30, 6), np.zeros(6)])}
    hierarchical = solve_formation(FormationProblem(curve=Bean(), **fields))
    monolithic = solve_formation(FormationProblem(curve=Bean(), **fields),
                                 options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and monolithic.converged
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert max(hierarchical.coupling_residual, monolithic.coupling_residual) <= 1e-9
    with pytest.raises(ValueError, match="curve: not closed"):
        FormationProblem(curve=Open(), **fields)


@dataclass(frozen=True)
class SpringMass:
    """A user's own model: a unit mass on a spring to the origin in 3-D, pushed by a force u,
    L = ½|q̇|² − ½ k|q|²."""

    k: float = 0.5
    nq = 3
    nu = 3

    def lagrangian(self, q, qdot, interval=0):
        return 0.5 * ca.dot(qdot, qdot) - 0.5 * self.k * ca.dot(q, q)

    def generalized_force(self, q, u):
        return u


def test_a_users_own_model_on_a_tilted_ellipse():
    ellipse = Ellipse(semi_axes=(2.0, 1.0), center=np.array([0.0, 0.0, 3.0]),
                      axes=np.array([E1, E2]))
    problem = FormationProblem(name="springs", shape=DmocShape(SpringMass(), 10, 1.0),
                               curve=ellipse,
                               starts=np.outer(np.linspace(-1, 1, 5), [1.0, 0.5, 0.0]),
                               start_velocities=np.ones((5, 3)))
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and monolithic.converged
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert max(hierarchical.coupling_residual, monolithic.coupling_residual) <= 1e-9
    np.testing.assert_allclose(hierarchical.trajectories[:, -1],
                               ellipse.points(hierarchical.phi), atol=1e-12)


def test_circle_closed_form_matches_the_generic_curve_evaluation():
    """The circle's numpy z, z′, z″ against the compiled CasADi derivatives every curve has,
    on a tilted circle in 3-D."""
    from ocpar.formation.targets.curve import Curve

    circle = Circle(radius=3.0, center=np.array([1.0, 2.0, 0.5]),
                    axes=np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]]))
    generic = Curve.evaluator.func(circle)   # the CasADi evaluator every curve has
    phi = np.random.default_rng(0).uniform(-7.0, 7.0, 50)
    for which in range(3):
        np.testing.assert_allclose(circle.evaluator.evaluate(phi, which),
                                   generic.evaluate(phi, which), rtol=0, atol=1e-14)
