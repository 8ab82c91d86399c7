"""Thrust-limited fleets for tests/test_feasibility.py, given by reference
(``tests.feasibility_problems:fleet``): 12 planar point masses of masses 1 + 0.1 i onto the
circle of radius 4 about (0, 6) from a line (the geometry of
:mod:`ocpar.examples.formation_mixed_fleet`: T = 5, N = 20), with a box or norm thrust limit
at ``fraction`` of the free optimum's peak thrust max_i,k |u_ik| (computed from the free run)."""

from __future__ import annotations

from functools import cache

import casadi as ca
import numpy as np

from ocpar.formation import (
    Circle,
    DmocShape,
    FormationOptions,
    FormationProblem,
    solve_formation,
)
from ocpar.models import PointMass
from ocpar.ocp.constraints import PathConstraint

INTERVALS, DURATION = 20, 5.0


def masses(agents: int) -> np.ndarray:
    return 1.0 + 0.1 * np.arange(agents)


def shape(mass: float, limit: str | None, u_max: float, extra: tuple = ()) -> DmocShape:
    """One agent's shape; ``extra`` path constraints besides a norm limit (with a box limit,
    any path constraint makes the reach set unknown to ocpar: the general fallback)."""
    common = {"model": PointMass(dim=2, mass=mass), "intervals": INTERVALS,
              "duration": DURATION}
    if limit is None:
        return DmocShape(**common)
    if limit == "box":
        return DmocShape(**common, solver="sqpmethod", path_constraints=extra,
                         control_bounds=((-u_max, u_max), (-u_max, u_max)))
    thrust = PathConstraint(lambda u: ca.sumsqr(u), upper=u_max**2, name="thrust")
    return DmocShape(**common, solver="sqpmethod", path_constraints=(thrust,))


def build(agents: int, limit: str | None, u_max: float, extra: tuple = ()) -> FormationProblem:
    starts = np.zeros((agents, 2))
    starts[:, 0] = np.linspace(-3.0, 3.0, agents)
    return FormationProblem(
        name=f"fleet-{limit}", curve=Circle(radius=4.0, center=np.array([0.0, 6.0])),
        shape=tuple(shape(float(m), limit, u_max, extra) for m in masses(agents)),
        starts=starts)


@cache
def free_peak(agents: int = 12) -> float:
    """max_i,k |u_ik| (force unit) of the free optimum (no limit) from its default start."""
    result = solve_formation(build(agents, None, 0.0), options=FormationOptions())
    assert result.status == "converged"
    return float(np.max(np.linalg.norm(result.controls, axis=2)))


def fleet(limit: str = "box", fraction: float = 0.8, agents: int = 12,
          u_max: float | None = None) -> FormationProblem:
    """The fleet with its ``limit`` (box or norm) at ``fraction`` of the free peak thrust, or
    at ``u_max`` (force unit) if given."""
    return build(agents, limit, fraction * free_peak(agents) if u_max is None else u_max)
