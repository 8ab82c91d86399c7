"""The MACS paper's Goddard-like ascent (§V, eq. 16–18) as a :class:`ocpar.macs.MacsProblem`.

From rest at the origin of a flat, airless body to the altitude y = 10 with v_y = 0 at a free
t_f ∈ [100, 250]: min (t_f, −v_x(t_f)). Thrust angle u ∈ [−π/2, π/2] (a true limit, not one
period of an angle); 4 DFET elements of order 6. t_f below ~109.1 is infeasible.
"""

import math

from ocpar.macs import MacsProblem, Objective, reference_front
from ocpar.models import GoddardAscent


def make(elements: int = 4) -> MacsProblem:
    """The paper's problem, with its reference front; ``elements`` DFET elements (the
    paper's 4)."""
    model = GoddardAscent()
    return MacsProblem(
        name="goddard",
        model=model,
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(mayer=lambda xf, tf: -xf[1], name="-v_x(t_f)")),
        initial_state=(0.0, 0.0, 0.0, 0.0),
        final_time=(100.0, 250.0),
        control_bounds=((-math.pi / 2, math.pi / 2),),
        final_state={2: model.height, 3: 0.0},
        elements=elements,
        order=6,
        reference_front=reference_front("goddard"),
    )
