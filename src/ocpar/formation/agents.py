"""The formation's agents as resident agents (:mod:`ocpar.bsp.resident`): each agent's inner
DMOC solution stays on the worker that computed it, and a superstep moves only what the outer
step needs.

Per agent and superstep the coordinator sends an :class:`AgentTask` (its DMOC shape, shared by
a chunk's agents, and its boundary data: 4 nq numbers) and gets back an :class:`AgentOutcome`
(J*, dJ*/dq_N, the end Hessian's position block, success, status, attempts: 1 + nq + d²
numbers, d = the curve's dimension). The agent's :class:`~ocpar.ocp.DmocSolution` (paths,
controls, multipliers) is its resident state: the next superstep's fallback start (the
failure policy of :func:`~ocpar.ocp.solve_tasks`), gathered by the coordinator once, at the
end. The solves are those of sending the previous solutions out as fallbacks each superstep,
bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ocpar.bsp.columns import SHARED, STACKED, Columns, to_columns
from ocpar.bsp.kernel import run_chunk
from ocpar.ocp import OcpTask, Shape

#: The engine kernel the agents' solves go through (so that the kernel hook
#: :data:`~ocpar.bsp.kernel.WRAPPER_VARIABLE` applies to them as to any superstep's).
INNER_KERNEL = "ocpar.ocp:solve_tasks"


@dataclass(frozen=True)
class AgentTask:
    """One agent's inner solve in a superstep: its DMOC ``shape``, boundary data ``params``
    p = (q_0, q̇_0, q_N, q̇_N) (4 nq,), and ``positions`` d, the number of leading
    configuration entries whose end-Hessian block the outer step needs."""

    shape: Shape
    params: np.ndarray
    positions: int


@dataclass
class AgentOutcome:
    """What the outer step needs of one agent's solve: ``cost`` J* (NaN on failure),
    ``end_gradient`` dJ*/dq_N (nq,), ``end_hessian`` the position block of d²J*/dq_N²
    (d, d), ``success``, the solver's ``status`` and the failure policy's ``attempts``."""

    cost: float
    end_gradient: np.ndarray
    end_hessian: np.ndarray
    success: bool
    status: str
    attempts: int


def solve_agents(tasks: Columns, states: Columns | None) -> tuple[Columns, Columns]:
    """Resident kernel: the agents' solves from ``tasks`` (Columns of :class:`AgentTask`),
    each falling back to its previous solution (``states``: Columns of
    :class:`~ocpar.ocp.DmocSolution`; None on the first superstep: no fallback). Returns
    their :class:`AgentOutcome` and their new solutions (the new states)."""
    k = len(tasks)
    fallback: tuple[str, object] = (SHARED, None)
    if states is not None:
        q, u = np.asarray(states.column("q")), np.asarray(states.column("u"))
        fallback = (STACKED, np.hstack([q[:, 1:-1].reshape(k, -1), u.reshape(k, -1)]))
    inner = Columns(cls=OcpTask, length=k, fields={
        "shape": tasks.fields["shape"], "params": tasks.fields["params"],
        "warm_start": (SHARED, None), "multipliers": (SHARED, None), "fallback": fallback})
    solutions = to_columns(run_chunk(INNER_KERNEL, inner).results)
    assert isinstance(solutions, Columns)
    d = int(tasks.column("positions")[0])  # the curve's dimension: every agent's
    nq = np.asarray(solutions.column("q")).shape[2]
    gradient = np.asarray(solutions.column("cost_gradient"))[:, 2 * nq: 3 * nq]
    outcome = Columns(cls=AgentOutcome, length=k, fields={
        "cost": solutions.fields["cost"],
        "end_gradient": (STACKED, np.ascontiguousarray(gradient)),
        "end_hessian": (STACKED, np.ascontiguousarray(
            np.asarray(solutions.column("end_hessian"))[:, :d, :d])),
        "success": solutions.fields["success"],
        "status": solutions.fields["status"],
        "attempts": solutions.fields["attempts"],
    })
    return outcome, solutions


def agent_tasks(shapes: tuple[str, object], params: np.ndarray, positions: int) -> Columns:
    """Columns of :class:`AgentTask`: one per row of ``params`` (n, 4 nq), the ``shapes``
    column as :meth:`~ocpar.formation.FormationProblem.task_columns` makes it (one shared
    shape, or one per agent), ``positions`` d shared."""
    return Columns(cls=AgentTask, length=len(params), fields={
        "shape": shapes, "params": (STACKED, params), "positions": (SHARED, positions)})


__all__ = ["INNER_KERNEL", "AgentOutcome", "AgentTask", "agent_tasks", "solve_agents"]
