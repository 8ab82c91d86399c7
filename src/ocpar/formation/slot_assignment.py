"""The outer solve of a formation onto :class:`~ocpar.formation.targets.slots.Slots`: the assignment
of agents to slots minimising the total inner cost, its pair costs solved in supersteps
(:mod:`ocpar.formation.targets.slots`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ocpar.bsp import Backend
from ocpar.formation.feasibility import InnerSolveFailed, NoFeasibleFormation, phase_one
from ocpar.formation.ordering import solved_pairs
from ocpar.formation.problem import FormationProblem
from ocpar.formation.targets.slots import SLOT_CANDIDATES, assign_over_candidates


@dataclass
class SlotChoice:
    """Outcome of :func:`assign_slots`: ``slots`` (n,) the slot index of each agent;
    ``total_cost`` Σ_i Ĵ_i there; ``candidates`` slots per agent in the last round (m: all,
    the global optimum); ``inner_solves``."""

    slots: np.ndarray
    total_cost: float
    candidates: int
    inner_solves: int

    @property
    def phi(self) -> np.ndarray:
        """The slots as the formation's parameter vector (floats)."""
        return self.slots.astype(float)


def assign_slots(problem: FormationProblem, backend: Backend,
                 candidates: int = SLOT_CANDIDATES,
                 progress: Callable[[str], None] | None = None) -> SlotChoice:
    """The assignment of ``problem``'s agents to its slots minimising the total inner cost
    (module docstring), its inner solves on ``backend`` (an infeasible pair is +∞:
    :func:`~ocpar.formation.ordering.pair_costs`); where no assignment has every agent's pair
    feasible, phase 1 (:func:`~ocpar.formation.feasibility.phase_one`: the assignment of
    least total elastic slack) raises
    :class:`~ocpar.formation.feasibility.NoFeasibleFormation` with that slack."""
    solves = 0

    def inner_costs(agents: np.ndarray, chosen: np.ndarray) -> np.ndarray:
        nonlocal solves
        found = solved_pairs(problem, backend, agents, chosen.astype(float), "slot-cost")
        solves += found.solved   # the pairs out of reach are +∞, not solved
        return found.costs

    starts = problem.positions(problem.starts)
    try:
        slots, k, total = assign_over_candidates(starts, problem.curve, candidates,
                                                 inner_costs, progress)
    except ValueError:   # every slot a candidate, and no assignment of finite pairs
        # phase 1: the assignment of least total slack; raises NoFeasibleFormation with it
        try:
            found = phase_one(problem, backend, problem.initial_phi(), progress=progress)
        except NoFeasibleFormation as exc:
            raise NoFeasibleFormation(f"no assignment of every agent to a slot it can reach: "
                                      f"{exc}", exc.slack) from None
        slots = found.phi.astype(np.intp)   # (only if the hard solves failed where it is 0)
        solves += found.inner_solves
        total, k = float(np.sum(inner_costs(np.arange(problem.agents), slots))), \
            problem.curve.count
        if not np.isfinite(total):
            raise InnerSolveFailed("no assignment of every agent to a slot it can reach "
                                   "(every one takes an infeasible pair)") from None
    return SlotChoice(slots, total, k, solves)
