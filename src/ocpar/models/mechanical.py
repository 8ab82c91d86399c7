"""The interface a model offers to the DMOC transcription."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import casadi as ca


@runtime_checkable
class MechanicalSystem(Protocol):
    """A controlled mechanical system on R^nq given by its Lagrangian.

    Implementations are frozen dataclasses: hashable (they key the per-process solver cache)
    and picklable (they travel inside tasks), and they hold no CasADi objects.
    """

    @property
    def nq(self) -> int:
        """Dimension of the configuration q."""
        ...

    @property
    def nu(self) -> int:
        """Dimension of the control u."""
        ...

    def lagrangian(self, q: ca.SX, qdot: ca.SX) -> ca.SX:
        """L(q, q̇), a scalar expression; q and q̇ are (nq, 1)."""
        ...

    def generalized_force(self, q: ca.SX, u: ca.SX) -> ca.SX:
        """Generalised force (nq, 1) exerted by control u (nu, 1) at configuration q."""
        ...
