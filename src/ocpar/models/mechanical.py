"""The interface a model offers to the DMOC transcription."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import casadi as ca


@runtime_checkable
class MechanicalSystem(Protocol):
    """A controlled mechanical system on R^nq given by its Lagrangian.

    Implementations are frozen dataclasses: hashable (they key the per-process solver cache)
    and picklable (they travel inside tasks), and they hold no CasADi objects.

    Time-dependent Lagrangians (e.g. linearised about a reference orbit) depend on which DMOC
    interval they are evaluated on: ``interval`` k = 0 … N−1 is the interval [t_k, t_k+1];
    the boundary momenta use the first and the last interval's Lagrangian. Autonomous
    systems ignore it. Optional members: ``time_dependent`` (bool, default False: one
    Lagrangian for all intervals) and ``intervals`` (N, if the model is tabulated per
    interval); ``n_constraints``, ``constraints(q)`` (holonomic constraints c(q) = 0, nc
    entries, each with a multiplier at every node) and ``project(q)`` (numpy rows (m, nq) to
    the nearest configurations that satisfy them, for initial guesses).
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
