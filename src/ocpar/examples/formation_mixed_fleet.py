"""A new worked example (in none of the papers): a mixed fleet with thrust limits. ``agents``
planar point masses, of masses 0.5, 1 and 1.5 in turn (mass unit), start at rest on a line
along x1 from −3 to 3 and end at rest on the circle of radius 4 about (0, 6) after T = 5
(N = 20 DMOC intervals), minimising Σ∫|u|² dt, their final angles coupled by the formation
paper's potential. Each agent's thrust is limited, by a box |u_j| ≤ u_max on each axis
(``limit="box"``, DMOC control bounds) or by the norm |u| ≤ u_max (``limit="norm"``, a path
constraint), or not at all (``limit=None``); with the default u_max = 2.7 (force unit) the
limits of the heaviest agents bind at the optimum, which the free optimum breaks (peak
3.23): the total cost rises from 63.0311 to 63.2814 (box) and 63.2996 (norm). With
``obstacle`` = R a ball of radius R about (0, 5), which the optimal paths cross, is kept
clear on the continuous paths by every agent's inner problem (:mod:`ocpar.ocp.obstacles`), and
the formation turns for it: with R = 2.5 the cost is 63.5748 (no limit), 63.9466 (box) and
63.9941 (norm). With ``unlimited`` = m
the last m agents have no thrust limit: a fleet listed by kind, whose solves' cost is skewed
by agent order (a limited agent's solve, by ``sqpmethod``, ~0.24 ms; an unlimited one's, by
the batched Newton kernel, ~0.05 ms), what resident agents' blocks are rebalanced for
(:mod:`ocpar.bsp.resident`).
"""

import casadi as ca
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, Sphere
from ocpar.models import PointMass
from ocpar.ocp.constraints import PathConstraint

LIMITS = ("box", "norm")


def thrust_shape(mass: float, limit: str | None, u_max: float) -> DmocShape:
    """One agent's DMOC shape: a planar point mass of ``mass`` with its thrust limit."""
    common = {"model": PointMass(dim=2, mass=mass), "intervals": 20, "duration": 5.0}
    if limit is None:
        return DmocShape(**common)
    if limit == "box":
        return DmocShape(**common, solver="sqpmethod",
                         control_bounds=((-u_max, u_max), (-u_max, u_max)))
    if limit == "norm":
        thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
        return DmocShape(**common, solver="sqpmethod", path_constraints=(thrust,))
    raise ValueError(f"limit: {limit!r} is not one of {LIMITS} or None")


def make(agents: int = 12, limit: str | None = "box", u_max: float = 2.7,
         obstacle: float | None = None, unlimited: int = 0) -> FormationProblem:
    """``agents`` point masses of masses 0.5, 1, 1.5 in turn, thrust limit ``limit`` at ``u_max``
    (force unit) but for the last ``unlimited`` of them, and a ball of radius ``obstacle``
    about (0, 5) to keep clear of (None: none)."""
    if not 0 <= unlimited <= agents:
        raise ValueError(f"unlimited: {unlimited} is not between 0 and {agents} agents")
    masses = 0.5 + 0.5 * (np.arange(agents) % 3)
    limits = [limit] * (agents - unlimited) + [None] * unlimited
    starts = np.zeros((agents, 2))
    starts[:, 0] = np.linspace(-3.0, 3.0, agents)
    return FormationProblem(
        name="mixed-fleet",
        shape=tuple(thrust_shape(float(m), lim, u_max) for m, lim in zip(masses, limits,
                                                                          strict=True)),
        curve=Circle(radius=4.0, center=np.array([0.0, 6.0])),
        starts=starts,
        obstacles=() if obstacle is None else (Sphere((0.0, 5.0), obstacle, "ball"),),
    )
