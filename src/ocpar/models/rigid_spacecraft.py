"""A rigid spacecraft near a reference orbit: linearised relative translation, quaternion attitude.

Configuration q = (δx, p) ∈ R⁷: δx ∈ R³ the deviation from the reference orbit in a formation
length unit (e.g. 1 km: the dynamics are linear in δx, so its unit is free), p ∈ R⁴ the unit
quaternion (scalar first) of the attitude. Control u = (F, τ) ∈ R⁶: force per unit mass
(length unit / time unit²) and body torque (inertia = identity, rad / time unit²).

Lagrangian on DMOC interval k (the paper's Remark 2: the three-body problem linearised about the
halo, in the rotating frame of angular rate 1):

    L = ½|δẋ|² + δxᵀ S δẋ + ½ δxᵀ K_k δx + 2|ṗ|²,   S = [[0, 1, 0], [−1, 0, 0], [0, 0, 0]],

K_k the Hessian of the effective potential at the reference point at the interval's midpoint
time, and 2|ṗ|² = ½|Ω|² for a unit quaternion. The constraint |p|² − 1 = 0 has a multiplier
at every node. The force enters as F, the torque as the generalised force 2 p ⊗ (0, τ).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca
import numpy as np

#: The Coriolis coupling of the rotating frame, δxᵀ S δẋ = δx₁δẋ₂ − δx₂δẋ₁.
CORIOLIS = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def quaternion_product(a: ca.SX | np.ndarray, b: ca.SX | np.ndarray) -> ca.SX | np.ndarray:
    """Hamilton product a ⊗ b of quaternions (scalar first), CasADi or numpy (4,)."""
    a0, a1, a2, a3 = (a[i] for i in range(4))
    b0, b1, b2, b3 = (b[i] for i in range(4))
    parts = (a0 * b0 - a1 * b1 - a2 * b2 - a3 * b3,
             a0 * b1 + a1 * b0 + a2 * b3 - a3 * b2,
             a0 * b2 - a1 * b3 + a2 * b0 + a3 * b1,
             a0 * b3 + a1 * b2 - a2 * b1 + a3 * b0)
    return ca.vertcat(*parts) if isinstance(a, ca.SX) or isinstance(b, ca.SX) else np.array(parts)


@dataclass(frozen=True)
class RelativeRigidSpacecraft:
    """The model above with K_k tabulated per DMOC interval.

    ``hessians``: one tuple of 9 floats (K row by row, 1/time unit²) per interval, in time
    order; their number is the DMOC interval count N (checked by ``DmocShape``).
    """

    hessians: tuple[tuple[float, ...], ...]

    time_dependent: ClassVar[bool] = True
    n_constraints: ClassVar[int] = 1
    #: δx is the position; the quaternion is not.
    position_indices: ClassVar[tuple[int, ...]] = (0, 1, 2)
    #: The cost's parts by control entries: |F|² (translation) and |τ|² (rotation).
    cost_parts: ClassVar[dict[str, tuple[int, int]]] = {
        "translational_cost": (0, 3), "rotational_cost": (3, 6)}
    #: Names of the entries (:mod:`ocpar.models.labels`; normalised units): the position
    #: δx, the quaternion p, the force per unit mass F and the torque τ.
    state_names: ClassVar[tuple[str, ...]] = ("x", "y", "z", "p0", "p1", "p2", "p3")
    control_names: ClassVar[tuple[str, ...]] = ("F_x", "F_y", "F_z", "tau_x", "tau_y", "tau_z")

    def __post_init__(self) -> None:
        if not self.hessians or any(len(k) != 9 for k in self.hessians):
            raise ValueError("hessians must be one 3x3 matrix (9 floats) per interval")
        if not np.all(np.isfinite(np.asarray(self.hessians))):
            raise ValueError("hessians must be finite")

    @classmethod
    def from_matrices(cls, hessians: np.ndarray) -> RelativeRigidSpacecraft:
        """From an array (N, 3, 3) of K at the N interval midpoints."""
        array = np.asarray(hessians, float)
        if array.ndim != 3 or array.shape[1:] != (3, 3):
            raise ValueError(f"hessians must have shape (N, 3, 3), got {array.shape}")
        return cls(tuple(tuple(float(x) for x in k.ravel()) for k in array))

    @property
    def intervals(self) -> int:
        return len(self.hessians)

    @property
    def nq(self) -> int:
        return 7

    @property
    def nu(self) -> int:
        return 6

    def lagrangian(self, q: ca.SX, qdot: ca.SX, interval: int = 0) -> ca.SX:
        dx, dv, pdot = q[:3], qdot[:3], qdot[3:]
        k = ca.DM(np.reshape(self.hessians[interval], (3, 3)))
        return (0.5 * ca.dot(dv, dv) + ca.dot(dx, ca.DM(CORIOLIS) @ dv)
                + 0.5 * ca.dot(dx, k @ dx) + 2.0 * ca.dot(pdot, pdot))

    def generalized_force(self, q: ca.SX, u: ca.SX) -> ca.SX:
        torque = ca.vertcat(0, u[3:])
        return ca.vertcat(u[:3], 2.0 * quaternion_product(q[3:], torque))

    def constraints(self, q: ca.SX) -> ca.SX:
        return ca.dot(q[3:], q[3:]) - 1.0

    def project(self, q: np.ndarray) -> np.ndarray:
        """Rows (m, 7) with their quaternion part normalised (a zero quaternion stays)."""
        out = np.array(q, float)
        norms = np.linalg.norm(out[:, 3:], axis=1, keepdims=True)
        np.divide(out[:, 3:], norms, out=out[:, 3:], where=norms > 0)
        return out
