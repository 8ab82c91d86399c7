"""The hierarchical formation scheme on the paper's first example."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from conftest import golden

from ocpar.bsp import open_backend
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import Circle, FormationOptions, solve_formation
from ocpar.formation.couplings.potential import (
    EXPANSION_RATIO,
    circle_coupling,
    coupling,
    coupling_expr,
    coupling_jacobian,
    equidistance_error,
    respace,
    within_expansion,
)
from ocpar.formation.hierarchical import OuterObjective
from ocpar.formation.verify import DIRECT_COUPLING_MAX_AGENTS, coupling_residual


def test_outer_gradient_from_sensitivities_matches_finite_differences():
    problem = paper_example(agents=6)
    rng = np.random.default_rng(0)
    phi = problem.initial_phi() + 0.1 * rng.standard_normal(6)
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        grad = objective.gradient(phi)
        step = 1e-6
        fd = np.array([
            (objective.value(phi + step * e) - objective.value(phi - step * e)) / (2 * step)
            for e in np.eye(6)
        ])
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_outer_hessian_diagonal_matches_central_differences_of_the_gradient():
    """d²J/dφ_i² from the inner KKT systems (and z″) against differences of dJ/dφ_i; the
    Hessian is diagonal: moving φ_j leaves dJ/dφ_i (i ≠ j) unchanged."""
    problem = paper_example(agents=6)
    phi = problem.initial_phi() + 0.1 * np.random.default_rng(2).standard_normal(6)
    step = 1e-5
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        hessian = objective.hessian_diagonal(phi)
        fd = np.array([(objective.gradient(phi + step * e) - objective.gradient(phi - step * e))
                       / (2 * step) for e in np.eye(6)])
    np.testing.assert_allclose(hessian, np.diag(fd), rtol=1e-6)
    assert np.max(np.abs(fd - np.diag(np.diag(fd)))) == 0.0


def test_respace_is_the_closed_form_projection_onto_equidistant_angles():
    """Equidistant angles in any agent order and on any branch come back unchanged; perturbed
    ones go to the equidistant family at their mean offset, order and branches kept."""
    rng = np.random.default_rng(5)
    n = 9
    slots = rng.permutation(n)
    equidistant = 0.4 + 2 * np.pi * slots / n + 2 * np.pi * rng.integers(-2, 3, n)
    np.testing.assert_allclose(respace(equidistant), equidistant, atol=1e-13)
    noise = 1e-3 * rng.standard_normal(n)
    projected = respace(equidistant + noise)
    assert equidistance_error(projected) < 1e-13
    np.testing.assert_allclose(projected, equidistant + np.mean(noise), atol=1e-7)


def test_closed_form_coupling_equals_the_symbolic_one():
    phi = np.random.default_rng(4).uniform(0, 2 * np.pi, 7)
    sym = ca.SX.sym("phi", 7)
    circle = Circle(radius=3.0)
    expr = coupling_expr(sym, circle)
    c = ca.Function("c", [sym], [expr, ca.jacobian(expr, sym)])
    value, jacobian = (np.asarray(v) for v in c(phi))
    np.testing.assert_allclose(coupling(phi, circle), value.ravel(), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(coupling_jacobian(phi, circle), jacobian, rtol=1e-11, atol=1e-14)


def test_coupling_vanishes_exactly_at_equidistant_angles():
    def c(phi):
        return coupling(phi, Circle(radius=10.0))

    def dc(phi):
        return coupling_jacobian(phi, Circle(radius=10.0))

    equidistant = 0.3 + 2 * np.pi * np.arange(60) / 60
    assert np.max(np.abs(np.asarray(c(equidistant)))) < 1e-12
    perturbed = equidistant.copy()
    perturbed[5] += 1e-3
    assert np.max(np.abs(np.asarray(c(perturbed)))) > 1e-6
    # rank n-1 after dropping one row: a common rotation is the only null direction
    assert np.linalg.matrix_rank(np.asarray(dc(equidistant))) == 59
    assert equidistance_error(equidistant) < 1e-13
    assert equidistance_error(perturbed) == pytest.approx(1e-3, rel=1e-6)


def long_double_coupling(phi: np.ndarray) -> np.ndarray:
    """c(φ) on a circle by the direct sum in long double: −(1/2n³) Σ_{j≠k} (w + w³),
    w = cot((φ_k − φ_j)/2) (n − 1,)."""
    angles = np.asarray(phi, np.longdouble)
    n = len(angles)
    w = 1 / np.tan((angles[:, None] - angles[None, :] + np.eye(n)) / 2)
    np.fill_diagonal(w, 0)
    return np.asarray(-(w + w**3).sum(axis=1) / (2 * np.longdouble(n) ** 3), float)[:-1]


@pytest.mark.parametrize("n, spread", [(500, 0.0), (501, 1e-12), (800, 1e-6),
                                       (1500, 0.4 * EXPANSION_RATIO)])
def test_circle_coupling_matches_the_direct_sum(n, spread):
    """Near-equidistant angles in any order, on any branch, on circles of any radius and
    centre: the O(n log n) expansion agrees with the direct sum (within its rounding) and
    with the direct sum in long double (closer still)."""
    rng = np.random.default_rng(n)
    phi = (rng.uniform(0, 7) + 2 * np.pi * rng.permutation(n) / n
           + spread * np.pi / n * rng.uniform(-1, 1, n) + 2 * np.pi * rng.integers(-2, 3, n))
    assert within_expansion(phi)
    fast = circle_coupling(phi)
    reference = long_double_coupling(phi)
    direct = coupling(phi, Circle(radius=3.0, center=np.array([1.0, -2.0])))
    scale = 1e-17 * n   # the direct sum's rounding: ~1e-15 at 500 agents
    np.testing.assert_allclose(direct, reference, rtol=0, atol=scale * 10)
    np.testing.assert_allclose(fast, reference, rtol=0, atol=scale)


def test_circle_coupling_refuses_angles_far_from_equidistant():
    phi = 2 * np.pi * np.arange(200) / 200
    phi[7] += 2 * EXPANSION_RATIO * np.pi / 200
    assert not within_expansion(phi)
    with pytest.raises(ValueError, match="from equidistant"):
        circle_coupling(phi)


def test_coupling_residual_above_the_direct_limit_uses_the_expansion():
    """Above the direct sum's limit on a circle: the expansion near equidistant angles, the
    direct sum (up to its own limit) elsewhere, the same value within rounding."""
    n = DIRECT_COUPLING_MAX_AGENTS + 1
    problem = paper_example(agents=n)
    phi = respace(problem.initial_phi())
    assert coupling_residual(problem, phi) == np.max(np.abs(circle_coupling(phi)))
    assert coupling_residual(problem, phi) < 1e-12
    far = phi + 0.1 * np.pi / n * np.sin(np.arange(n))
    assert coupling_residual(problem, far) == np.max(np.abs(coupling(far, problem.curve)))


def test_initial_guess_places_agents_sorted_by_x_counter_clockwise():
    problem = paper_example(agents=60)
    phi0 = problem.initial_phi()
    assert np.all(np.diff(phi0) > 0)  # starts are sorted by x already
    np.testing.assert_allclose(np.diff(phi0), 2 * np.pi / 60)
    assert np.mean(phi0) == pytest.approx(-3 * np.pi / 4)


@pytest.fixture(scope="module")
def sixty_agents():
    problem = paper_example(agents=60)
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    return hierarchical, monolithic


def test_hierarchical_equals_monolithic_sixty_agents(sixty_agents):
    """The paper's equivalence theorem (§IV-B) on its 60-point-mass example."""
    hierarchical, monolithic = sixty_agents
    assert hierarchical.converged, hierarchical.message
    assert monolithic.converged, monolithic.message
    assert hierarchical.total_cost == pytest.approx(
        monolithic.total_cost, rel=golden("formation-60.hierarchical_vs_monolithic").rel)
    np.testing.assert_allclose(hierarchical.phi, monolithic.phi, atol=1e-5)
    np.testing.assert_allclose(hierarchical.agent_costs, monolithic.agent_costs, rtol=1e-4)
    assert hierarchical.equidistance_error <= 1e-9
    assert monolithic.equidistance_error <= 1e-9


