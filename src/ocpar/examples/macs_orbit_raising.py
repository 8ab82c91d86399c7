"""The MACS paper's maximum-energy orbit raising (§V, eq. 19–21) as a
:class:`ocpar.macs.MacsProblem`.

From the circular orbit r = 1.1 (canonical units): min (t_f, −E(t_f)) with the specific energy
E = (v_r² + v_t²)/2 − 1/r, t_f ∈ [20, 80] free. The thrust angle u ∈ [−π, π] is periodic: a
node on one bound is the same direction as on the other. 30 DFET elements of order 1.
"""

import math

from ocpar.macs import MacsProblem, Objective, reference_front
from ocpar.models import OrbitRaising


def final_energy(xf, tf):
    """−E(t_f) of the final state (r, v_r, θ, v_t)."""
    r, vr, vt = xf[0], xf[1], xf[3]
    return -((vr**2 + vt**2) / 2 - 1 / r)


def make(elements: int = 30) -> MacsProblem:
    """The paper's problem, with its reference front; ``elements`` DFET elements (the
    paper's 30)."""
    model = OrbitRaising()
    r0 = 1.1
    return MacsProblem(
        name="orbit-raising",
        model=model,
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(mayer=final_energy, name="-E(t_f)")),
        initial_state=(r0, 0.0, 0.0, 1 / math.sqrt(r0)),  # circular orbit
        final_time=(20.0, 80.0),
        control_bounds=((-math.pi, math.pi),),
        periodic_controls=True,
        elements=elements,
        order=1,
        reference_front=reference_front("orbit-raising"),
    )
