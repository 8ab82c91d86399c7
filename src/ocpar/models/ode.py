"""The interface a model offers to the multiple-shooting transcription."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import casadi as ca
import numpy as np


@runtime_checkable
class OdeModel(Protocol):
    """A controlled ODE ẋ = f(x, u) with a running cost g(x, u) ≥ 0.

    Implementations are frozen dataclasses (hashable cache keys, picklable, no CasADi objects).
    """

    @property
    def nx(self) -> int:
        """Dimension of the state x."""
        ...

    @property
    def nu(self) -> int:
        """Dimension of the control u."""
        ...

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """f(x, u), shape (nx, 1)."""
        ...

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """g(x, u), scalar."""
        ...

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (nx,) on every state sample (±inf where unbounded)."""
        ...
