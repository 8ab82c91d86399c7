"""The best formation where the coupling's solutions are isolated: every curve but a circle.

Off a circle the coupling g(φ) = ∂G/∂φ = 0 (:mod:`ocpar.formation.couplings.potential`) admits only
the
critical configurations of the potential G on the curve: a discrete set, which the initial
guess selects from (the default, the paper's method). G is symmetric in the agents, so each
critical configuration is a *set* of n points on the curve, and every assignment of the
agents to its points is feasible. :func:`best_isolated_formation` searches both choices:

1. **Critical sets**, on the coordinator: from the initial guess and from ``starts`` random
   angle vectors (seeded, so the same on every backend), either relaxation to a local
   minimum of G (``critical="stable"``: a stable, spread-out formation, checked by G's
   Hessian on the curve being positive definite) or Newton's method on g(φ) = 0
   (``critical="any"``: the paper's reading, saddles included). Results are sorted modulo
   2π and merged when they agree to :data:`SAME_SET_TOL` (rad) up to a cyclic shift.
2. **Assignments**, on the workers: for each of the M distinct sets S_m the table
   C[m, i, j] = Ĵ_i(S_m[j]) of n² inner optimal costs, all M tables in one superstep
   (:func:`~ocpar.formation.ordering.cost_tables`; a pair outside an exact reach set +∞
   without a solve), then the cheapest assignment of each
   (:func:`scipy.optimize.linear_sum_assignment`, exact).

On a surface the search runs in the surface's chart, except that a set found with a point
near a chart pole (where the azimuth does not move the point and c = 0 does not make it
critical) that is not critical in space, or not regular in the chart, is solved again in a
chart whose pole is far from every point
(:meth:`~ocpar.formation.targets.surface.EllipsoidSurface.charted_away`). Where the surface has
rotational symmetry (a sphere, an ellipsoid of revolution) the sets are isolated up to its
rotations, and each set's best rotation is searched by rotating its points rigidly in space
(:func:`~ocpar.formation.hierarchical.rotation_newton`), then re-charting them. Every
candidate is then checked from its own returned end points, in space, without the chart
(:func:`_verify`): a set whose points are not critical or whose points' potential is not the
one reported is dropped, and said so.

The best (set, assignment) is returned with every candidate set's cost. It is the global
optimum over the sets found; a set that no start reaches is not seen (the count of starts
that led to each set is reported, so a user can judge coverage).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.couplings.potential import (
    coupling_scale,
    point_potential,
    potential,
    surface_criticality,
)
from ocpar.formation.hierarchical import (
    ROUNDING_RTOL,
    InnerSolveFailed,
    OuterObjective,
    rotation_newton,
    tangent_newton,
)
from ocpar.formation.ordering import assignment_cost, cheapest_assignment, solved_tables
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.curve import Curve
from ocpar.formation.targets.surface import EllipsoidSurface, Surface

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

#: Random starts of the search besides the initial guess, at least (default)...
CRITICAL_STARTS = 32
#: ... then more until this many consecutive starts found no new set (the enumeration has
#: saturated: on the sphere's line-through-the-centre case the best set, the octagon, is first
#: reached by start 45 of 200, after 32 starts had found 10 of the 12 sets)...
SATURATION_STARTS = 32
#: ... or this many random starts in all.
MAX_CRITICAL_STARTS = 1024
#: The two readings of the coupling: local minima of G only, or every critical point.
CRITICAL_READINGS = ("stable", "any")
#: Two sets of sorted angles agreeing to this (rad), up to a cyclic shift, are one set.
SAME_SET_TOL = 1e-6
#: Newton's method on g = 0 (``any``) has converged at max |c_k| ≤ this (c scaled as
#: :func:`~ocpar.formation.couplings.potential.coupling`).
ROOT_TOL = 1e-10
#: A critical set on a surface counts only with every agent's ∂z/∂φ_i of rank 2, its smaller
#: singular value at least this times the length scale.
REGULAR_RTOL = 1e-6
#: On a surface with free directions: rounds of assignment and outer solve over them per
#: critical set, at most, and the outer solve's iterations per round.
ROTATION_ROUNDS, MAX_ROTATION_ITERATIONS = 5, 50
#: On a surface with rotational symmetry: the turns of each critical set the search over
#: rotations starts from (the set as found and seeded random rotations of it).
ROTATION_STARTS, ROTATION_SEED = 32, 0
#: A candidate is critical, checked from its returned points, when max_i |tangential ∇G_i|
#: ≤ this times max_i |∇G_i| (the gradient of G in the 3-D positions at the same points,
#: :func:`~ocpar.formation.couplings.potential.tangential_potential_gradient`).
CRITICAL_RTOL = 1e-8
#: ... and its reported potential (at the set as found) equals its points' to this, relative.
POTENTIAL_RTOL = 1e-9


@dataclass
class CriticalSet:
    """One critical configuration of G: ``phi`` (n,) its points' angles (rad, sorted in
    [0, 2π)), on a surface (2n,) their parameters as found; ``potential`` the scaled G there;
    ``min_eigenvalue`` the smallest eigenvalue of the scaled Hessian of G on the target
    across its symmetries (> 0: a stable formation); ``hits`` how many starts reached it;
    ``assignment`` (n,) the cheapest point index per agent and ``total_cost`` Σ_i Ĵ_i there
    (None until the tables are solved); ``rotated`` (2n,) on a sphere the set turned by the
    outer solve over its rotations, in agent order (``total_cost`` is there);
    ``points_potential`` and ``tangential_gradient`` on a surface the scaled G and the largest
    tangential |∇G| (length⁻³) of the returned points (:func:`_verify`); ``first_start`` the
    search that first reached it (0: the initial guess)."""

    phi: np.ndarray
    potential: float
    min_eigenvalue: float
    first_start: int = 0
    hits: int = 1
    assignment: np.ndarray | None = None
    total_cost: float | None = None
    rotated: np.ndarray | None = None
    points_potential: float | None = None
    tangential_gradient: float | None = None

    @property
    def stable(self) -> bool:
        return self.min_eigenvalue > 0

    def returned(self) -> np.ndarray:
        """The parameters in agent order that carry ``total_cost``: ``rotated`` where the set
        was turned, else the set's points in the cheapest assignment (n k,)."""
        if self.rotated is not None:
            return self.rotated
        n = len(self.assignment)
        return self.phi.reshape(n, -1)[self.assignment].ravel()

    def to_dict(self) -> dict:
        """The candidate as ``result.json`` lists it (on a surface with its returned points'
        scaled potential and largest tangential |∇G|, length⁻³)."""
        found = {"total_cost": self.total_cost, "potential": self.potential,
                 "stable": self.stable, "min_eigenvalue": self.min_eigenvalue,
                 "hits": self.hits, "first_start": self.first_start,
                 "phi": self.phi.tolist()}
        if self.rotated is not None:
            found["rotated_phi"] = self.rotated.tolist()
        if self.points_potential is not None:
            found["points_potential"] = self.points_potential
            found["tangential_gradient"] = self.tangential_gradient
        return found


