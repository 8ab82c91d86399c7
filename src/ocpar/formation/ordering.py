"""Which agent takes which slot on the circle: the optimal ordering (the paper's open problem).

Circles only: on another curve the coupling fixes the angles up to discrete choices, and the
equidistant slots and common offset below do not exist.

The equidistance constraint leaves the final angles φ_i = θ + base_σ(i): n equidistant slots
base_j (those of :meth:`~ocpar.formation.problem.FormationProblem.initial_phi`, sorted; slot
width w = 2π/n), a common offset θ (rad) and an assignment σ of agents to slots. The ``keep``
ordering is the initial guess's σ; ``optimal`` minimises J(σ, θ) = Σ_i Ĵ_i(θ + base_σ(i))
over both:

* for a fixed offset θ, σ is a linear assignment problem on the n × n table
  C[i, j] = Ĵ_i(θ + base_j) (:func:`cost_table`: n² independent inner solves, one superstep;
  :func:`scipy.optimize.linear_sum_assignment`);
* for a fixed σ, θ is the 1-D offset search
  :func:`~ocpar.formation.hierarchical.solve_outer_offset` (a few supersteps of n solves).

Alternating the two (coordinate descent) only lowers J and stops when the assignment no longer
changes, but it stops at local optima: F(θ) = min_σ J(σ, θ) is the lower envelope of one
smooth curve per ordering, and the best ordering can be the cheapest only on a narrow range
of offsets (in one 7-agent case 0.13 rad of the 0.9 rad slot width) that the descent never
visits. From θ = 0 alone it missed the brute-force optimum in ~10 % of random instances with
5–7 agents; real tables at 6 offsets per slot width, descending from the best sampled
ordering, still missed ~1 % (the narrow case above among them).

Hence a multi-start through a surrogate (:class:`CostSurrogate`). Offsets matter only modulo
w (a shift by w relabels the slots), and the tables at the M offsets m·w/M (m = 0..M−1,
filled in ONE superstep) hold every agent's cost Ĵ_i at M·n equally spaced angles round the
whole circle. Their trigonometric interpolant gives every table at every offset and every
ordering's J(σ, ·) without further inner solves. It is exact when Ĵ_i(φ) is a trigonometric
polynomial of degree < M·n/2: Ĵ_i is quadratic in the final position for both examples (a
double integrator; linearised relative motion with a fixed final attitude), and for
linear–quadratic ODE agents (e.g. Clohessy–Wiltshire spacecraft) J* is a quadratic of the
whole end state, which on a circle is affine in (cos φ, sin φ); either way of degree
2 in φ, so 5 samples would do; M = ⌈:data:`MIN_SAMPLES` / n⌉ leaves a margin for smooth
nonlinear inner problems and costs a single table from 16 agents on. On the surrogate, the
assignment is scanned at :data:`FINE_OFFSETS` offsets per slot width, a coordinate descent
(global over θ for each ordering) runs from every distinct ordering found there and from
``keep``, and the best result starts the real descent, which verifies it with inner solves
(the first table at the real optimum offset then confirms the assignment; the largest
difference surrogate − real table is reported). The result is a local optimum of the true J
in this sense: on a fleet of 12 norm-limited point masses it stopped 9.4e-4 above the
global optimum.

Hence the proof that follows it (:mod:`~ocpar.formation.ordering_bound`): where every inner
problem is convex in its end position (:func:`~ocpar.ocp.reach.end_cost_convexity`: point
masses and linear–quadratic ODE agents such as Clohessy–Wiltshire spacecraft, free or with
box or norm thrust limits), a branch and bound over the offset with
assignment lower bounds on intervals finds the global optimum over assignments and rotation
and proves it to a relative gap (:data:`~ocpar.formation.ordering_bound.GAP_TOL`), or stops
at its budget of rounds with the gap it proved. Elsewhere (obstacles, other models) no bound
is claimed and the descent's result stands.

Infeasible pairs (an agent that cannot reach a slot, e.g. under a thrust limit) are +∞ in
the tables (:func:`pair_costs`: outside an exact reach set not even solved; a failed solve
likewise), never an error. Then no interpolant exists: the candidates are each multi-start
table's cheapest assignment with every pair feasible, the real descent runs from the
cheapest of them and from ``keep`` (at its feasible start,
:func:`~ocpar.formation.feasibility.feasible_start`), and the offset searches are the
Newton search that stays inside the feasible shifts
(:func:`~ocpar.formation.hierarchical.solve_outer_newton`); the better end wins.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.feasibility import InnerCosts, feasible_start, inner_costs
from ocpar.formation.hierarchical import (
    InnerSolveFailed,
    OuterObjective,
    solve_outer_newton,
    solve_outer_offset,
)
from ocpar.formation.ordering_bound import (
    GAP_TOL,
    SEARCH_ROUNDS,
    PlaneBounds,
    SurrogateBounds,
    branch_and_bound,
)
from ocpar.formation.problem import FormationProblem
from ocpar.ocp.reach import QUADRATIC, end_cost_convexity

ORDERINGS = ("keep", "optimal")

#: Angles per agent round the circle sampled by the multi-start tables (at least): the
#: surrogate resolves costs Ĵ_i(φ) up to degree 7 in φ.
MIN_SAMPLES = 16

#: A convex quadratic inner cost (:data:`~ocpar.ocp.reach.QUADRATIC`) is a trigonometric
#: polynomial of this degree in the angle on a circle: the surrogate is exact for it with
#: more than twice as many samples per agent.
QUADRATIC_DEGREE = 2

#: Offsets per slot width at which the surrogate's assignment is scanned for candidates.
FINE_OFFSETS = 32

#: A new assignment replaces the current one only if it lowers the table's total by more than
#: this fraction of it: equal-cost assignments (ties, inner-solver noise) must not cycle.
IMPROVEMENT_RTOL = 1e-10

#: Iteration limit of each offset search.
OFFSET_MAX_ITERATIONS = 100


@dataclass
class OrderingResult:
    """Outcome of :func:`optimal_ordering`.

    ``phi`` (n,) final angles (rad, equidistant, in agent order); ``assignment`` (n,) slot
    index j of each agent, slot j at angle base_j + ``offset`` (base = the sorted
    ``initial_phi()``, ``offset`` in [0, 2π/n) rad); ``total_cost`` Σ_i Ĵ_i(φ_i) (the inner
    cost's unit); ``rounds`` alternations (offset search + cost table); ``table_supersteps``
    (the multi-start's included) and ``inner_solves`` (tables and offset searches);
    ``converged``: the assignment stopped changing and every offset search converged;
    ``starts`` offsets per slot width of the multi-start tables; ``candidates`` distinct
    orderings (modulo rotation) the surrogate scan proposed; ``surrogate_error`` the largest
    |surrogate − real| entry of the tables of the rounds, relative to the largest real entry
    (NaN where the tables held infeasible pairs and no surrogate was built);
    ``message`` why it stopped. The global search
    (:mod:`~ocpar.formation.ordering_bound`): ``bound`` what it rests on, ``"convex"``
    (supporting planes of solves), ``"quadratic"`` (the exact surrogate) or None (no bound
    claimed: a non-convex inner problem, e.g. with obstacles); ``proven`` the relative gap
    ``gap`` = (total_cost − ``lower_bound``) / total_cost is within its tolerance (NaN
    gap and lower bound where none is claimed); ``search_supersteps`` and
    ``search_solves`` its own (the offset searches it ran to polish are counted in
    ``table_supersteps`` and ``inner_solves``); ``search_message`` why it stopped.
    """

    phi: np.ndarray
    assignment: np.ndarray
    total_cost: float
    rounds: int
    table_supersteps: int
    inner_solves: int
    converged: bool
    offset: float = 0.0
    starts: int = 1
    candidates: int = 1
    surrogate_error: float = 0.0
    message: str = ""
    bound: str | None = None
    proven: bool = False
    gap: float = math.nan
    lower_bound: float = math.nan
    search_supersteps: int = 0
    search_solves: int = 0
    search_message: str = ""


def slot_base(problem: FormationProblem) -> np.ndarray:
    """The n equidistant slots at offset 0 (rad, increasing, span < 2π): the sorted
    :meth:`~ocpar.formation.problem.FormationProblem.initial_phi`."""
    return np.sort(problem.initial_phi())


def keep_assignment(problem: FormationProblem) -> np.ndarray:
    """The ``keep`` ordering: slot index (n,) of each agent in ``initial_phi()``."""
    return np.searchsorted(slot_base(problem), problem.initial_phi())


def default_starts(agents: int) -> int:
    """Offsets per slot width of the multi-start tables: ⌈:data:`MIN_SAMPLES` / n⌉."""
    return max(1, math.ceil(MIN_SAMPLES / agents))


def cost_table(problem: FormationProblem, backend: Backend, slots: np.ndarray) -> np.ndarray:
    """C[i, j] = Ĵ_i(slots[j]): agent i's inner optimal cost ending at angle ``slots[j]``
    (rad), shape (n, n) for n agents and n ``slots``, +∞ where infeasible
    (:func:`pair_costs`). One superstep of n² inner solves (task i·n + j)."""
    slots = np.asarray(slots, float)
    if slots.shape != (problem.agents,):
        raise ValueError(f"slots must have shape ({problem.agents},) (one angle per agent, "
                         f"rad), got {slots.shape}")
    return cost_tables(problem, backend, slots[None, :])[0]


def cost_tables(problem: FormationProblem, backend: Backend, slots: np.ndarray) -> np.ndarray:
    """Cost tables (M, n, n) for the M rows of ``slots`` (M, n) (rad), in one superstep."""
    return solved_tables(problem, backend, slots)[0]


def solved_tables(problem: FormationProblem, backend: Backend, slots: np.ndarray,
                  all_infeasible: bool = False) -> tuple[np.ndarray, InnerCosts]:
    """:func:`cost_tables` (M, n, n) and the superstep's
    :class:`~ocpar.formation.feasibility.InnerCosts` (pair k = (m n + i) n + j: table m,
    agent i, slot j; with dĴ/dz). ``all_infeasible``: tables of +∞ only are an answer (on a
    surface a turn of a critical set may lie beyond every agent's reach), not
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed`."""
    n = problem.agents
    if not np.all(np.isfinite(slots)):
        raise ValueError("slots must be finite angles (rad)")
    tables = len(slots)
    agents = np.tile(np.repeat(np.arange(n), n), tables)
    angles = np.repeat(slots, n, axis=0).ravel()  # row (m, i) holds the slots of table m
    found = inner_costs(problem, backend, agents, angles) if all_infeasible \
        else solved_pairs(problem, backend, agents, angles, "cost-table")
    return found.costs.reshape(tables, n, n), found


def pair_costs(problem: FormationProblem, backend: Backend, agents: np.ndarray,
               phi: np.ndarray, what: str) -> np.ndarray:
    """Ĵ (p,) of agent ``agents[k]`` ending at ``phi[k]`` (an angle, rad, or a slot index):
    one superstep of inner solves, +∞ where the pair is infeasible: its solve failed, or its
    target lies outside the agent's exact reach set (then it is not solved:
    :func:`~ocpar.formation.feasibility.inner_costs`). Raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed`, naming them ``what``, only if
    every pair is infeasible."""
    return solved_pairs(problem, backend, agents, phi, what).costs


def solved_pairs(problem: FormationProblem, backend: Backend, agents: np.ndarray,
                 phi: np.ndarray, what: str) -> InnerCosts:
    """:func:`pair_costs` with the rest of what the superstep found (its
    :class:`~ocpar.formation.feasibility.InnerCosts`)."""
    found = inner_costs(problem, backend, agents, phi)
    if not np.any(np.isfinite(found.costs)):
        first = f"; first: {found.first_failure}" if found.failed else ""
        raise InnerSolveFailed(f"all {len(found.costs)} {what} solve(s) infeasible: "
                               f"{found.failed} failed, {found.skipped} out of reach{first}")
    return found


def cheapest_assignment(table: np.ndarray) -> np.ndarray:
    """The cheapest assignment of a cost table (+∞: an infeasible pair): slot index per agent
    (n,). Raises :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if every assignment
    takes an infeasible pair."""
    from scipy.optimize import linear_sum_assignment
    try:
        rows, cols = linear_sum_assignment(table)
    except ValueError:   # scipy: "cost matrix is infeasible"
        raise InnerSolveFailed("no assignment of every agent to a place it can reach (every "
                               "one takes an infeasible pair)") from None
    assignment = np.empty(len(table), dtype=np.intp)
    assignment[rows] = cols
    return assignment


def assignment_cost(table: np.ndarray, assignment: np.ndarray) -> float:
    return float(np.sum(table[np.arange(len(table)), assignment]))


def _improves(table: np.ndarray, current: np.ndarray, new: np.ndarray) -> bool:
    old = assignment_cost(table, current)
    return assignment_cost(table, new) < old - IMPROVEMENT_RTOL * abs(old)


def _canonical(assignment: np.ndarray) -> tuple[int, ...]:
    """The ordering modulo rotation (agent 0 in slot 0)."""
    return tuple(((assignment - assignment[0]) % len(assignment)).tolist())


def _wrap(assignment: np.ndarray, offset: float, width: float) -> tuple[np.ndarray, float]:
    """The same angles with the offset in [0, width): the slot indices shift along."""
    shift = math.floor(offset / width)
    offset -= shift * width
    if offset >= width:  # rounding just below a multiple of the width
        shift, offset = shift + 1, 0.0
    return (assignment + shift) % len(assignment), offset


class CostSurrogate:
    """Every agent's cost round the circle, Ĵ_i(base_0 + x) (x in rad), as the trigonometric
    interpolant of the M multi-start tables ``tables`` (M, n, n), table m at offset m·w/M:
    together they sample each agent at the L = M·n angles base_0 + g·2π/L."""

    def __init__(self, tables: np.ndarray) -> None:
        self.starts, n, _ = tables.shape
        self.agents, self.samples = n, self.starts * n
        samples = tables.transpose(1, 2, 0).reshape(n, self.samples)  # g = j M + m
        self.coefficients = np.fft.rfft(samples, axis=1)  # (n, L//2 + 1)
        self.frequencies = np.arange(self.coefficients.shape[1])
        # weights of the real series: the conjugate half counts twice, but not k = 0 or the
        # Nyquist frequency L/2 (for even L)
        self.weights = np.full(len(self.frequencies), 2.0)
        self.weights[0] = 1.0
        if self.samples % 2 == 0:
            self.weights[-1] = 1.0

    def table(self, offset: float) -> np.ndarray:
        """The cost table (n, n) at ``offset`` (rad): C̃[i, j] ≈ Ĵ_i(base_j + offset)."""
        phase = np.exp(1j * self.frequencies * offset)
        values = np.fft.irfft(self.coefficients * phase, n=self.samples, axis=1)
        return values[:, :: self.starts]

    def ordering(self, assignment: np.ndarray) -> np.ndarray:
        """Fourier coefficients (L//2 + 1,) of θ ↦ J(σ, θ) for the ordering ``assignment``:
        slot j lies j·M samples on, a phase 2πkj/n at frequency k."""
        shift = np.exp(2j * np.pi * np.outer(assignment, self.frequencies) / self.agents)
        return np.sum(self.coefficients * shift, axis=0)

    def evaluate(self, series: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """The real series of :meth:`ordering` at ``offsets`` (rad), any shape."""
        offsets = np.asarray(offsets, float)
        terms = series * np.exp(1j * np.multiply.outer(offsets, self.frequencies))
        return (terms.real @ self.weights) / self.samples

    def minimise(self, assignment: np.ndarray) -> tuple[float, float]:
        """(min J̃(σ, θ), its θ in rad) over the whole circle: the best of n·FINE_OFFSETS
        equally spaced offsets, polished by bounded Brent within one spacing."""
        from scipy.optimize import minimize_scalar
        series = self.ordering(assignment)
        points = self.agents * max(FINE_OFFSETS, 2 * self.starts)  # > L: no aliasing
        step = 2 * np.pi / points
        grid = np.arange(points) * step
        # the series on the grid by one zero-padded inverse FFT (irfft doubles every bin
        # but 0 and its own Nyquist bin, hence weights / 2)
        padded = np.zeros(points // 2 + 1, dtype=complex)
        padded[: len(series)] = series * self.weights / 2
        padded[0] = series[0]
        values = np.fft.irfft(padded, n=points) * points / self.samples
        best = int(np.argmin(values))
        polish = minimize_scalar(lambda theta: float(self.evaluate(series, theta)),
                                 bounds=(grid[best] - step, grid[best] + step),
                                 method="bounded", options={"xatol": 1e-12})
        if polish.fun < values[best]:
            return float(polish.fun), float(polish.x)
        return float(values[best]), float(grid[best])

    def descend(self, assignment: np.ndarray, max_rounds: int) -> tuple[float, float, np.ndarray]:
        """Coordinate descent on the surrogate from ``assignment``: minimise over θ, reassign
        at that θ, until the assignment stops changing. Returns (J̃, θ in [0, w), assignment)."""
        width = 2 * np.pi / self.agents
        value, offset = self.minimise(assignment)
        assignment, offset = _wrap(assignment, offset, width)
        for _ in range(max_rounds):
            table = self.table(offset)
            better = cheapest_assignment(table)
            if not _improves(table, assignment, better):
                break
            value, offset = self.minimise(better)
            assignment, offset = _wrap(better, offset, width)
        return value, offset, assignment


def optimal_ordering(
    problem: FormationProblem,
    backend: Backend,
    tol: float = 1e-12,
    max_rounds: int = 20,
    progress: Callable[[str], None] | None = None,
    starts: int | None = None,
    gap: float = GAP_TOL,
    search_rounds: int = SEARCH_ROUNDS,
) -> OrderingResult:
    """The agent→slot assignment and common offset minimising Σ_i Ĵ_i(φ_i) over equidistant
    φ (see the module docstring): one superstep of ``starts`` cost tables per slot width
    (default :func:`default_starts`), the surrogate's multi-start descent in the coordinator,
    then alternating offset searches (relative tolerance ``tol`` on the offset, as
    :func:`~ocpar.formation.hierarchical.solve_outer_offset`) and cost tables at the new offset
    until the assignment stops changing or ``max_rounds`` offset searches were run.
    Then, where the inner problems are convex in their end position
    (:func:`~ocpar.ocp.reach.end_cost_convexity`), the branch and bound of
    :mod:`~ocpar.formation.ordering_bound` proves the result globally optimal to the relative
    ``gap`` (or improves it), within ``search_rounds`` rounds.
    ``progress`` gets one line for the multi-start and one per round. Raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if an inner solve fails. Only for
    a problem on a :class:`~ocpar.formation.Circle` (ValueError otherwise)."""
    problem.require_circle("ordering 'optimal'")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol!r}")
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, int | np.integer) \
            or max_rounds < 1:
        raise ValueError(f"max_rounds must be an integer ≥ 1, got {max_rounds!r}")
    n = problem.agents
    starts = default_starts(n) if starts is None else starts
    if isinstance(starts, bool) or not isinstance(starts, int | np.integer) or starts < 1:
        raise ValueError(f"starts must be an integer ≥ 1, got {starts!r}")
    if not (np.isfinite(gap) and 0 < gap < 1):
        raise ValueError(f"gap must be a number in (0, 1), got {gap!r}")
    if isinstance(search_rounds, bool) or not isinstance(search_rounds, int | np.integer) \
            or search_rounds < 1:
        raise ValueError(f"search_rounds must be an integer ≥ 1, got {search_rounds!r}")
    width = 2 * np.pi / n
    base = slot_base(problem)
    keep = keep_assignment(problem)
    say = progress or (lambda _line: None)

    # multi-start: tables at `starts` offsets within one slot width, one superstep
    offsets = np.arange(starts) * width / starts
    tables, seed = solved_tables(problem, backend, base[None, :] + offsets[:, None])
    inner_solves, table_supersteps = seed.solved, 1   # pairs out of reach: not solved
    found: dict[tuple[int, ...], np.ndarray] = {}
    scanned: dict[float, float] = {}
    if np.all(np.isfinite(tables)):
        surrogate: CostSurrogate | None = CostSurrogate(tables)
        for offset in np.arange(FINE_OFFSETS) * width / FINE_OFFSETS:
            scan = surrogate.table(offset)
            candidate = cheapest_assignment(scan)
            found.setdefault(_canonical(candidate), candidate)
            scanned[float(offset)] = assignment_cost(scan, candidate)   # the search's start
        descents = [surrogate.descend(a, max_rounds) for a in [keep, *found.values()]]
        estimate, offset, assignment = min(descents, key=lambda d: d[0])
        say(f"ordering tables: {starts} offset(s) x {n}x{n} solves, {len(found)} candidate "
            f"ordering(s); surrogate optimum {estimate:.12e} at offset {offset:.6f} rad, "
            f"{np.count_nonzero(assignment != keep)} agent(s) off the keep ordering")
        begin = [(assignment, offset)]
    else:   # infeasible pairs (+∞): no interpolant; each table's cheapest assignment
        surrogate = None
        best = None
        for table, offset in zip(tables, offsets, strict=True):
            try:
                candidate = cheapest_assignment(table)
            except InnerSolveFailed:   # no finite assignment at this offset
                continue
            found.setdefault(_canonical(candidate), candidate)
            value = assignment_cost(table, candidate)
            if best is None or value < best[0]:
                best = (value, candidate, float(offset))
        # and keep, from its feasible start
        start = feasible_start(problem, base[keep])
        begin = [_wrap(keep, float(start[0] - base[keep[0]]), width)]
        if best is not None:
            begin.insert(0, (best[1], best[2]))
        say(f"ordering tables: {starts} offset(s) x {n}x{n} solves, "
            f"{int(np.sum(~np.isfinite(tables)))} infeasible pair(s), {len(found)} candidate "
            f"ordering(s) with every pair feasible; descending from "
            f"{'the cheapest and ' if best is not None else ''}keep")
    # the offset search: the secant where every agent is feasible everywhere, else the
    # Newton search that keeps to the feasible shifts (hierarchical._shift_newton)
    search = solve_outer_offset if surrogate is not None and not problem.reach_sets() \
        else solve_outer_newton
    objective = OuterObjective(problem, backend)
    outcomes = []
    for assignment, offset in begin:
        try:
            outcomes.append(_descend(problem, backend, objective, search, base, assignment,
                                     offset, tol, max_rounds, surrogate, say))
        except InnerSolveFailed as exc:   # this start's descent met an infeasible step
            failure = exc
    if not outcomes:
        objective.close()
        raise failure
    kinds = {end_cost_convexity(shape) for shape in problem.agents_by_shape()}
    proof = None
    if None not in kinds:
        def polish(assignment: np.ndarray, offset: float) -> float:
            try:
                outcomes.append(_descend(problem, backend, objective, search, base,
                                         assignment, offset, tol, max_rounds, surrogate, say))
            except InnerSolveFailed:
                return math.inf
            return outcomes[-1]["total_cost"]

        exact = kinds == {QUADRATIC} and surrogate is not None \
            and surrogate.samples > 2 * QUADRATIC_DEGREE
        bounds = SurrogateBounds(surrogate, scanned) if exact \
            else PlaneBounds(problem, backend, base, (offsets, seed))
        best = min(o["total_cost"] for o in outcomes)
        proof = branch_and_bound(problem, bounds, best, polish, gap, search_rounds, say)
    objective.close()   # the chosen angles start the outer solve, with its own agents
    table_supersteps += sum(o.pop("tables") for o in outcomes)
    inner_solves += sum(o.pop("solves") for o in outcomes) + objective.inner_solves
    claimed = {} if proof is None else {
        "bound": "quadratic" if isinstance(bounds, SurrogateBounds) else "convex",
        "proven": proof.proven, "gap": proof.gap, "lower_bound": proof.lower_bound,
        "search_supersteps": proof.supersteps, "search_solves": proof.inner_solves,
        "search_message": proof.message}
    return OrderingResult(**min(outcomes, key=lambda o: o["total_cost"]),
                          table_supersteps=table_supersteps + (
                              0 if proof is None else proof.supersteps),
                          inner_solves=inner_solves + (0 if proof is None
                                                       else proof.inner_solves),
                          starts=starts, candidates=len(found), **claimed)


def _descend(problem: FormationProblem, backend: Backend, objective: OuterObjective,
             search, base: np.ndarray, assignment: np.ndarray, offset: float, tol: float,
             max_rounds: int, surrogate: CostSurrogate | None,
             say: Callable[[str], None]) -> dict:
    """The real descent of :func:`optimal_ordering` from ``assignment`` at ``offset``:
    alternating offset searches (``search``) and cost tables at the new offset until the
    assignment stops changing or ``max_rounds`` offset searches were run. Returns the fields
    of :class:`OrderingResult` it decides, with ``tables`` and ``solves`` (its table
    supersteps and their solves)."""
    width = 2 * np.pi / problem.agents
    converged, message = False, f"assignment still changing after {max_rounds} round(s)"
    all_offsets_converged, surrogate_error = True, 0.0 if surrogate is not None else math.nan
    tables = solves = 0
    for rounds in range(1, max_rounds + 1):
        phi0 = base[assignment] + offset
        start_cost = objective.value(phi0)  # the search's first superstep (then cached)
        phi, _, success, offset_message = search(objective, phi0, tol, OFFSET_MAX_ITERATIONS)
        total_cost = objective.value(phi)  # cached: the search's last superstep
        if total_cost > start_cost:
            # started at the optimum (the surrogate's): the search only moved by rounding, or
            # it failed; the start is the better of the two either way
            success = total_cost - start_cost <= IMPROVEMENT_RTOL * abs(start_cost)
            phi, total_cost = phi0, start_cost
        if not success:
            all_offsets_converged = False
            message = f"offset search of round {rounds}: {offset_message}"
        assignment, offset = _wrap(assignment, float(phi[0] - base[assignment[0]]), width)
        found_tables, found = solved_tables(problem, backend, (base + offset)[None, :])
        table = found_tables[0]
        tables += 1
        solves += found.solved
        if surrogate is not None:
            surrogate_error = max(surrogate_error, float(
                np.max(np.abs(surrogate.table(offset) - table)) / np.max(np.abs(table))))
        better = cheapest_assignment(table)
        improved = _improves(table, assignment, better)
        moved = int(np.count_nonzero(better != assignment)) if improved else 0
        say(f"ordering round {rounds}: cost {total_cost:.12e}, {moved} agent(s) moved")
        if not improved:
            converged = all_offsets_converged
            message = "assignment unchanged" if converged else message
            break
        # the better assignment at this offset: its cost is known from the table, exactly
        assignment = better
        phi, total_cost = base[assignment] + offset, assignment_cost(table, assignment)
    return {"phi": np.asarray(phi, float), "assignment": assignment,
            "total_cost": float(total_cost), "rounds": rounds, "converged": converged,
            "offset": offset, "surrogate_error": surrogate_error, "message": message,
            "tables": tables, "solves": solves}
