"""Slots: a formation given as m ≥ n target points, so that only the assignment is free.

A :class:`Slots` target has no parameters per agent (k = 0): agent i ends at the slot
σ(i), and the outer problem is the assignment σ that minimises Σ_i Ĵ_i(σ(i)), the problem
that concurrent assignment and planning (CAPT) solves. The angle vector φ of the other
targets carries the slot indices here (exact integers as floats), so that the inner tasks,
the separation rounds, the obstacles and the result work unchanged.

:func:`~ocpar.formation.slot_assignment.assign_slots` solves it, on
:func:`assign_over_candidates`:

1. **Candidates**: for each agent the k nearest slots (:class:`scipy.spatial.cKDTree`) to
   its start position, and the k nearest to its start moved and scaled with all starts
   onto the slots (equal centroids and RMS radii: the slots near its place in the
   formation); k = ``candidates`` to begin with, all m slots when m ≤ k.
2. **Their inner costs**: the ≤ 2 n k inner optimal costs Ĵ_i(slot), one superstep (each
   pair solved once over the rounds).
3. **The assignment**: exact on the candidate pairs (:func:`_match`, by
   :func:`scipy.optimize.linear_sum_assignment`).
4. **Confirmation**: k doubles and steps 2–3 repeat (also while the candidates admit no
   assignment of every agent), until doubling no longer lowers the total; the assignment
   before the last doubling is returned.

With every slot a candidate the assignment is the global optimum. With fewer it is the
optimum over the candidate pairs, and the last doubling found nothing cheaper among twice
as many; ``tests/test_slots.py`` compares it against the full n × m table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ocpar.formation.keep_out.separation import closest_pair

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

#: Candidate slots per agent to begin with (its nearest, twice: module docstring).
SLOT_CANDIDATES = 16
#: Doubling the candidates confirms the assignment when it lowers the total by no more than
#: this fraction of it.
ASSIGNMENT_RTOL = 1e-12


@dataclass(frozen=True, eq=False)
class Slots:
    """m target points ``points`` (m, d), d = 2 or 3 (length unit), all distinct; a formation
    of n ≤ m agents takes n of them (module docstring)."""

    points: np.ndarray
    name: str = "slots"

    def __post_init__(self) -> None:
        try:
            points = np.array(self.points, dtype=float)
        except (TypeError, ValueError):
            raise ValueError("curve: slots must be an array of numbers (m, d)") from None
        if points.ndim != 2 or points.shape[1] not in (2, 3) or not len(points):
            raise ValueError(f"curve: slots must have shape (m, 2) or (m, 3), got "
                             f"{points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("curve: slots must be finite")
        if len(points) > 1:
            gap, (i, j) = closest_pair(points)
            if gap == 0:
                raise ValueError(f"curve: slots {i} and {j} coincide")
        points.setflags(write=False)
        object.__setattr__(self, "points", points)

    @property
    def dim(self) -> int:
        """d, the number of position entries a slot fixes."""
        return self.points.shape[1]

    @property
    def count(self) -> int:
        """m, the number of slots."""
        return len(self.points)

    def at(self, indices: np.ndarray) -> np.ndarray:
        """The slots ``indices`` (n,) (integers, or floats holding them): shape (n, d); a NaN
        index (no slot assigned: a run with no feasible assignment) gives a NaN row."""
        index = np.asarray(indices, float)
        assigned = np.isfinite(index)
        if assigned.all():
            return self.points[index.astype(np.intp)]
        out = np.full((*index.shape, self.dim), np.nan)
        out[assigned] = self.points[index[assigned].astype(np.intp)]
        return out

    def locate(self, points: np.ndarray, hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The slots assigned, ``hint`` (n,), and the distances (n,) of ``points`` (n, d) from
        them, length unit (a slot is not searched for: the assignment names it)."""
        hint = np.asarray(hint, float).ravel()
        return hint, np.linalg.norm(np.asarray(points, float) - self.at(hint), axis=1)


def nearest_assignment(starts: np.ndarray, slots: Slots,
                       candidates: int = SLOT_CANDIDATES) -> np.ndarray:
    """The slot index (n,) of each start position (n, d) minimising Σ_i |start_i − slot|²,
    CAPT's assignment, over each start's ``candidates`` candidate slots
    (:func:`assign_over_candidates`)."""
    def squared(agents: np.ndarray, chosen: np.ndarray) -> np.ndarray:
        return np.sum((starts[agents] - slots.at(chosen)) ** 2, axis=1)
    return assign_over_candidates(starts, slots, candidates, squared)[0]