@dataclass
class IsolatedChoice:
    """Outcome of :func:`best_isolated_formation`: ``phi`` (n,) the best angles in agent order
    (rad); ``total_cost`` there; ``sets`` every distinct critical set found and verified,
    cheapest first; ``starts`` the searches run (the initial guess's included; those that did
    not converge or were not stable are ``starts`` − Σ hits − the dropped sets' hits),
    ``saturated`` whether the last ``saturation`` of them found no new set;
    ``inner_solves`` M n² and the rotation searches'; ``dropped`` the sets whose returned
    points failed :func:`_verify`."""

    phi: np.ndarray
    total_cost: float
    sets: list[CriticalSet]
    starts: int
    saturated: bool
    saturation: int
    inner_solves: int
    dropped: int = 0


def critical_sets(problem: FormationProblem, critical: str = "stable",
                  starts: int = CRITICAL_STARTS, seed: int = 0,
                  saturation: int = SATURATION_STARTS
                  ) -> tuple[list[CriticalSet], int, int, bool]:
    """The distinct critical sets of G reached from the initial guess and seeded random angle
    vectors (module docstring, step 1), in order of discovery: at least ``starts`` random
    ones, then more until ``saturation`` consecutive starts found no new set (0: exactly
    ``starts``), at most :data:`MAX_CRITICAL_STARTS`; the number of searches that did not
    converge (``any``) or ended on a set that is not stable (``stable``); the number of
    searches made (the initial guess's included); and whether the last ``saturation`` of them
    found no new set (the enumeration saturated; False with ``saturation`` 0)."""
    if critical not in CRITICAL_READINGS:
        raise ValueError(f"critical must be one of {', '.join(CRITICAL_READINGS)}, got "
                         f"{critical!r}")
    curve, n, coupling = problem.curve, problem.agents, problem.coupling
    on_surface = isinstance(curve, Surface)
    rng = np.random.default_rng(seed)
    found: list[CriticalSet] = []
    failed, made, last_new = 0, 0, 0
    limit = max(starts, MAX_CRITICAL_STARTS) if saturation else starts
    while made <= limit and (made <= starts or (saturation and made - last_new <= saturation)):
        if not made:
            guess = problem.initial_phi().ravel()
        elif on_surface:
            guess = curve.parameters_toward(rng.normal(size=(n, 3))).ravel()
        else:
            guess = np.sort(rng.uniform(0, 2 * np.pi, n))
        start, made = made, made + 1
        phi, chart = _solve(problem, guess, critical, curve), curve
        points = problem.final_positions(phi) if on_surface else None
        if isinstance(curve, EllipsoidSurface) and not (
                _regular(curve, phi) and _critical_points(curve, points)[0]):
            chart = curve.charted_away(points)   # near a pole: solved again away from it
            if chart is not curve:
                phi = _solve(problem, chart.locate(points).ravel(), critical, chart)
        eigenvalue = _smallest_eigenvalue(problem, phi, chart)
        converged = np.max(np.abs(coupling.residual(phi, chart))) <= ROOT_TOL \
            and (not on_surface or _regular(chart, phi))
        if not converged or (critical == "stable" and eigenvalue <= 0):
            failed += 1
            continue
        if on_surface:   # kept in the problem's chart
            phi = curve.locate(chart.points(phi.reshape(n, -1))).ravel()
        else:
            phi = np.sort(np.mod(phi, 2 * np.pi))
        same = next((s for s in found if _same_set(problem, s.phi, phi)), None)
        if same is None:
            found.append(CriticalSet(phi, _potential(problem, phi), eigenvalue, start))
            last_new = start
        else:
            same.hits += 1
    return found, failed, made, bool(saturation) and made - 1 - last_new >= saturation