def test_offset_outer_solver_finds_the_sqp_optimum(sixty_agents):
    """Optimising only the common offset of the equidistant angles reaches SLSQP's optimum
    (the feasible set c(φ) = 0 near equidistant angles is that one-parameter family)."""
    sqp, _ = sixty_agents
    offset = solve_formation(paper_example(agents=60), options=FormationOptions(outer="offset"))
    assert offset.converged, offset.message
    assert offset.total_cost == pytest.approx(sqp.total_cost, rel=1e-11)
    np.testing.assert_allclose(offset.phi, sqp.phi, atol=1e-6)
    assert offset.equidistance_error <= 1e-12
    with pytest.raises(ValueError, match="equidistant"):
        solve_formation(paper_example(agents=4), phi0=np.array([0.0, 0.1, 0.2, 0.3]),
                        options=FormationOptions(outer="offset"))
    with pytest.raises(ValueError, match="unknown outer solver"):
        FormationOptions(outer="bfgs")


def test_newton_outer_solver_finds_the_papers_sqp_optimum(sixty_agents):
    """The default outer solver (projected Newton) reaches the optimum of the paper's SLSQP
    in a handful of supersteps (SLSQP: 10)."""
    newton, _ = sixty_agents
    sqp = solve_formation(paper_example(agents=60), options=FormationOptions(outer="sqp"))
    assert newton.converged and sqp.converged, (newton.message, sqp.message)
    assert FormationOptions().outer == "newton"
    assert newton.total_cost == pytest.approx(sqp.total_cost, rel=1e-10)
    assert newton.total_cost == pytest.approx(golden("formation-60.total_cost").value,
                                              rel=1e-10)
    np.testing.assert_allclose(newton.phi, sqp.phi, atol=1e-6)
    assert newton.supersteps <= 8 < sqp.supersteps
    assert newton.equidistance_error <= 1e-12


