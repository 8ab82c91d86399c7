"""The global archive A_g: non-dominated solutions, bounded in size by a potential-field filter.

When the archive exceeds its size, members are removed one at a time, each time the one with
the largest pseudo-electric potential Σ_k 1/d_ik (d in objective space normalised to the
archive's ideal and nadir), never one of the extremes (the best of each objective): what is
left is spread along the front (after Ricciardi & Vasile, Eurogen 2015).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Objective differences below this (relative) count as ties: solutions on a bound of t_f
#: differ by IPOPT's bound relaxation (~1e-8) and must still dominate each other.
TIE_TOL = 1e-7


@dataclass
class Member:
    """One archived solution: its NLP vector ``z``, objectives ``objectives`` (m,), and
    whether a scalarised local search produced it (``optimised``) or only restoration. After
    the final refinement (None before): whether its refinement was kept (``refined``), whether
    its point is one a neighbour's start reached (``moved``) and by how much that dominates
    what its own start reached (``improvement``, Σ_i ΔJ_i/s_i over the archive's span s),
    whether none of the starts of its last check beat it by more than the tolerance
    (``settled``), its Pareto-stationarity residual ``stationarity`` and trade-off weights
    ``tradeoff`` (m,)."""

    z: np.ndarray
    objectives: np.ndarray
    optimised: bool = True
    refined: bool | None = None
    moved: bool | None = None
    improvement: float | None = None
    settled: bool | None = None
    stationarity: float | None = None
    tradeoff: np.ndarray | None = None


def dominates(a: np.ndarray, b: np.ndarray) -> bool:
    """a Pareto-dominates b (minimisation), with ties up to :data:`TIE_TOL`."""
    tol = TIE_TOL * (1 + np.abs(b))
    return bool(np.all(a <= b + tol) and np.any(a < b - tol))


@dataclass
class Archive:
    """Non-dominated members of ``n_objectives`` objectives, at most ``size`` of them."""

    size: int
    n_objectives: int
    members: list[Member] = field(default_factory=list)

    def objectives(self) -> np.ndarray:
        """Objectives of the members, shape (len, m)."""
        return np.array([m.objectives for m in self.members]).reshape(-1, self.n_objectives)

    def ideal_and_nadir(self) -> tuple[np.ndarray, np.ndarray]:
        """Componentwise best (utopia z) and worst (nadir z*_A) objectives of the members."""
        f = self.objectives()
        return f.min(axis=0), f.max(axis=0)

    def add(self, candidates: list[Member]) -> int:
        """Insert the non-dominated candidates, drop what they dominate, filter to ``size``.
        Returns how many candidates are in the archive afterwards."""
        pool = self.members + candidates
        if not pool:  # nothing feasible yet (every search so far failed)
            return 0
        f = np.array([m.objectives for m in pool], dtype=float).reshape(len(pool), -1)
        a, b = f[:, None, :], f[None, :, :]  # [i, k]: does pool[i] dominate / repeat pool[k]?
        tol = TIE_TOL * (1 + np.abs(b))
        dominated = (np.all(a <= b + tol, axis=2) & np.any(a < b - tol, axis=2)).any(axis=0)
        # np.allclose(pool[i], pool[k], rtol=atol=TIE_TOL) for an earlier i < k
        close = np.all(np.abs(a - b) <= TIE_TOL + TIE_TOL * np.abs(b), axis=2)
        duplicate = np.triu(close, k=1).any(axis=0)
        keep = [m for m, drop in zip(pool, dominated | duplicate, strict=True) if not drop]
        self.members = self._filter(keep)
        return sum(any(m is c for m in self.members) for c in candidates)

    def _filter(self, members: list[Member]) -> list[Member]:
        while len(members) > self.size:
            f = np.array([m.objectives for m in members])
            span = np.maximum(f.max(axis=0) - f.min(axis=0), 1e-300)
            g = (f - f.min(axis=0)) / span
            d = np.linalg.norm(g[:, None, :] - g[None, :, :], axis=2)
            np.fill_diagonal(d, np.inf)
            potential = np.sum(1.0 / np.maximum(d, 1e-12), axis=1)
            potential[np.argmin(f, axis=0)] = -np.inf  # keep the extremes
            members = [m for i, m in enumerate(members) if i != int(np.argmax(potential))]
        return members