def _solve(problem: FormationProblem, guess: np.ndarray, critical: str,
           curve: Curve | Surface) -> np.ndarray:
    """The solution of c = 0 on ``curve`` (the problem's, or its surface in another chart)
    that ``guess`` leads to: :meth:`~ocpar.formation.couplings.coupling.Coupling.project`
    (``stable``),
    else Levenberg–Marquardt on a surface (c = 0 is rank-deficient there where the surface
    has symmetries) or Newton's method (SciPy's ``root``) on a curve."""
    from scipy.optimize import least_squares, root
    coupling = problem.coupling
    if critical == "stable":
        return coupling.project(guess, curve)
    if isinstance(curve, Surface):
        solution = least_squares(coupling.residual, guess, jac=coupling.jacobian,
                                 args=(curve,), method="lm", xtol=1e-15, ftol=1e-15,
                                 gtol=1e-15)
        return coupling.retract(np.asarray(solution.x, float), curve)
    solution = root(coupling.residual, guess, args=(curve,), jac=coupling.jacobian)
    return np.asarray(solution.x, float)


def _regular(surface: Surface, phi: np.ndarray) -> bool:
    """Whether no agent sits at a singular point of the surface's parametrisation (a chart
    pole: there dc/dφ = 0 does not make the point critical), the smaller singular value of
    each ∂z/∂φ_i at least :data:`REGULAR_RTOL` times the length scale."""
    singular = np.linalg.svd(surface.jacobians(phi.reshape(-1, 2)), compute_uv=False)
    return bool(np.min(singular[:, 1]) >= REGULAR_RTOL * surface.length_scale)


