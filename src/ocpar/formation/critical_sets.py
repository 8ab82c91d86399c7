"""The best formation where the coupling's solutions are isolated: every curve but a circle.

Off a circle the coupling g(φ) = ∂G/∂φ = 0 (:mod:`ocpar.formation.potential`) admits only the
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
   (:func:`~ocpar.formation.ordering.cost_tables`), then the cheapest assignment of each
   (:func:`scipy.optimize.linear_sum_assignment`, exact).

The best (set, assignment) is returned with every candidate set's cost. It is the global
optimum over the sets found; a set that no start reaches is not seen (the count of starts
that led to each set is reported, so a user can judge coverage).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import root

from ocpar.bsp import Backend
from ocpar.formation.ordering import assignment_cost, cheapest_assignment, cost_tables
from ocpar.formation.potential import coupling, coupling_jacobian, potential, relax
from ocpar.formation.problem import FormationProblem

#: Random starts of the search besides the initial guess (default).
CRITICAL_STARTS = 32
#: The two readings of the coupling: local minima of G only, or every critical point.
CRITICAL_READINGS = ("stable", "any")
#: Two sets of sorted angles agreeing to this (rad), up to a cyclic shift, are one set.
SAME_SET_TOL = 1e-6
#: Newton's method on g = 0 (``any``) has converged at max |c_k| ≤ this (c scaled as
#: :func:`~ocpar.formation.potential.coupling`).
ROOT_TOL = 1e-10


@dataclass
class CriticalSet:
    """One critical configuration of G: ``phi`` (n,) its points' angles (rad, sorted in
    [0, 2π)); ``potential`` the scaled G there; ``min_eigenvalue`` the smallest eigenvalue of
    the scaled Hessian of G on the curve (> 0: a stable formation); ``hits`` how many starts
    reached it; ``assignment`` (n,) the cheapest point index per agent and ``total_cost``
    Σ_i Ĵ_i there (None until the tables are solved)."""

    phi: np.ndarray
    potential: float
    min_eigenvalue: float
    hits: int = 1
    assignment: np.ndarray | None = None
    total_cost: float | None = None

    @property
    def stable(self) -> bool:
        return self.min_eigenvalue > 0

    def to_dict(self) -> dict:
        """The candidate as ``result.json`` lists it."""
        return {"total_cost": self.total_cost, "potential": self.potential,
                "stable": self.stable, "min_eigenvalue": self.min_eigenvalue,
                "hits": self.hits, "phi": self.phi.tolist()}


@dataclass
class IsolatedChoice:
    """Outcome of :func:`best_isolated_formation`: ``phi`` (n,) the best angles in agent order
    (rad); ``total_cost`` there; ``sets`` every distinct critical set found, cheapest first;
    ``starts`` the searches run (the initial guess's included; those that did not converge or
    were not stable are ``starts`` − Σ hits); ``inner_solves`` M n²."""

    phi: np.ndarray
    total_cost: float
    sets: list[CriticalSet]
    starts: int
    inner_solves: int


def critical_sets(problem: FormationProblem, critical: str = "stable",
                  starts: int = CRITICAL_STARTS, seed: int = 0
                  ) -> tuple[list[CriticalSet], int]:
    """The distinct critical sets of G reached from the initial guess and ``starts`` random
    angle vectors (module docstring, step 1), in order of discovery; and the number of
    searches that did not converge (``any``) or ended on a set that is not stable
    (``stable``)."""
    if critical not in CRITICAL_READINGS:
        raise ValueError(f"critical must be one of {', '.join(CRITICAL_READINGS)}, got "
                         f"{critical!r}")
    curve, n = problem.curve, problem.agents
    rng = np.random.default_rng(seed)
    guesses = [problem.initial_phi(), *(np.sort(rng.uniform(0, 2 * np.pi, n))
                                        for _ in range(starts))]
    found: list[CriticalSet] = []
    failed = 0
    for guess in guesses:
        if critical == "stable":
            phi = relax(guess, curve)
        else:
            solution = root(coupling, guess, args=(curve,), jac=coupling_jacobian)
            phi = np.asarray(solution.x, float)
        eigenvalue = float(np.linalg.eigvalsh(coupling_jacobian(phi, curve))[0])
        converged = np.max(np.abs(coupling(phi, curve))) <= ROOT_TOL
        if not converged or (critical == "stable" and eigenvalue <= 0):
            failed += 1
            continue
        phi = np.sort(np.mod(phi, 2 * np.pi))
        same = next((s for s in found if _same_set(s.phi, phi)), None)
        if same is None:
            found.append(CriticalSet(phi, potential(phi, curve), eigenvalue))
        else:
            same.hits += 1
    return found, failed


def _same_set(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether sorted angle sets ``a`` and ``b`` (n,) agree to :data:`SAME_SET_TOL` up to a
    cyclic shift (the wrap at 2π moves the first angle to the end)."""
    return any(np.max(np.abs(np.angle(np.exp(1j * (np.roll(a, k) - b))))) <= SAME_SET_TOL
               for k in range(len(a)))


def best_isolated_formation(problem: FormationProblem, backend: Backend,
                            critical: str = "stable", starts: int = CRITICAL_STARTS,
                            progress: Callable[[str], None] | None = None) -> IsolatedChoice:
    """The cheapest critical set and assignment (module docstring): the sets on the
    coordinator, their cost tables in one superstep; raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if an inner solve fails, and
    ValueError on a circle (its feasible set is continuous:
    :func:`~ocpar.formation.ordering.optimal_ordering`) or when no search converged."""
    if problem.curve.rotation_invariant:
        raise ValueError("best_isolated_formation is for curves whose coupling has isolated "
                         "solutions; on a circle use optimal_ordering")
    sets, failed = critical_sets(problem, critical, starts)
    if not sets:
        raise ValueError(f"no critical set of the potential found from {starts + 1} starts "
                         f"(reading {critical!r})")
    tables = cost_tables(problem, backend, np.array([s.phi for s in sets]))
    for candidate, table in zip(sets, tables, strict=True):
        candidate.assignment = cheapest_assignment(table)
        candidate.total_cost = assignment_cost(table, candidate.assignment)
    sets.sort(key=lambda s: s.total_cost)
    best = sets[0]
    if progress is not None:
        progress(f"critical sets ({critical}): {len(sets)} distinct from {starts + 1} starts "
                 f"({failed} not converged or not stable); costs "
                 + ", ".join(f"{s.total_cost:.9e}" for s in sets))
    return IsolatedChoice(best.phi[best.assignment], float(best.total_cost), sets, starts + 1,
                          tables.size)
