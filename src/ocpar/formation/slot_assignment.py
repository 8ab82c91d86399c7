"""The outer solve of a formation onto :class:`~ocpar.formation.slots.Slots`: the assignment
of agents to slots minimising the total inner cost, its pair costs solved in supersteps
(:mod:`ocpar.formation.slots`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.hierarchical import InnerSolveFailed
from ocpar.formation.problem import FormationProblem
from ocpar.formation.slots import SLOT_CANDIDATES, cheapest_assignment
from ocpar.ocp import solve_tasks


@dataclass
class SlotChoice:
    """Outcome of :func:`assign_slots`: ``slots`` (n,) the slot index of each agent;
    ``total_cost`` Σ_i Ĵ_i there; ``candidates`` slots per agent in the last round (m: all,
    the global optimum); ``inner_solves``; ``supersteps``."""

    slots: np.ndarray
    total_cost: float
    candidates: int
    inner_solves: int
    supersteps: int

    @property
    def phi(self) -> np.ndarray:
        """The slots as the formation's parameter vector (floats)."""
        return self.slots.astype(float)


def assign_slots(problem: FormationProblem, backend: Backend,
                 candidates: int = SLOT_CANDIDATES,
                 progress: Callable[[str], None] | None = None) -> SlotChoice:
    """The assignment of ``problem``'s agents to its slots minimising the total inner cost
    (module docstring), its inner solves on ``backend``; raises
    :class:`~ocpar.formation.hierarchical.InnerSolveFailed` if one fails."""
    costs = {"solves": 0, "supersteps": 0}

    def inner_costs(agents: np.ndarray, chosen: np.ndarray) -> np.ndarray:
        sols = backend.superstep_columns(solve_tasks,
                                         problem.tasks_for(agents, chosen.astype(float)))
        costs["solves"] += len(agents)
        costs["supersteps"] += 1
        failed = np.flatnonzero(~np.asarray(sols.column("success"), dtype=bool))
        if len(failed):
            k = int(failed[0])
            raise InnerSolveFailed(
                f"{len(failed)} of {len(agents)} slot-cost solve(s) failed; first: agent "
                f"{agents[k]} to slot {chosen[k]}: {sols.column('status')[k]}")
        return np.asarray(sols.column("cost"), dtype=float)

    starts = problem.positions(problem.starts)
    slots, k, total = cheapest_assignment(starts, problem.curve, candidates, inner_costs,
                                          progress)
    return SlotChoice(slots, total, k, costs["solves"], costs["supersteps"])