def _smallest_eigenvalue(problem: FormationProblem, phi: np.ndarray,
                         curve: Curve | Surface) -> float:
    """The smallest eigenvalue of G's scaled Hessian dc/dφ at ``phi`` on ``curve`` (the
    problem's, or its surface in another chart) across its symmetry (on a sphere the three
    rotations leave G unchanged: their directions are left out)."""
    from scipy.linalg import null_space
    hessian = problem.coupling.jacobian(phi, curve)
    if not isinstance(curve, Surface):
        return float(np.linalg.eigvalsh(hessian)[0])
    across = null_space(problem.coupling.free_directions(phi, curve).T)
    return float(np.linalg.eigvalsh(across.T @ hessian @ across)[0])


def _rotations(problem: FormationProblem) -> np.ndarray | None:
    """The axes (k, 3) of the rotations that map the problem's surface onto itself where
    known (an ellipsoid's :attr:`~ocpar.formation.targets.surface.EllipsoidSurface.symmetry_axes`),
    else None (a parametric surface: its free directions come from dc/dφ)."""
    curve = problem.curve
    return curve.symmetry_axes if isinstance(curve, EllipsoidSurface) else None


def _turnable(problem: FormationProblem, phi: np.ndarray) -> bool:
    """Whether the set ``phi`` is isolated only up to free directions of c = 0 (the surface's
    rotations): k > 0 for an ellipsoid, the null space of dc/dφ otherwise."""
    axes = _rotations(problem)
    if axes is not None:
        return bool(len(axes))
    return bool(problem.coupling.free_directions(phi, problem.curve).shape[1])


def _verify(problem: FormationProblem, candidate: CriticalSet) -> bool:
    """Check a candidate on a surface from its returned end points x = z(φ) alone (no chart):
    records their scaled potential (ℓ²/n³) G(x) and max_i |tangential ∇G_i| (length⁻³), and
    says whether they are critical (that at most :data:`CRITICAL_RTOL` max_i |∇G_i|) and
    carry the reported potential (to :data:`POTENTIAL_RTOL`)."""
    n, surface = problem.agents, problem.curve
    points = problem.final_positions(candidate.returned())
    candidate.points_potential = coupling_scale(surface, n) * point_potential(points)
    critical, candidate.tangential_gradient = _critical_points(surface, points)
    return critical and abs(candidate.points_potential - candidate.potential) \
        <= POTENTIAL_RTOL * abs(candidate.potential)


def _critical_points(surface: Surface, points: np.ndarray) -> tuple[bool, float]:
    """Whether ``points`` (n, 3) on ``surface`` are a critical configuration of G, checked in
    space (max_i |tangential ∇G_i| ≤ :data:`CRITICAL_RTOL` max_i |∇G_i|:
    :func:`~ocpar.formation.couplings.potential.surface_criticality`), and that largest tangential
    |∇G_i| (length⁻³)."""
    relative, tangential = surface_criticality(surface, points)
    return relative <= CRITICAL_RTOL, tangential


def _potential(problem: FormationProblem, phi: np.ndarray) -> float:
    """The scaled potential (ℓ²/n³) G at ``phi``."""
    if isinstance(problem.curve, Surface):
        return problem.coupling.scaled_potential(phi, problem.curve)
    return potential(phi, problem.curve)