def test_newton_projects_a_start_that_is_not_equidistant(sixty_agents):
    """From perturbed angles (same order) the first projection restores equidistance and the
    same optimum follows."""
    newton, _ = sixty_agents
    problem = paper_example(agents=60)
    phi0 = problem.initial_phi() + 0.02 * np.random.default_rng(3).standard_normal(60)
    result = solve_formation(problem, phi0=phi0)
    assert result.converged, result.message
    assert result.total_cost == pytest.approx(newton.total_cost, rel=1e-10)
    np.testing.assert_allclose(result.phi, newton.phi, atol=1e-6)
    assert result.supersteps <= 8


def test_hierarchical_run_bookkeeping(sixty_agents):
    result, _ = sixty_agents
    # every superstep solves each agent once; no superstep gathers their paths (the
    # verification and the files take what they need where the paths are)
    assert result.inner_solves == 60 * result.supersteps
    assert result.failed_solves == 0
    assert len(result.trace) == result.supersteps > 1
    assert all(t.tasks == 60 for t in result.trace)
    ends = paper_example(60).final_positions(result.phi)
    np.testing.assert_allclose(result.trajectories[:, -1], ends)
    np.testing.assert_allclose(result.trajectories[:, 0, 0], np.linspace(-30, 30, 60))


def test_optimum_is_a_rotation_minimum():
    """For rest-to-rest straight-line transfers J(θ) is a sinusoid in the common rotation θ:
    the optimum must beat any rotated copy of itself."""
    problem = paper_example(agents=12)
    result = solve_formation(problem)
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        for dtheta in (-1e-2, 1e-2, 0.5):
            assert objective.value(result.phi + dtheta) > result.total_cost


def test_newton_leaves_a_maximum_of_the_rotation():
    """Started at the optimum rotated by π (with 12 agents the same slots, the assignment
    shifted by six: there dJ/dθ = 0 and d²J/dθ² < 0), the safeguarded Newton steps do not stop
    but descend to a minimum over the rotation; started at other rotations, to the optimum."""
    problem = paper_example(agents=12)
    best = solve_formation(problem)
    for rotation in (2.0, -2.5):
        result = solve_formation(problem, phi0=best.phi + rotation)
        assert result.converged, result.message
        assert result.total_cost == pytest.approx(best.total_cost, rel=1e-10)
        np.testing.assert_allclose(np.cos(result.phi - best.phi), 1.0, atol=1e-10)
        assert result.supersteps <= 15
    result = solve_formation(problem, phi0=best.phi + np.pi)
    assert result.converged and result.supersteps <= 15, result.message
    with open_backend("serial") as backend:
        objective = OuterObjective(problem, backend)
        assert result.total_cost < objective.value(best.phi + np.pi)
        for dtheta in (-1e-2, 1e-2):
            assert objective.value(result.phi + dtheta) > result.total_cost


def test_bad_problems_are_refused():
    with pytest.raises(ValueError, match="at least 2"):
        paper_example(agents=1)
    with pytest.raises(ValueError, match="radius"):
        paper_example(agents=4, radius=0.0)
    with pytest.raises(ValueError, match="mode"):
        FormationOptions(mode="parallel")
    with pytest.raises(ValueError, match="phi0"):
        solve_formation(paper_example(agents=4), phi0=np.zeros(3))


@pytest.mark.slow
@pytest.mark.parametrize("agents", [120, 200])
def test_hierarchical_equals_monolithic_many_agents(agents):
    problem = paper_example(agents=agents)
    hierarchical = solve_formation(problem)
    monolithic = solve_formation(problem, options=FormationOptions(mode="monolithic"))
    assert hierarchical.converged and monolithic.converged
    assert hierarchical.total_cost == pytest.approx(monolithic.total_cost, rel=1e-8)
    assert max(hierarchical.equidistance_error, monolithic.equidistance_error) <= 1e-9


@pytest.mark.parametrize("agents", [1, 60, 10_000, 10_001, 99_999, 100_000, 250_001])
def test_the_picture_draws_every_path_up_to_its_limit_and_at_most_that_many_above(agents):
    from ocpar.formation.plot import MAX_PATHS_DRAWN, SAMPLE_PATHS, path_step

    step = path_step(agents)
    drawn = len(range(0, agents, step))
    assert drawn <= MAX_PATHS_DRAWN
    assert step == 1 if agents <= MAX_PATHS_DRAWN else SAMPLE_PATHS // 2 < drawn <= SAMPLE_PATHS
