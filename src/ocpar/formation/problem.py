"""The formation reconfiguration problem: n agents, fixed starts, ends equidistant on a circle.

Agent i starts at rest (or with a given velocity) at ``starts[i]`` and must end, after
``duration``, on the circle of ``radius`` about ``center`` at angle φ_i, with final velocity
``final_velocity``; the angles are chosen by the outer problem subject to g(φ) = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ocpar.bsp.columns import Columns
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, DmocTask


@dataclass(frozen=True)
class FormationProblem:
    """A planar formation problem.

    Shapes: ``starts`` (n, 2), ``start_velocities`` (n, 2), ``center`` (2,),
    ``final_velocity`` (2,). Units are the model's (the paper's example is nondimensional).
    """

    name: str
    starts: np.ndarray
    center: np.ndarray
    radius: float
    start_velocities: np.ndarray
    final_velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    shape: DmocShape = field(default_factory=lambda: DmocShape(PointMass(dim=2, mass=1.0), 10, 1.0))

    def __post_init__(self) -> None:
        n = len(self.starts)
        if n < 2:
            raise ValueError(f"a formation needs at least 2 agents, got {n}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius must be a positive number, got {self.radius}")
        if np.shape(self.starts) != (n, 2) or np.shape(self.start_velocities) != (n, 2):
            raise ValueError("starts and start_velocities must both have shape (n, 2)")

    @property
    def agents(self) -> int:
        return len(self.starts)

    def final_positions(self, phi: np.ndarray) -> np.ndarray:
        """Points on the circle at angles φ (rad): shape (n, 2)."""
        phi = np.asarray(phi, float)
        return self.center + self.radius * np.column_stack([np.cos(phi), np.sin(phi)])

    def boundary_params(self, i: int, phi_i: float) -> np.ndarray:
        """DMOC boundary data p = (q_0, q̇_0, q_N, q̇_N) of agent i ending at angle φ_i."""
        end = self.center + self.radius * np.array([np.cos(phi_i), np.sin(phi_i)])
        return np.concatenate(
            [self.starts[i], self.start_velocities[i], end, self.final_velocity]
        )

    def tasks(self, phi: np.ndarray) -> Columns:
        """One inner DMOC task per agent for the final angles φ, in columnar form (a
        :class:`~ocpar.bsp.columns.Columns` of :class:`~ocpar.ocp.DmocTask`: the shared shape
        and the (n, 8) boundary data, row i = :meth:`boundary_params` of agent i)."""
        n = self.agents
        params = np.hstack([self.starts, self.start_velocities, self.final_positions(phi),
                            np.broadcast_to(self.final_velocity, (n, 2))])
        return Columns.of(DmocTask, n, shape=self.shape, params=params)

    def initial_phi(self) -> np.ndarray:
        """The documented initial guess for φ (rad).

        The agents are ranked by their position along the circle's counter-clockwise tangent
        at θ_c, the angle of the start centroid seen from the centre, and placed equidistantly
        counter-clockwise in that order, centred on θ_c:
        φ_i = θ_c + 2π (rank_i − (n−1)/2) / n. In the paper's example θ_c = −3π/4 and the
        tangent points along +x, so agents sorted by x go counter-clockwise. This ordering
        decides which local optimum is found (the ordering problem is not solved here).
        """
        n = self.agents
        offset = self.starts.mean(axis=0) - self.center
        theta_c = float(np.arctan2(offset[1], offset[0]))
        tangent = np.array([-np.sin(theta_c), np.cos(theta_c)])
        rank = np.empty(n)
        rank[np.argsort(self.starts @ tangent, kind="stable")] = np.arange(n)
        return theta_c + 2 * np.pi * (rank - (n - 1) / 2) / n


def paper_example(agents: int = 60, radius: float = 10.0) -> FormationProblem:
    """The paper's first example (§VI): ``agents`` unit point masses at rest, uniformly spread
    on the x-axis over [−30, 30], to a circle of ``radius`` centred at (100, 100), at rest,
    t ∈ [0, 1], N = 10 DMOC intervals."""
    if agents < 2:
        raise ValueError(f"a formation needs at least 2 agents, got {agents}")
    starts = np.column_stack([np.linspace(-30.0, 30.0, agents), np.zeros(agents)])
    return FormationProblem(
        name="point-mass-plane",
        starts=starts,
        center=np.array([100.0, 100.0]),
        radius=float(radius),
        start_velocities=np.zeros((agents, 2)),
    )
