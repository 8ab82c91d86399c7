"""The proof of :func:`~ocpar.formation.ordering.optimal_ordering`: branch and bound over the
common offset θ ∈ [0, w] (w = 2π/n) with assignment lower bounds on intervals of θ.

F(θ) = min_σ Σ_i Ĵ_i(θ + base_σ(i)) is the cost of the best ordering at offset θ (a linear
assignment problem, LAP, on the n × n table of inner costs); the optimum is min_θ F(θ). On an
interval [a, b] of length ℓ, each pair (agent i, slot j) gets an affine lower bound in θ,
anchored at either end e ∈ {a, b}: a function P_ij (below) with P_ij ≤ Ĵ_i(· + base_j) on the
whole interval, value V = P(e), slope S = P′(e) and |P″| ≤ K gives

    Ĵ_ij(θ) ≥ P(θ) ≥ V + S (θ − e) − ½ K ℓ |θ − e|     (θ in [a, b]),

affine in θ, so for every ordering σ the sum over i is affine and its minimum over the
interval is at an end: min(LAP(V), LAP(V ± S ℓ − ½ K ℓ²)) is a lower bound on min F over
[a, b], from either anchor (the larger one is kept). Its error is O(ℓ²), so intervals near an
optimum need not be tiny. P comes from what is known of the inner problem
(:func:`~ocpar.ocp.reach.end_cost_convexity`):

* **convex** (point masses, or linear–quadratic ODE agents, with box or norm thrust limits):
  Ĵ_i is convex in the end position z (the rest of p held fixed: the restriction of a convex
  function) and each solve returns its derivative g = dĴ/dz, so every solved point (z₀, Ĵ₀,
  g) gives a supporting plane Ĵ_i(z) ≥ Ĵ₀ + g·(z − z₀), valid wherever agent i can go; on
  the circle z(φ) = c + r (cos φ e₀ + sin φ e₁) it is a sinusoid of φ with |P″| ≤ r |(g·e₀,
  g·e₁)|. At an end where the pair is feasible P is its own plane (V = Ĵ, exact); where it
  is not (outside the exact reach set, or a failed solve) the plane of the agent's solved
  point nearest on the circle. A pair whose reach excess e (1-Lipschitz in z, ≤ 0 where
  reachable) is positive at both ends with e_a + e_b > r ℓ is infeasible on the whole
  interval: +∞.
* **quadratic** (no inequalities): J*_i is a convex quadratic of its boundary data p, and
  the parts of p that vary with φ are affine in (cos φ, sin φ): a point mass's end position
  z(φ) = c + r (cos φ e₀ + sin φ e₁); an ODE agent's end state, z(φ) in its position entries
  and the fixed ``final_state`` elsewhere (free entries minimised out, which keeps J* a
  convex quadratic of the rest), its start fixed. So Ĵ_i(φ) = J*_i(p(φ)) is a trigonometric
  polynomial of degree 2 whatever the agent's quadratic form (no structure such as a
  dependence on the displacement alone is used), and the surrogate of the multi-start
  tables (:class:`~ocpar.formation.ordering.CostSurrogate`, L > 4 samples of each agent
  round the circle) is exact: it interpolates each agent's own solved costs;
  K_i = Σ_k k² |c_k| bounds its second derivative, so Ĵ_ij lies above its chord on
  [a, b] less K_i ℓ²/8, and the bound is min(F(a), F(b)) − Σ_i K_i ℓ²/8 (a shift of a row
  does not change the best assignment): no inner solves, one LAP per offset.

Any pair may be left unsolved at an offset (then bounded like an infeasible one, by the
plane of its agent's nearest solved point): the first round is the multi-start's tables
(every pair solved, ``seed``), later rounds solve only the pairs that can matter by the
planes' bounds (each agent's :data:`LAZY_SLOTS` cheapest slots and the cheapest
assignment: a choice that leaves every bound valid, and on the tests' fleets about as few
rounds as solving every pair, with a third of the solves).

Upper bounds: the LAP of the real table at every solved offset (its unsolved pairs +∞: a
formation with real costs); the best one, where it beats the best known by more than the
gap, is polished by the offset search of its ordering (``polish``). Each round splits the
open intervals of the smallest bounds (at most :data:`SPLITS_PER_ROUND`) at their
midpoints, all solved in ONE superstep, and drops those whose bound is within the gap of
the best. It stops when the proven gap (best − smallest bound) / best ≤ ``gap``,
or at its budget of supersteps. The bounds are exact up to the inner solves' accuracy
(``DmocShape.kkt_tol``); a failed solve inside the reach set leaves the gap unproven.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.feasibility import InnerCosts, inner_costs
from ocpar.formation.problem import FormationProblem

#: The search's stopping test: the proven relative gap (best − lower bound) / best.
GAP_TOL = 1e-9

#: The search's budget: rounds at most (each one superstep of inner solves where the bounds
#: come from solves).
SEARCH_ROUNDS = 100

#: Intervals of the offset (per slot width) the search starts from.
FIRST_INTERVALS = 8

#: Slots per agent solved at a new offset (its cheapest by the planes' bounds), besides the
#: cheapest assignment's.
LAZY_SLOTS = 2

#: Intervals split per round at most (those of the smallest lower bounds).
SPLITS_PER_ROUND = 32


@dataclass
class SearchOutcome:
    """What the search proved: ``lower_bound`` on the optimum (cost unit), ``gap`` the
    relative gap (best − lower bound) / best, ``proven`` gap ≤ the tolerance, ``supersteps``
    and ``inner_solves`` of the search (its polishing offset searches included), ``failed``
    inner solves inside a reach set (each leaves the gap unproven), ``intervals`` of the
    offset examined, and why it stopped (``message``)."""

    lower_bound: float
    gap: float
    proven: bool
    supersteps: int
    inner_solves: int
    failed: int
    intervals: int
    message: str


@dataclass
class _Point:
    """One offset θ of the search: its table (n, n) (real, +∞ where infeasible or not
    solved; the surrogate's), and, once computed, per pair the anchor data of the module
    docstring (:meth:`PlaneBounds.anchor`) and the LAP of its values."""

    theta: float
    table: np.ndarray | None
    gradients: np.ndarray | None = None   # (n, n, d) dĴ/dz, NaN where infeasible
    excess: np.ndarray | None = None      # (n, n) reach excess, −∞ where none is known
    anchor: tuple[np.ndarray, ...] | None = None
    anchor_lap: float = math.nan   # LAP(V) (V = the table where every pair is feasible)


def _lap(table: np.ndarray) -> tuple[float, np.ndarray | None]:
    """(min over assignments of Σ table[i, σ(i)], σ): +∞ and None if every one is +∞,
    −∞ and None (no bound) if the table holds −∞ or NaN."""
    from scipy.optimize import linear_sum_assignment
    if not np.all(np.isfinite(table) | (table == np.inf)):
        return -math.inf, None
    try:
        rows, cols = linear_sum_assignment(table)
    except ValueError:
        return math.inf, None
    assignment = np.empty(len(table), dtype=np.intp)
    assignment[rows] = cols
    return float(np.sum(table[rows, cols])), assignment


class PlaneBounds:
    """Anchors from supporting planes of solved points (convex inner problems): each round's
    new offsets are solved in one superstep (n² solves each, with dĴ/dz)."""

    def __init__(self, problem: FormationProblem, backend: Backend, base: np.ndarray,
                 seed: tuple[np.ndarray, InnerCosts] | None = None) -> None:
        self.problem, self.backend, self.base = problem, backend, base
        self.curve = problem.curve   # a Circle: z(φ) = c + r (cos φ e₀ + sin φ e₁)
        n = problem.agents
        self.n = n
        # every feasible solved point per agent: angle (mod 2π), cost, gradient
        self.known: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in
                                                                              range(n)]
        self.supersteps = self.solves = self.failed = 0
        self.starts = problem.positions(problem.starts)
        self.reach = np.full(n, None, dtype=object)
        for reach, members in problem.reach_sets():
            for i in members:
                self.reach[i] = reach
        self.seed = seed

    def evaluate(self, thetas: np.ndarray, lazy: bool = True) -> list[_Point]:
        """The points at ``thetas`` (rad), their pairs solved in one superstep: all of them,
        or (``lazy``, once planes are known) those that can matter (:meth:`_chosen`); the
        others stay +∞ in the point's table (no upper bound uses them) and are bounded by
        the planes of the agent's nearest solved points, like an infeasible pair."""
        points = [self._blank(float(theta)) for theta in thetas]
        chosen = np.stack([self._chosen(point) if lazy else np.ones((self.n, self.n), bool)
                           for point in points])                           # (m, n, n)
        where = np.nonzero(chosen)
        slots = self.base[where[2]] + np.asarray(thetas)[where[0]]
        found = inner_costs(self.problem, self.backend, where[1], slots)
        self.supersteps += 1
        self._record(points, where, found)
        return points

    def first(self, width: float) -> list[_Point]:
        """The first round: the multi-start's tables (``seed``: their offsets in [0,
        ``width``) and their superstep's :class:`~ocpar.formation.feasibility.InnerCosts`),
        with ``width`` itself (offset 0's table: a shift by a slot width moves every agent
        to the next slot); without them :data:`FIRST_INTERVALS` intervals, every pair
        solved (one superstep)."""
        if self.seed is None:
            return self.evaluate(np.linspace(0.0, width, FIRST_INTERVALS + 1), lazy=False)
        offsets, found = self.seed
        n, m = self.n, len(offsets)
        points = [self._blank(float(theta)) for theta in offsets]
        where = np.nonzero(np.ones((m, n, n), dtype=bool))
        self._record(points, where, found, counted=False)   # the multi-start's solves
        last = self._blank(width)
        last.table = np.roll(points[0].table, -1, axis=1)
        last.gradients = np.roll(points[0].gradients, -1, axis=1)
        return [*points, last]

    def _blank(self, theta: float) -> _Point:
        """The point at offset ``theta`` (rad) with nothing solved: its reach excesses."""
        n = self.n
        excess = np.full((n, n), -np.inf)
        ends = self.curve.points(self.base + theta)                        # (n, d)
        for i in range(n):
            if self.reach[i] is not None:
                excess[i] = self.reach[i].excess(ends - self.starts[i])
        return _Point(theta, np.full((n, n), np.inf), np.full((n, n, ends.shape[1]), np.nan),
                      excess)

    def _record(self, points: list[_Point], where: tuple[np.ndarray, ...],
                found: InnerCosts, counted: bool = True) -> None:
        """The solves ``found`` of the pairs ``where`` (point, agent, slot) into their points'
        tables and the agents' known planes (counted as the search's own, or not)."""
        self.solves += found.solved if counted else 0
        self.failed += found.failed
        for k, point in enumerate(points):
            rows = where[0] == k
            point.table[where[1][rows], where[2][rows]] = found.costs[rows]
            point.gradients[where[1][rows], where[2][rows]] = found.gradients[rows]
            slots = self.base + point.theta
            for i in range(self.n):
                ok = np.isfinite(point.table[i])
                if np.any(ok):
                    self.known[i].append((np.mod(slots[ok], 2 * np.pi), point.table[i][ok],
                                          point.gradients[i][ok]))

    def _chosen(self, point: _Point) -> np.ndarray:
        """The pairs (n, n) worth solving at ``point`` (before any is solved there): on the
        planes' lower bounds V, each agent's :data:`LAZY_SLOTS` cheapest slots and the
        cheapest assignment's pairs; every pair of an agent without a plane yet; none
        outside its reach set."""
        value = self.anchor(point)[0]
        chosen = np.zeros(value.shape, dtype=bool)
        rows = np.arange(len(value))
        order = np.argsort(value, axis=1)[:, :LAZY_SLOTS]
        chosen[rows[:, None], order] = True
        assignment = _lap(value)[1]
        if assignment is not None:
            chosen[rows, assignment] = True
        chosen[~np.all(np.isfinite(value), axis=1)] = True
        return chosen & ~(point.excess > 0)

    def anchor(self, point: _Point) -> tuple[np.ndarray, ...]:
        """V, S (n, n) at ``point`` (module docstring), from the planes known now, and each
        plane's amplitude ρ and phase β (n, n) on the circle: P(φ) = A + ρ cos(φ − β)."""
        phi = self.base + point.theta                                      # (n,)
        z, tangent = self.curve.points(phi), self.curve.tangents(phi)     # (n, d)
        value = point.table.copy()
        gradient = point.gradients.copy()                                  # (n, n, d)
        origin = np.broadcast_to(z, gradient.shape).copy()                 # the planes' z₀
        for i in np.flatnonzero(~np.all(np.isfinite(value), axis=1)):
            if not self.known[i]:
                value[i][~np.isfinite(value[i])] = -np.inf   # nothing known: no bound
                continue
            angles, costs, grads = (np.concatenate(part) for part in zip(*self.known[i],
                                                                            strict=True))
            for j in np.flatnonzero(~np.isfinite(value[i])):
                gap = np.abs(np.angle(np.exp(1j * (angles - phi[j]))))
                k = int(np.argmin(gap))
                value[i, j], gradient[i, j] = costs[k], grads[k]
                origin[i, j] = self.curve.points(angles[k:k + 1])[0]
                value[i, j] += float(gradient[i, j] @ (z[j] - origin[i, j]))
        slope = np.einsum("ijd,jd->ij", gradient, tangent)
        # the plane on the circle: P(φ) = A + ρ cos(φ − β), P″ = −ρ cos(φ − β)
        planar = self.curve.radius * (gradient @ self.curve.plane.T)      # (n, n, 2)
        amplitude = np.where(np.isfinite(value), np.hypot(planar[..., 0], planar[..., 1]), 0)
        phase = np.arctan2(planar[..., 1], planar[..., 0])
        return value, slope, amplitude, np.nan_to_num(phase)

    def excluded(self, a: _Point, b: _Point) -> np.ndarray:
        """Pairs (n, n) provably outside their reach on the whole interval [a, b]."""
        length = self.curve.radius * (b.theta - a.theta)
        return (a.excess > 0) & (b.excess > 0) & (a.excess + b.excess > length)

    def interval_bound(self, a: _Point, b: _Point) -> float:
        """The larger of the two anchors' bounds (module docstring)."""
        length = b.theta - a.theta
        out = self.excluded(a, b)
        best = -math.inf
        for here, sign in ((a, 1.0), (b, -1.0)):
            if here.anchor is None:
                here.anchor = self.anchor(here)
            value, slope, amplitude, phase = here.anchor
            if not np.any(out):   # LAP(V) is the point's own only where nothing is excluded
                if math.isnan(here.anchor_lap):
                    here.anchor_lap = _lap(value)[0]
                near = here.anchor_lap
            else:
                near = _lap(np.where(out, np.inf, value))[0]
            if near <= best:   # this anchor cannot raise the bound
                continue
            curvature = amplitude * self._concavity(a.theta, b.theta, phase)
            far = value + sign * slope * length - 0.5 * curvature * length**2
            best = max(best, min(near, _lap(np.where(out, np.inf, far))[0]))
        return best

    def _concavity(self, a: float, b: float, phase: np.ndarray) -> np.ndarray:
        """max(0, max of cos(φ − β) over slot j's arc φ ∈ [base_j + a, base_j + b]) (n, n):
        −P″ / ρ at its largest, 0 where the plane is convex on the whole arc."""
        start = np.mod(self.base + a - phase, 2 * np.pi)                 # (n, n): φ_a − β
        inside = start + (b - a) >= 2 * np.pi                             # β on the arc
        ends = np.maximum(np.cos(start), np.cos(start + (b - a)))
        return np.clip(np.where(inside, 1.0, ends), 0.0, 1.0)


class SurrogateBounds:
    """Anchors from the exact surrogate (inner costs quadratic in z): no inner solves."""

    def __init__(self, surrogate, scanned: dict[float, float] | None = None) -> None:
        self.surrogate = surrogate
        self.scanned = scanned or {}
        c = surrogate.coefficients                                         # (n, L//2+1)
        k = surrogate.frequencies
        # |f''| ≤ (1/L) Σ_k w_k k² |c_k| per agent
        self.curvature = (np.abs(c) * surrogate.weights * k**2).sum(axis=1) / surrogate.samples
        self.supersteps = self.solves = self.failed = 0

    def evaluate(self, thetas: np.ndarray) -> list[_Point]:
        return [_Point(float(t), self.surrogate.table(float(t))) for t in thetas]

    def first(self, width: float) -> list[_Point]:
        """The first round: the offsets the multi-start scanned (``scanned``: offset in
        [0, ``width``) → its LAP, known), and ``width`` itself (the same LAP as 0: a shift
        by a slot width relabels the slots); :data:`FIRST_INTERVALS` intervals without."""
        if 0.0 not in self.scanned:
            return self.evaluate(np.linspace(0.0, width, FIRST_INTERVALS + 1))
        points = self.evaluate(np.array([*sorted(self.scanned), width]))
        for point in points:
            point.anchor_lap = self.scanned.get(point.theta, self.scanned[0.0])
        return points

    def interval_bound(self, a: _Point, b: _Point) -> float:
        """Each Ĵ_ij lies above its chord on [a, b] less K_i ℓ²/8, an affine function whose
        row shift is the same for every slot: min(F(a), F(b)) − Σ_i K_i ℓ²/8."""
        for point in (a, b):
            if math.isnan(point.anchor_lap):
                point.anchor_lap = _lap(point.table)[0]
        length = b.theta - a.theta
        return min(a.anchor_lap, b.anchor_lap) - float(np.sum(self.curvature)) * length**2 / 8


@dataclass
class _Interval:
    a: _Point
    b: _Point
    bound: float = math.nan


def branch_and_bound(problem: FormationProblem, bounds, best: float,
                     polish: Callable[[np.ndarray, float], float],
                     gap: float, max_supersteps: int,
                     say: Callable[[str], None]) -> SearchOutcome:
    """The search of the module docstring on ``bounds`` (:class:`PlaneBounds` or
    :class:`SurrogateBounds`) from the best known total ``best``; ``polish(assignment,
    offset)`` runs the offset search of an ordering (slot index per agent) from an offset
    (rad) and returns its real total, +∞ if it failed (it becomes the best known if lower)."""
    n = problem.agents
    width = 2 * np.pi / n

    def improve(points: list[_Point]) -> None:
        nonlocal best
        found = None
        for point in points:
            table = point.table
            if table is None:
                continue
            if math.isnan(point.anchor_lap) or not np.all(np.isfinite(table)):
                value = _lap(table)[0]
                if np.all(np.isfinite(table)):   # then V = the table: LAP(V) known
                    point.anchor_lap = value
            else:
                value = point.anchor_lap
            if value < best * (1 - gap) and (found is None or value < found[0]):
                found = (value, point)
        if found is not None and (assignment := _lap(found[1].table)[1]) is not None:
            best = min(best, polish(assignment, found[1].theta))   # a real outcome, or +∞

    points = bounds.first(width)
    improve(points)
    open_ = [_Interval(a, b) for a, b in itertools.pairwise(points)]
    closed: list[float] = []
    rounds = 1
    while True:
        for interval in open_:
            if math.isnan(interval.bound):
                interval.bound = bounds.interval_bound(interval.a, interval.b)
        cut = best * (1 - gap)
        closed += [iv.bound for iv in open_ if iv.bound >= cut]
        open_ = sorted((iv for iv in open_ if iv.bound < cut), key=lambda iv: iv.bound)
        lower = min([iv.bound for iv in open_] + closed + [best])
        proven_gap = max(0.0, (best - lower) / abs(best)) if math.isfinite(lower) else math.inf
        count = len(closed) + len(open_)
        say(f"ordering search round {rounds}: best {best:.12e}, lower bound {lower:.12e} "
            f"(gap {proven_gap:.2e}), {len(open_)} open interval(s) of {count}")
        if not open_:
            message = f"proven: gap {proven_gap:.2e} ≤ {gap:g}"
            break
        if rounds >= max_supersteps:
            message = (f"stopped by its budget of {max_supersteps} round(s) at a proven "
                       f"gap of {proven_gap:.2e} (> {gap:g})")
            break
        split = open_[:SPLITS_PER_ROUND]
        middles = bounds.evaluate(np.array([(iv.a.theta + iv.b.theta) / 2 for iv in split]))
        improve(middles)
        rest = open_[SPLITS_PER_ROUND:]
        open_ = rest + [half for iv, mid in zip(split, middles, strict=True)
                        for half in (_Interval(iv.a, mid), _Interval(mid, iv.b))]
        rounds += 1
    proven = not open_ and bounds.failed == 0
    if bounds.failed and not open_:
        message = (f"not proven: {bounds.failed} inner solve(s) failed inside their reach "
                   f"set (priced +∞); gap {proven_gap:.2e} otherwise")
    return SearchOutcome(lower_bound=lower, gap=proven_gap, proven=proven,
                         supersteps=bounds.supersteps, inner_solves=bounds.solves,
                         failed=bounds.failed, intervals=len(closed) + len(open_),
                         message=message)
