"""Minimum time against minimum control energy for a planar point mass whose thrust is limited
in norm, |u|₂ ≤ a: a MACS example with a nonlinear control constraint (in none of the papers,
with its Pareto front in closed form).

A unit mass moves rest to rest from the origin to a point at distance d along a diagonal,
r̈ = u ∈ R², with J1 = t_f and J2 = ∫|u|² dt. The least-energy control for a fixed t_f = T
points along the move (any other component costs energy and uses thrust) and is the
one-dimensional law saturated at a: with σ² = 3(T²/4 − d/a) (s = t − T/2),

    u(s) = −sat_a(a s/σ),   J2 = a²(T − 4σ/3)   for 2√(d/a) ≤ T ≤ √(6d/a),
    u(s) = −(12 d/T³) s,    J2 = 12 d²/T³        for T ≥ √(6d/a) (the limit is inactive),

2√(d/a) being the bang–bang minimum time. A box |u_j| ≤ a on the components would allow a
thrust of a√2 along the diagonal: the norm limit cannot be written as control bounds, so it is
a :class:`~ocpar.ocp.constraints.PathConstraint` of ``u``.
"""

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ocpar.macs import MacsProblem, Objective
from ocpar.ocp.constraints import PathConstraint


@dataclass(frozen=True)
class PlanarDoubleIntegrator:
    """ṙ = v, v̇ = u in the plane; state (r_x, r_y, v_x, v_y), control (u_x, u_y)."""

    nx: int = 4
    nu: int = 2

    def rhs(self, x, u):
        return ca.vertcat(x[2], x[3], u[0], u[1])

    def state_bounds(self):
        return np.full(4, -np.inf), np.full(4, np.inf)


def front(t_f: np.ndarray, distance: float = 1.0, thrust: float = 1.0) -> np.ndarray:
    """The closed-form Pareto front at final times ``t_f`` (k,) ≥ 2√(d/a): (k, 2) rows
    (t_f, least ∫|u|² dt), the saturated law below √(6d/a) and 12 d²/T³ above."""
    t = np.asarray(t_f, dtype=float)
    sigma = np.sqrt(np.maximum(3 * (t**2 / 4 - distance / thrust), 0.0))
    saturated = thrust**2 * (t - 4 * sigma / 3)
    free = 12 * distance**2 / t**3
    return np.column_stack([t, np.where(t < np.sqrt(6 * distance / thrust), saturated, free)])


def make(distance: float = 1.0, thrust: float = 1.0, heading_deg: float = 36.87,
         t_max: float = 3.0, elements: int = 8) -> MacsProblem:
    """The problem on t_f ∈ [1.05 · 2√(d/a), t_max], moving ``distance`` along
    ``heading_deg`` (default: to (0.8, 0.6) d), with its closed-form front."""
    heading = np.radians(heading_deg)
    target = distance * np.array([np.cos(heading), np.sin(heading)])
    t_min = 1.05 * 2 * np.sqrt(distance / thrust)
    return MacsProblem(
        name="thrust-limited",
        model=PlanarDoubleIntegrator(),
        objectives=(Objective(mayer=lambda xf, tf: tf, name="t_f"),
                    Objective(running=lambda x, u: ca.sumsqr(u), name="∫|u|² dt")),
        initial_state=(0.0, 0.0, 0.0, 0.0),
        final_time=(t_min, t_max),
        control_bounds=((-thrust, thrust), (-thrust, thrust)),
        final_state={0: target[0], 1: target[1], 2: 0.0, 3: 0.0},
        elements=elements, order=3, control_order=1,
        path_constraints=(PathConstraint(lambda u: ca.sumsqr(u), upper=thrust**2,
                                         name="thrust"),),
        reference_front=front(np.linspace(t_min, t_max, 2000), distance, thrust),
    )
