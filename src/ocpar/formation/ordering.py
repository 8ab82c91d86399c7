"""Which agent takes which slot on the circle: the optimal ordering (the paper's open problem).

The equidistance constraint leaves the final angles φ_i = θ + base_σ(i): n equidistant slots
base_j (those of :meth:`~ocpar.formation.problem.FormationProblem.initial_phi`, sorted), a
common offset θ (rad) and an assignment σ of agents to slots. The ``keep`` ordering is the
initial guess's σ; ``optimal`` minimises J(σ, θ) = Σ_i Ĵ_i(θ + base_σ(i)) over both:

* for a fixed offset θ, σ is a linear assignment problem on the n × n table
  C[i, j] = Ĵ_i(θ + base_j) (:func:`cost_table`: n² independent inner solves, one superstep;
  :func:`scipy.optimize.linear_sum_assignment`);
* for a fixed σ, θ is the 1-D offset search :func:`~ocpar.formation.hierarchical.
  solve_outer_offset` (a few supersteps of n solves).

Alternating the two (coordinate descent) only lowers J and stops when the assignment no longer
changes, but it can stop at a local optimum: F(θ) = min_σ J(σ, θ) is the lower envelope of
one smooth curve per ordering, and the best ordering may be cheapest only on a narrow range of
offsets that the descent never visits. Started from θ = 0 alone it missed the brute-force
optimum in ~10 % of random instances with 5–7 agents. Hence a multi-start: offsets matter only
modulo one slot width w = 2π/n (a shift by w relabels the slots), so the tables at ``starts``
offsets m·w/``starts`` (m = 0..starts−1) are filled in ONE superstep; each table's assignment
is a candidate ordering. Every table also gives every ordering's J at those offsets shifted by
whole slots (a rotation of σ), i.e. each candidate's J on a grid of ``starts``·n offsets round
the circle; the descent starts from the candidate whose parabola through its three best
neighbouring grid values has the lowest minimum, at its best grid offset. With ``starts`` = 6
(the default) this found the brute-force optimum in all of ~2000 random instances with 5–7
agents (4 missed ~0.3 %); it is a heuristic, not a certificate.

Cost: (``starts`` + rounds) · n² inner solves in 1 + rounds table supersteps, plus the offset
searches (rounds × a few supersteps of n solves).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ocpar.bsp import Backend
from ocpar.formation.hierarchical import InnerSolveFailed, OuterObjective, solve_outer_offset
from ocpar.formation.problem import FormationProblem
from ocpar.ocp import solve_dmoc_task

ORDERINGS = ("keep", "optimal")

#: Offsets per slot width whose cost tables are filled in the first superstep (multi-start).
DEFAULT_STARTS = 6

#: A new assignment replaces the current one only if it lowers the table's total by more than
#: this fraction of it: equal-cost assignments (ties, inner-solver noise) must not cycle.
IMPROVEMENT_RTOL = 1e-10

#: Iteration limit of each offset search.
OFFSET_MAX_ITERATIONS = 100


@dataclass
class OrderingResult:
    """Outcome of :func:`optimal_ordering`.

    ``phi`` (n,) final angles (rad, equidistant, in agent order); ``assignment`` (n,) slot
    index j of each agent, slot j at angle ``offset`` + base_j (base = the sorted
    ``initial_phi()``, ``offset`` in [0, 2π/n)); ``total_cost`` Σ_i Ĵ_i(φ_i) (the inner
    cost's unit); ``rounds`` alternations (offset search + table); ``table_supersteps`` and
    ``inner_solves`` (tables and offset searches together); ``converged``: the assignment
    stopped changing and every offset search converged; ``starts`` offsets of the multi-start;
    ``candidates`` distinct orderings (modulo rotation) its tables proposed; ``message`` why
    it stopped.
    """

    phi: np.ndarray
    assignment: np.ndarray
    total_cost: float
    rounds: int
    table_supersteps: int
    inner_solves: int
    converged: bool
    offset: float = 0.0
    starts: int = DEFAULT_STARTS
    candidates: int = 1
    message: str = ""


def slot_base(problem: FormationProblem) -> np.ndarray:
    """The n equidistant slots at offset 0 (rad, increasing, span < 2π): the sorted
    :meth:`~ocpar.formation.problem.FormationProblem.initial_phi`."""
    return np.sort(problem.initial_phi())


def cost_table(problem: FormationProblem, backend: Backend, slots: np.ndarray) -> np.ndarray:
    """C[i, j] = Ĵ_i(slots[j]): agent i's inner optimal cost ending at angle ``slots[j]``
    (rad), shape (n, n) for n agents and n ``slots``. One superstep of n² inner solves
    (task i·n + j); raises :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if any
    fails."""
    slots = np.asarray(slots, float)
    if slots.shape != (problem.agents,):
        raise ValueError(f"slots must have shape ({problem.agents},) (one angle per agent, "
                         f"rad), got {slots.shape}")
    return _tables(problem, backend, slots[None, :])[0][0]


def _tables(problem: FormationProblem, backend: Backend,
            slots: np.ndarray) -> tuple[np.ndarray, int]:
    """Cost tables (M, n, n) for M rows of ``slots`` (M, n), in one superstep; and the
    number of inner solves."""
    n = problem.agents
    if not np.all(np.isfinite(slots)):
        raise ValueError("slots must be finite angles (rad)")
    tables = len(slots)
    agents = np.tile(np.repeat(np.arange(n), n), tables)
    angles = np.repeat(slots, n, axis=0).ravel()  # row (m, i) holds the slots of table m
    sols = backend.superstep_columns(solve_dmoc_task, problem.tasks_for(agents, angles))
    failed = np.flatnonzero(~np.asarray(sols.column("success"), dtype=bool))
    if len(failed):
        k = int(failed[0])
        raise InnerSolveFailed(
            f"{len(failed)} of {len(sols)} cost-table solve(s) failed; first: agent "
            f"{agents[k]} at angle {angles[k]:.6f} rad: {sols.column('status')[k]}")
    costs = np.asarray(sols.column("cost"), dtype=float)
    return costs.reshape(tables, n, n), len(sols)


def _assign(table: np.ndarray) -> np.ndarray:
    """The cheapest assignment of a cost table: slot index per agent (n,)."""
    rows, cols = linear_sum_assignment(table)
    assignment = np.empty(len(table), dtype=np.intp)
    assignment[rows] = cols
    return assignment


def _table_cost(table: np.ndarray, assignment: np.ndarray) -> float:
    return float(np.sum(table[np.arange(len(table)), assignment]))


def _grid_values(tables: np.ndarray, assignment: np.ndarray) -> np.ndarray:
    """J of ordering ``assignment`` at the offsets (m + M k)·w/M, k = 0..n−1, from the M
    tables at offsets m·w/M: entry m + M k is table m with every slot index shifted by k."""
    n = tables.shape[1]
    shifted = (assignment[None, :] + np.arange(n)[:, None]) % n  # (k, i)
    values = tables[:, np.arange(n)[None, :], shifted].sum(axis=2)  # (m, k)
    return values.T.ravel()


def _parabola_minimum(values: np.ndarray) -> tuple[float, int]:
    """(estimated minimum, index of the least value) of periodic samples on a uniform grid:
    the vertex of the parabola through the least value and its two neighbours."""
    best = int(np.argmin(values))
    left, mid, right = values[best - 1], values[best], values[(best + 1) % len(values)]
    curvature = left - 2 * mid + right
    if curvature <= 0:
        return float(mid), best
    return float(mid - (right - left) ** 2 / (8 * curvature)), best


def _canonical(assignment: np.ndarray) -> tuple[int, ...]:
    """The ordering modulo rotation (agent 0 in slot 0)."""
    return tuple(((assignment - assignment[0]) % len(assignment)).tolist())


def optimal_ordering(
    problem: FormationProblem,
    backend: Backend,
    tol: float = 1e-12,
    max_rounds: int = 20,
    progress: Callable[[str], None] | None = None,
    starts: int = DEFAULT_STARTS,
) -> OrderingResult:
    """The agent→slot assignment and common offset minimising Σ_i Ĵ_i(φ_i) over equidistant
    φ (see the module docstring): a multi-start superstep of ``starts`` cost tables, then
    alternating offset searches (relative tolerance ``tol`` on the offset, as
    :func:`~ocpar.formation.hierarchical.solve_outer_offset`) and cost tables at the new
    offset until the assignment stops changing or ``max_rounds`` offset searches were run.
    ``progress`` gets one line per round. Raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if an inner solve fails."""
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol}")
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, int | np.integer) \
            or max_rounds < 1:
        raise ValueError(f"max_rounds must be an integer ≥ 1, got {max_rounds!r}")
    if isinstance(starts, bool) or not isinstance(starts, int | np.integer) or starts < 1:
        raise ValueError(f"starts must be an integer ≥ 1, got {starts!r}")
    n = problem.agents
    width = 2 * np.pi / n
    base = slot_base(problem)
    say = progress or (lambda _line: None)

    # multi-start: tables at `starts` offsets within one slot width, one superstep
    offsets = np.arange(starts) * width / starts
    tables, inner_solves = _tables(problem, backend, base[None, :] + offsets[:, None])
    table_supersteps = 1
    candidates: dict[tuple[int, ...], np.ndarray] = {}
    for table in tables:
        candidates.setdefault(_canonical(a := _assign(table)), a)
    estimate, pick = min((_parabola_minimum(_grid_values(tables, a)), key)
                         for key, a in candidates.items())
    k, m = divmod(estimate[1], starts)  # grid point (m + starts k): offset m·w/M, shift k
    assignment = (candidates[pick] + k) % n
    offset = float(offsets[m])
    keep = np.searchsorted(base, problem.initial_phi())  # the keep ordering's slots
    moved = int(np.count_nonzero(assignment != keep))
    say(f"ordering tables: {starts} offset(s) x {n}x{n} solves, {len(candidates)} candidate "
        f"ordering(s); start at offset {offset:.6f} rad, {moved} agent(s) off the keep ordering")

    objective = OuterObjective(problem, backend)
    converged, message = False, f"assignment still changing after {max_rounds} round(s)"
    all_offsets_converged = True
    for rounds in range(1, max_rounds + 1):
        phi, _, success, offset_message = solve_outer_offset(
            objective, base[assignment] + offset, tol, OFFSET_MAX_ITERATIONS)
        total_cost = objective.value(phi)  # cached: the search's last superstep
        if not success:
            all_offsets_converged = False
            message = f"offset search of round {rounds}: {offset_message}"
        # relabel: an offset beyond one slot width shifts every slot index
        theta = float(phi[0] - base[assignment[0]])
        shift = int(np.floor(theta / width))
        offset = theta - shift * width
        assignment = (assignment + shift) % n
        table = cost_table(problem, backend, base + offset)
        table_supersteps += 1
        inner_solves += n * n
        current = _table_cost(table, assignment)
        better = _assign(table)
        improved = _table_cost(table, better) < current - IMPROVEMENT_RTOL * abs(current)
        moved = int(np.count_nonzero(better != assignment)) if improved else 0
        say(f"ordering round {rounds}: cost {total_cost:.12e}, {moved} agent(s) moved")
        if not improved:
            converged = all_offsets_converged
            message = "assignment unchanged" if converged else message
            break
        # the better assignment at this offset: its cost is known from the table, exactly
        assignment = better
        phi, total_cost = base[assignment] + offset, _table_cost(table, assignment)
    return OrderingResult(
        phi=np.asarray(phi, float),
        assignment=assignment,
        total_cost=float(total_cost),
        rounds=rounds,
        table_supersteps=table_supersteps,
        inner_solves=inner_solves + objective.inner_solves,
        converged=converged,
        offset=offset,
        starts=starts,
        candidates=len(candidates),
        message=message,
    )
