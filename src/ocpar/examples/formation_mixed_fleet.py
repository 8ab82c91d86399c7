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
(:mod:`ocpar.bsp.resident`). With ``dim`` = 3 the same in space: the circle tilted by
:data:`TILT` rad about the x1 axis and lifted to x3 = 0.5, the ball about (0, 5, 0.2), the box
limit on each of the three axes: cost 63.3680 free, with the ball R = 2.5 63.7229 (no limit),
64.0072 (box) and 64.1244 (norm).
"""

import casadi as ca
import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, Sphere
from ocpar.models import PointMass
from ocpar.ocp.constraints import PathConstraint

LIMITS = ("box", "norm")
#: The 3-D case's circle is tilted by this angle about the x1 axis (rad).
TILT = 0.3


def thrust_shape(mass: float, limit: str | None, u_max: float, dim: int = 2) -> DmocShape:
    """One agent's DMOC shape: a point mass of ``mass`` in ``dim`` dimensions with its
    thrust limit."""
    common = {"model": PointMass(dim=dim, mass=mass), "intervals": 20, "duration": 5.0}
    if limit is None:
        return DmocShape(**common)
    if limit == "box":
        return DmocShape(**common, solver="sqpmethod",
                         control_bounds=((-u_max, u_max),) * dim)
    if limit == "norm":
        thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
        return DmocShape(**common, solver="sqpmethod", path_constraints=(thrust,))
    raise ValueError(f"limit: {limit!r} is not one of {LIMITS} or None")


def make(agents: int = 12, limit: str | None = "box", u_max: float = 2.7,
         obstacle: float | None = None, unlimited: int = 0, dim: int = 2) -> FormationProblem:
    """``agents`` point masses of masses 0.5, 1, 1.5 in turn, thrust limit ``limit`` at ``u_max``
    (force unit) but for the last ``unlimited`` of them, and a ball of radius ``obstacle``
    about (0, 5) to keep clear of (None: none), in ``dim`` (2 or 3) dimensions."""
    if not 0 <= unlimited <= agents:
        raise ValueError(f"unlimited: {unlimited} is not between 0 and {agents} agents")
    if dim not in (2, 3):
        raise ValueError(f"dim: must be 2 or 3, got {dim}")
    masses = 0.5 + 0.5 * (np.arange(agents) % 3)
    limits = [limit] * (agents - unlimited) + [None] * unlimited
    starts = np.zeros((agents, dim))
    starts[:, 0] = np.linspace(-3.0, 3.0, agents)
    if dim == 2:
        curve, centre = Circle(radius=4.0, center=np.array([0.0, 6.0])), (0.0, 5.0)
    else:
        axes = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(TILT), np.sin(TILT)]])
        curve = Circle(radius=4.0, center=np.array([0.0, 6.0, 0.5]), axes=axes)
        centre = (0.0, 5.0, 0.2)
    return FormationProblem(
        name="mixed-fleet" if dim == 2 else "mixed-fleet-3d",
        shape=tuple(thrust_shape(float(m), lim, u_max, dim) for m, lim in zip(masses, limits,
                                                                               strict=True)),
        curve=curve,
        starts=starts,
        obstacles=() if obstacle is None else (Sphere(centre, obstacle, "ball"),),
    )
