"""Minimum time against minimum control energy for a double integrator (a MACS example in none
of the papers, with its Pareto front in closed form).

A unit mass moves rest to rest over the distance d, ẍ = u, |u| ≤ u_max: J1 = t_f, J2 = ∫u² dt.
For a fixed t_f the least energy is spent by u = (6d/t_f²)(1 − 2t/t_f), whose peak 6d/t_f² is
inside the bound when t_f ≥ √(6d/u_max); then J2 = 12 d²/t_f³, so the front is J2 = 12 d²/J1³.
"""

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.macs import MacsProblem, Objective


@dataclass(frozen=True)
class DoubleIntegrator:
    """ẋ = v, v̇ = u; state (x, v), control u."""

    nx: int = 2
    nu: int = 1

    def rhs(self, x, u):
        return ca.vertcat(x[1], u[0])

    def state_bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)


def make(distance: float = 1.0, u_max: float = 1.0, t_max: float = 5.0,
         elements: int = 4) -> MacsProblem:
    """The problem on t_f ∈ [1.02 √(6d/u_max), t_max], with its closed-form front;
    ``elements`` DFET elements."""
    t_min = 1.02 * np.sqrt(6 * distance / u_max)
    t_f = np.linspace(t_min, t_max, 1000)
    return MacsProblem(
        name="double-integrator",
        model=DoubleIntegrator(),
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=lambda x, u: u[0] ** 2, name="∫u² dt")),
        initial_state=(0.0, 0.0),
        final_time=(t_min, t_max),
        control_bounds=((-u_max, u_max),),
        final_state={0: distance, 1: 0.0},
        elements=elements, order=3, control_order=1,
        reference_front=np.column_stack([t_f, 12 * distance**2 / t_f**3]),
    )
