"""The orbit transfer problem of the local-pursuit paper (§VI), its two cases and the initial
feasible trajectory that agent 0 follows.

Units: Mm, t, min (see :mod:`ocpar.models.orbit_transfer`). The spacecraft starts on the
circular orbit r = 9.6 Mm with μ = 0.525 t and must reach, at T = 300 min, the circular orbit
r = R_T (ṙ = 0, θ̇ = √(u_E/R_T³), longitude free) with the least fuel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from ocpar.models import OrbitTransfer

#: Target radius (Mm) per case: case 1 the well-conditioned transfer (guess eq. 16), case 2
#: the ill-conditioned one (guess eq. 20).
CASE_RADIUS = {1: 12.7778, 2: 23.642}
#: Components fixed on the target set S_Q: r, ṙ, θ̇ (the mass is what is optimised).
TARGET_COMPONENTS = (0, 1, 2)


@dataclass(frozen=True)
class OrbitTransferProblem:
    """One orbit transfer: ``case`` (1 or 2) sampled at ``samples`` points N over [0, T]
    (h = T/(N−1) min)."""

    case: int = 1
    samples: int = 301
    duration: float = 300.0
    initial_radius: float = 9.6
    initial_mass: float = 0.525
    model: OrbitTransfer = field(default_factory=OrbitTransfer)

    def __post_init__(self) -> None:
        if self.case not in CASE_RADIUS:
            raise ValueError(f"unknown case {self.case}; choose one of {sorted(CASE_RADIUS)}")
        if self.samples < 3:
            raise ValueError(f"need at least 3 samples, got {self.samples}")

    @property
    def name(self) -> str:
        return f"orbit-transfer-case{self.case}"

    @property
    def step(self) -> float:
        """h = T/(N−1), min."""
        return self.duration / (self.samples - 1)

    @property
    def target_radius(self) -> float:
        return CASE_RADIUS[self.case]

    @property
    def initial_state(self) -> np.ndarray:
        """x_I = (r0, 0, √(u_E/r0³), μ0)."""
        r0 = self.initial_radius
        return np.array([r0, 0.0, self.model.circular_rate(r0), self.initial_mass])

    @property
    def target(self) -> np.ndarray:
        """Values of (r, ṙ, θ̇) on the target set S_Q."""
        rt = self.target_radius
        return np.array([rt, 0.0, self.model.circular_rate(rt)])

    def guess_controls(self, t: np.ndarray) -> np.ndarray:
        """The paper's suboptimal controls u = I (sin φ, cos φ) at times t (min): eq. 16 for
        case 1, eq. 20 for case 2. Shape (len(t), 2)."""
        t = np.asarray(t, float)
        half, tt = t < self.duration / 2, self.duration
        if self.case == 1:
            thrust = np.where(half, 60 * (1.5 + np.sin(6 * np.pi * t / tt)) * 1e-4, 75e-4)
            angle = np.where(half, (1 + np.sin(2 * np.pi * t / tt)) * np.pi, 0.4417 * np.pi)
        else:
            thrust = np.where(half, 90 * (1.5 + np.sin(6 * np.pi * t / tt)) * 1e-4, 75e-4)
            angle = np.where(half, np.pi / 2, 0.4417 * np.pi)
        return np.column_stack([thrust * np.sin(angle), thrust * np.cos(angle)])

    def feasible_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Agent 0: the guess controls integrated accurately (RK45, rtol 1e-11), states
        sampled on the grid (N, 4), and the controls sampled at the grid points (N−1, 2).
        Explicit Euler with h = 1 min would land far from the paper's r(T)."""
        grid = np.arange(self.samples) * self.step
        sol = solve_ivp(
            lambda t, x: self.model.rhs_numpy(x, self.guess_controls(np.array([t]))[0]),
            (0.0, self.duration), self.initial_state, t_eval=grid, rtol=1e-11, atol=1e-13,
            max_step=self.duration / 600,
        )
        return sol.y.T.copy(), self.guess_controls(grid[:-1])
