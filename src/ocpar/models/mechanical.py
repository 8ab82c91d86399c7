"""The interface a model offers to the DMOC transcription."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import casadi as ca


@runtime_checkable
class MechanicalSystem(Protocol):
    """A controlled mechanical system on R^nq given by its Lagrangian L(q, q̇, t), a generalised
    force F(q, u) and optional holonomic constraints c(q) = 0: the class of agents the
    formation scheme (DMOC) accepts. Any model with these members works; nothing else in ocpar
    needs to know it (:class:`~ocpar.models.PointMass` and
    :class:`~ocpar.models.RelativeRigidSpacecraft` are two instances).

    Implementations are frozen dataclasses: hashable (they key the per-process solver cache)
    and picklable (they travel inside tasks), and they hold no CasADi objects.

    Time: DMOC's midpoint rule evaluates L once per interval, so a time-dependent Lagrangian
    L(q, q̇, t) is given per DMOC interval: ``lagrangian(q, qdot, interval)`` with
    ``interval`` k = 0 … N−1 the interval [t_k, t_k+1] returns L(q, q̇, t_k+½),
    t_k+½ = (k + ½) T/N (e.g. linearised about a reference orbit, tabulated at those times);
    the boundary momenta use the first and the last interval's Lagrangian. Such a model sets
    ``time_dependent = True`` and, since it must know T/N, ``intervals`` = N (the DMOC shape
    checks that it matches). Autonomous systems ignore ``interval``.

    Optional members: ``time_dependent`` (bool, default False: one Lagrangian for all
    intervals) and ``intervals`` (N, if the model is tabulated per interval);
    ``n_constraints``, ``constraints(q)`` (holonomic constraints c(q) = 0, nc entries, each
    with a multiplier at every node, boundary nodes included, whose boundary configurations
    must satisfy them) and ``project(q)`` (numpy rows (m, nq) to the nearest configurations
    that satisfy them, for initial guesses; required with constraints); ``cost_parts``
    ({name: (first, last) control entries}: the cost ∫|u|² dt split into named groups in
    results); ``position_indices`` (the configuration entries that are the agent's position
    in space, what separation between agents measures; default: the first d entries, d the
    formation curve's dimension).
    """

    @property
    def nq(self) -> int:
        """Dimension of the configuration q."""
        ...

    @property
    def nu(self) -> int:
        """Dimension of the control u."""
        ...

    def lagrangian(self, q: ca.SX, qdot: ca.SX, interval: int = 0) -> ca.SX:
        """L(q, q̇) on DMOC interval ``interval``, a scalar expression; q and q̇ are (nq, 1)."""
        ...

    def generalized_force(self, q: ca.SX, u: ca.SX) -> ca.SX:
        """Generalised force (nq, 1) exerted by control u (nu, 1) at configuration q."""
        ...
