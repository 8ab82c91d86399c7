"""The local-pursuit paper's orbit transfer (§VI), cases 1 and 2, as a :class:`PursuitProblem`.

Units: Mm, t, min (:class:`ocpar.models.OrbitTransfer`). The spacecraft starts on the circular
orbit r = 9.6 Mm with μ = 0.525 t and must reach, at T = 300 min, the circular orbit r = R_T
(ṙ = 0, θ̇ = √(u_E/R_T³); longitude and mass free) burning the least fuel. Agent 0 flies the
paper's suboptimal controls, integrated accurately (explicit Euler with h = 1 min would land far
from the paper's r(T)).

>>> from ocpar.examples.pursuit_orbit_transfer import make
>>> make(case=2, samples=101).target_components
(0, 1, 2)
"""

from __future__ import annotations

from functools import partial

import numpy as np

from ocpar.models import OrbitTransfer
from ocpar.models.orbit_transfer import KG_PER_T, M_PER_MM
from ocpar.pursuit import ControlLaw, FinalValue, PursuitProblem

#: Target radius (Mm) per case: case 1 the well-conditioned transfer (guess eq. 16), case 2
#: the ill-conditioned one (guess eq. 20).
CASE_RADIUS = {1: 12.7778, 2: 23.642}
#: Components fixed on the target set S_Q: r, ṙ, θ̇ (the mass is what is optimised).
TARGET_COMPONENTS = (0, 1, 2)
DURATION_MIN = 300.0
INITIAL_RADIUS_MM = 9.6
INITIAL_MASS_T = 0.525


def guess_controls(case: int, t: float) -> np.ndarray:
    """The paper's suboptimal controls u = I (sin φ, cos φ) at time t (min): eq. 16 for
    case 1, eq. 20 for case 2. Shape (2,)."""
    half, tt = t < DURATION_MIN / 2, DURATION_MIN
    if case == 1:
        thrust = np.where(half, 60 * (1.5 + np.sin(6 * np.pi * t / tt)) * 1e-4, 75e-4)
        angle = np.where(half, (1 + np.sin(2 * np.pi * t / tt)) * np.pi, 0.4417 * np.pi)
    else:
        thrust = np.where(half, 90 * (1.5 + np.sin(6 * np.pi * t / tt)) * 1e-4, 75e-4)
        angle = np.where(half, np.pi / 2, 0.4417 * np.pi)
    return np.array([thrust * np.sin(angle), thrust * np.cos(angle)])


def make(case: int = 1, samples: int = 301) -> PursuitProblem:
    """Case ``case`` (1 or 2) sampled at ``samples`` points N over [0, T] (h = T/(N−1) min)."""
    if case not in CASE_RADIUS:
        raise ValueError(f"unknown case {case}; choose one of {sorted(CASE_RADIUS)}")
    model, r0, rt = OrbitTransfer(), INITIAL_RADIUS_MM, CASE_RADIUS[case]
    return PursuitProblem(
        name=f"orbit-transfer-case{case}", model=model, duration=DURATION_MIN, samples=samples,
        initial_state=np.array([r0, 0.0, model.circular_rate(r0), INITIAL_MASS_T]),
        target_components=TARGET_COMPONENTS,
        target=np.array([rt, 0.0, model.circular_rate(rt)]),
        plan=ControlLaw(partial(guess_controls, case)),
        headline=FinalValue("final mass", "kg", lambda x: x[3] * KG_PER_T,
                            larger_is_better=True),
        cost_name="fuel", cost_unit="kg",  # the running cost is the burn rate in kg/min
        checks=(FinalValue("final altitude error", "m", lambda x: (x[0] - rt) * M_PER_MM),
                FinalValue("final radial velocity", "mps", lambda x: x[1] * M_PER_MM / 60)),
    )