def _same_set(problem: FormationProblem, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two critical sets are one. On a curve: sorted angles (n,) agreeing to
    :data:`SAME_SET_TOL` up to a cyclic shift (the wrap at 2π moves the first angle to the
    end). On a surface with free directions (a sphere's rotations): equal sorted pairwise
    distances, to :data:`SAME_SET_TOL` times the length scale (a rotation or reflection apart);
    on any other surface: the same points in some order, to that tolerance."""
    if not isinstance(problem.curve, Surface):
        return any(np.max(np.abs(np.angle(np.exp(1j * (np.roll(a, k) - b))))) <= SAME_SET_TOL
                   for k in range(len(a)))
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial.distance import cdist, pdist

    tol = SAME_SET_TOL * problem.curve.length_scale
    p, q = problem.final_positions(a), problem.final_positions(b)
    if _turnable(problem, a):
        return bool(np.max(np.abs(np.sort(pdist(p)) - np.sort(pdist(q)))) <= tol)
    distances = cdist(p, q)
    rows, cols = linear_sum_assignment(distances)
    return bool(np.max(distances[rows, cols]) <= tol)


def best_isolated_formation(problem: FormationProblem, backend: Backend,
                            critical: str = "stable", starts: int = CRITICAL_STARTS,
                            progress: Callable[[str], None] | None = None,
                            tol: float = 1e-12, saturation: int = SATURATION_STARTS
                            ) -> IsolatedChoice:
    """The cheapest critical set and assignment (module docstring): the sets on the
    coordinator (``starts`` random starts at least, then until ``saturation`` in a row find
    no new set: :func:`critical_sets`), their cost tables in one superstep; on a surface
    whose sets have free directions (a sphere's rotations) each set's assignment alternated
    with the outer Newton solve over them (:func:`_rotate`, tolerance ``tol``). Infeasible
    pairs are +∞ in the tables; a set with no assignment of feasible pairs is no candidate.
    Raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if no set has one, and
    ValueError on a circle (its feasible set is continuous:
    :func:`~ocpar.formation.ordering.optimal_ordering`) or when no search converged."""
    if not isinstance(problem.curve, Surface) and problem.curve.rotation_invariant:
        raise ValueError("best_isolated_formation is for curves whose coupling has isolated "
                         "solutions; on a circle use optimal_ordering")
    sets, failed, made, saturated = critical_sets(problem, critical, starts,
                                                  saturation=saturation)
    if not sets:
        raise ValueError(f"no critical set of the potential found from {made} starts "
                         f"(reading {critical!r})")
    n = problem.agents
    tables, solves = _tables(problem, backend, np.array([s.phi.reshape(n, -1) for s in sets]))
    for candidate, table in zip(sets, tables, strict=True):
        try:
            candidate.assignment = cheapest_assignment(table)
            candidate.total_cost = assignment_cost(table, candidate.assignment)
        except InnerSolveFailed:   # no assignment with every pair feasible: not a candidate
            candidate.total_cost = math.inf   # unless a turn of it has one
        if isinstance(problem.curve, Surface) and _turnable(problem, candidate.phi):
            candidate.rotated, candidate.total_cost, rotated_solves = _rotate(
                problem, backend, candidate.phi, tol)
            solves += rotated_solves
    dropped = []
    if isinstance(problem.curve, Surface):
        kept = [not math.isfinite(s.total_cost) or _verify(problem, s) for s in sets]
        dropped = [s for s, ok in zip(sets, kept, strict=True) if not ok]
        sets = [s for s, ok in zip(sets, kept, strict=True) if ok]
        if progress is not None:
            for s in dropped:
                progress(f"critical set dropped: its returned points have potential "
                         f"{s.points_potential:.12g} (reported {s.potential:.12g}) and "
                         f"tangential |grad G| {s.tangential_gradient:.1e}")
        if not sets:
            raise ValueError(f"no critical set of the potential passed the check from its "
                             f"returned points ({len(dropped)} dropped)")
    sets.sort(key=lambda s: s.total_cost)
    best = sets[0]
    if not math.isfinite(best.total_cost):
        raise InnerSolveFailed(f"none of the {len(sets)} critical set(s) has an assignment "
                               "with every agent's inner problem feasible")
    if progress is not None:
        progress(f"critical sets ({critical}): {len(sets)} distinct from {made} starts "
                 f"({failed} not converged or not stable, {len(dropped)} dropped by the check "
                 f"from their points); costs " + ", ".join(f"{s.total_cost:.9e}" for s in sets))
    return IsolatedChoice(best.returned(), float(best.total_cost), sets, made, saturated,
                          saturation, solves, len(dropped))


def _rotate(problem: FormationProblem, backend: Backend, phi: np.ndarray, tol: float
            ) -> tuple[np.ndarray, float, int]:
    """The best turn of a critical set ``phi`` (2n,) with free directions: from the set as
    labelled and, on a surface with rotational symmetry, from :data:`ROTATION_STARTS` − 1
    seeded random rotations of it (:func:`_turns`), rounds of the outer Newton solve over the
    free directions (the rotations applied rigidly, :func:`rotation_newton`; on a parametric
    surface the tangent space of c = 0, :func:`tangent_newton`) and the cheapest assignment of
    the agents to the points reached (one table superstep each), while the assignment changes
    (at most :data:`ROTATION_ROUNDS`); a start with no assignment of feasible pairs is
    skipped. Returns (φ in agent order, its total cost, inner solves), (None, +∞, inner
    solves) if no start has one."""
    n, solves = problem.agents, 0
    axes = _rotations(problem)
    starts = [phi]
    if axes is not None:
        centre = problem.curve.center
        points = problem.final_positions(phi) - centre
        starts += [problem.curve.locate(centre + turn.apply(points)).ravel()
                   for turn in _turns(axes)]
    newton = rotation_newton if axes is not None else tangent_newton
    best: tuple[np.ndarray, float] | None = None
    for start in starts:
        tables, solved = _tables(problem, backend, start.reshape(1, n, -1))
        table, solves = tables[0], solves + solved
        try:
            phi = start.reshape(n, -1)[cheapest_assignment(table)].ravel()
        except InnerSolveFailed:   # no agent order reaches this turn: the next start
            continue
        for _ in range(ROTATION_ROUNDS):
            objective = OuterObjective(problem, backend)
            phi, _, _, _ = newton(objective, phi, tol, MAX_ROTATION_ITERATIONS)
            cost = objective.value(phi)
            objective.close()
            tables, solved = _tables(problem, backend, phi.reshape(1, n, -1))
            table, solves = tables[0], solves + objective.inner_solves + solved
            assignment = cheapest_assignment(table)
            if assignment_cost(table, assignment) >= cost * (1 - ROUNDING_RTOL):
                break
            # the cheaper labelling of the same points: its cost is known from the table
            phi, cost = phi.reshape(n, -1)[assignment].ravel(), assignment_cost(table, assignment)
        if best is None or cost < best[1]:
            best = (phi, cost)
    return (None, math.inf, solves) if best is None else (best[0], best[1], solves)


def _tables(problem: FormationProblem, backend: Backend, slots: np.ndarray
            ) -> tuple[np.ndarray, int]:
    """The cost tables (M, n, n) of the M point sets ``slots`` (M, n, k) in one superstep,
    +∞ where a pair is infeasible (the pairs outside an exact reach set not solved; all may
    be), and the inner solves made."""
    tables, found = solved_tables(problem, backend, slots, all_infeasible=True)
    return tables, found.solved


def _turns(axes: np.ndarray) -> Rotation:
    """:data:`ROTATION_STARTS` − 1 seeded rotations about the axes (k, 3): uniformly random
    with three (a sphere's), else the angles 2πm/ROTATION_STARTS about the one axis."""
    from scipy.spatial.transform import Rotation
    if len(axes) == 3:
        return Rotation.random(ROTATION_STARTS - 1, random_state=ROTATION_SEED)
    angles = 2 * np.pi * np.arange(1, ROTATION_STARTS) / ROTATION_STARTS
    return Rotation.from_rotvec(angles[:, None] * axes[0])
