"""The formation reconfiguration problem: n agents, fixed starts, ends equidistant on a circle.

Agent i starts in configuration ``starts[i]`` with velocity ``start_velocities[i]`` and must
end, after the DMOC shape's ``duration``, with its position (the first d = len(``center``)
entries of its configuration) on the circle of ``radius`` about ``center`` at angle φ_i, the
rest of its configuration equal to ``final_attitude`` and velocity ``final_velocity``. The
circle lies in the plane spanned by the orthonormal rows of ``axes`` (2, d): the point at
angle φ is center + r (cos φ axes[0] + sin φ axes[1]). The angles are chosen by the outer
problem subject to g(φ) = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ocpar.bsp.columns import Columns
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, OcpTask


@dataclass(frozen=True)
class FormationProblem:
    """A formation problem (the paper's planar point masses, or rigid spacecraft in 3-D).

    Shapes, with nq the model's configuration size and d = len(``center``) ≤ nq:
    ``starts``, ``start_velocities`` (n, nq); ``center`` (d,); ``axes`` (2, d) orthonormal
    rows (default: the x1–x2 plane); ``final_attitude`` (nq − d,) the configuration entries
    after the position (none for point masses); ``final_velocity`` (nq,). Units are the
    model's (the paper's first example is nondimensional).
    """

    name: str
    starts: np.ndarray
    center: np.ndarray
    radius: float
    start_velocities: np.ndarray
    final_velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    shape: DmocShape = field(default_factory=lambda: DmocShape(PointMass(dim=2, mass=1.0), 10, 1.0))
    axes: np.ndarray | None = None
    final_attitude: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        n, nq, d = len(self.starts), self.shape.model.nq, len(self.center)
        if n < 2:
            raise ValueError(f"a formation needs at least 2 agents, got {n}")
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"radius must be a positive number, got {self.radius}")
        if np.shape(self.starts) != (n, nq) or np.shape(self.start_velocities) != (n, nq):
            raise ValueError(f"starts and start_velocities must both have shape (n, {nq})")
        if d < 2 or np.shape(self.final_attitude) != (nq - d,):
            raise ValueError(f"center needs 2..{nq} entries and final_attitude {nq} - "
                             "len(center)")
        if np.shape(self.final_velocity) != (nq,):
            raise ValueError(f"final_velocity must have shape ({nq},)")
        if not np.allclose(self.plane_axes @ self.plane_axes.T, np.eye(2), atol=1e-12):
            raise ValueError(f"axes must be two orthonormal rows of length {d}")

    @property
    def agents(self) -> int:
        return len(self.starts)

    @property
    def plane_axes(self) -> np.ndarray:
        """The circle's plane: two orthonormal rows (2, d)."""
        if self.axes is None:
            return np.eye(2, len(self.center))
        return np.asarray(self.axes, float)

    def final_positions(self, phi: np.ndarray) -> np.ndarray:
        """Points on the circle at angles φ (rad): shape (n, d)."""
        phi = np.asarray(phi, float)
        return self.center + self.radius * np.column_stack([np.cos(phi), np.sin(phi)]) \
            @ self.plane_axes

    def final_position_derivatives(self, phi: np.ndarray) -> np.ndarray:
        """d(final configuration q_N)/dφ_i for each agent: shape (n, nq) (zero beyond the
        position entries)."""
        phi = np.asarray(phi, float)
        along = self.radius * np.column_stack([-np.sin(phi), np.cos(phi)]) @ self.plane_axes
        return np.hstack([along, np.zeros((len(phi), len(self.final_attitude)))])

    def boundary_params(self, i: int, phi_i: float) -> np.ndarray:
        """DMOC boundary data p = (q_0, q̇_0, q_N, q̇_N) of agent i ending at angle φ_i."""
        return np.concatenate([self.starts[i], self.start_velocities[i],
                               self.final_positions(np.array([phi_i]))[0],
                               self.final_attitude, self.final_velocity])

    def tasks_for(self, agents: np.ndarray, phi: np.ndarray,
                  warm_starts: np.ndarray | None = None) -> Columns:
        """Task k: agent ``agents[k]`` ending at angle ``phi[k]`` (rad), in columnar form (a
        :class:`~ocpar.bsp.columns.Columns` of :class:`~ocpar.ocp.OcpTask`: the shared
        shape, the (len(agents), 4 nq) boundary data, row k =
        :meth:`boundary_params` (agents[k], phi[k]), and optional warm starts, one row per
        task, to retry from if a first attempt fails)."""
        agents = np.asarray(agents, dtype=np.intp)
        m = len(agents)
        params = np.hstack([self.starts[agents], self.start_velocities[agents],
                            self.final_positions(phi),
                            np.broadcast_to(self.final_attitude, (m, len(self.final_attitude))),
                            np.broadcast_to(self.final_velocity, (m, len(self.final_velocity)))])
        return Columns.of(OcpTask, m, shape=self.shape, params=params, warm_start=None,
                          multipliers=None, fallback=warm_starts)

    def tasks(self, phi: np.ndarray, warm_starts: np.ndarray | None = None) -> Columns:
        """One inner DMOC task per agent, agent i ending at φ_i (see :meth:`tasks_for`)."""
        return self.tasks_for(np.arange(self.agents), phi, warm_starts)

    def initial_phi(self) -> np.ndarray:
        """The documented initial guess for φ (rad).

        With the start positions projected into the circle's plane (coordinates along
        ``axes``, relative to the centre), the agents are ranked by their position along the
        circle's counter-clockwise tangent at θ_c, the angle of the start centroid seen from
        the centre, and placed equidistantly counter-clockwise in that order, centred on θ_c:
        φ_i = θ_c + 2π (rank_i − (n−1)/2) / n. In the paper's example θ_c = −3π/4 and the
        tangent points along +x, so agents sorted by x go counter-clockwise. This ordering
        decides which local optimum is found (the ordering problem is not solved here).
        """
        n = self.agents
        in_plane = (self.starts[:, : len(self.center)] - self.center) @ self.plane_axes.T
        offset = in_plane.mean(axis=0)
        theta_c = float(np.arctan2(offset[1], offset[0]))
        tangent = np.array([-np.sin(theta_c), np.cos(theta_c)])
        rank = np.empty(n)
        rank[np.argsort(in_plane @ tangent, kind="stable")] = np.arange(n)
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