def assign_over_candidates(starts: np.ndarray, slots: Slots, candidates: int,
                           cost: Callable[[np.ndarray, np.ndarray], np.ndarray],
                           progress: Callable[[str], None] | None = None
                           ) -> tuple[np.ndarray, int, float]:
    """The cheapest assignment of the starts (n, d) to ``slots`` over candidate pairs (module
    docstring: k = ``candidates`` to begin, doubled until an assignment exists and doubling
    no longer lowers the total), the pair costs from ``cost(agents, slots)`` (p,) → (p,),
    each pair's once: (slot per agent (n,), the k of the result, total cost). ``progress``
    gets a line per round."""
    from scipy.spatial import cKDTree
    n, m = len(starts), slots.count
    tree = cKDTree(slots.points)
    near = (starts, _aligned(starts, slots.points))
    known: dict[tuple[int, int], float] = {}
    best: tuple[np.ndarray, int, float] | None = None
    k = min(candidates, m)
    while True:
        pairs = np.unique(np.concatenate([_nearest_pairs(tree, points, k) for points in near]),
                          axis=0)
        new = [tuple(pair) for pair in pairs.tolist() if tuple(pair) not in known]
        if new:
            fresh = np.array(new)
            known.update(zip(new, cost(fresh[:, 0], fresh[:, 1]).tolist(), strict=True))
        values = np.array([known[pair] for pair in map(tuple, pairs.tolist())])
        try:
            assignment = _match(pairs, values, n, m)
        except ValueError:   # no assignment of every agent on these candidates
            if k == m:
                raise
            k = min(2 * k, m)
            continue
        total = float(sum(known[(i, int(s))] for i, s in enumerate(assignment)))
        if progress is not None:
            progress(f"slots: {k} candidate(s) per agent, {len(pairs)} pairs ({len(new)} new), "
                     f"total cost {total:.12e}")
        if best is not None and total >= best[2] - ASSIGNMENT_RTOL * abs(best[2]):
            return best
        best = (assignment, k, total)
        if k == m:
            return best
        k = min(2 * k, m)


def _nearest_pairs(tree: cKDTree, points: np.ndarray, k: int) -> np.ndarray:
    """(agent, slot) pairs (n k, 2) of each of ``points`` (n, d) with its k nearest slots."""
    _, nearest = tree.query(points, k=k)
    nearest = np.asarray(nearest).reshape(len(points), k)
    return np.column_stack([np.repeat(np.arange(len(points)), k), nearest.ravel()])


def _aligned(starts: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``starts`` (n, d) moved and scaled onto ``points`` (m, d): their centroids and RMS
    radii made equal, so that each start's nearest slots are the ones near its place in the
    formation, not the side of the slots nearest to all the starts."""
    spread = np.sqrt(np.mean(np.sum((starts - starts.mean(axis=0)) ** 2, axis=1)))
    target = np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))
    scale = target / spread if spread > 0 else 1.0
    return (starts - starts.mean(axis=0)) * scale + points.mean(axis=0)


def _match(pairs: np.ndarray, values: np.ndarray, n: int, m: int) -> np.ndarray:
    """The cheapest assignment of n agents to m slots over the candidate ``pairs`` (p, 2)
    (agent, slot) of costs ``values`` (p,): slot index per agent (n,). ValueError if none
    exists. Solved by :func:`scipy.optimize.linear_sum_assignment` on the dense n × m table
    with every other pair priced above any assignment over candidates (n m 8 bytes: 0.8 GB at
    10,000 × 10,000, ~150 s there on this machine, loaded); scipy's sparse
    ``min_weight_full_bipartite_matching`` took 11 s at 1000 × 1000 with 62,000 candidate
    pairs and 229 s at 4000 (integer costs), against 0.75 s and 25 s dense. Pairs of cost +∞
    (infeasible) are no candidates."""
    from scipy.optimize import linear_sum_assignment
    feasible = np.isfinite(values)
    pairs, values = pairs[feasible], values[feasible]
    if not len(values):
        raise ValueError("the candidate pairs admit no assignment of every agent")
    priced_out = (n + 1) * (float(values.max() - values.min()) + 1.0) + float(values.max())
    dense = np.full((n, m), priced_out)
    dense[pairs[:, 0], pairs[:, 1]] = values
    rows, cols = linear_sum_assignment(dense)
    if np.any(dense[rows, cols] == priced_out):
        raise ValueError("the candidate pairs admit no assignment of every agent")
    assignment = np.empty(n, dtype=np.intp)
    assignment[rows] = cols
    return assignment
