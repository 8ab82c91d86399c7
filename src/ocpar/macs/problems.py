"""The bi-objective optimal control problems of the MACS paper (§V), transcribed by DFET.

Both have t_0 = 0, free t_f and Mayer objectives computed from the final state x_f and t_f;
both are minimised.

- ``goddard``: ascent from a flat body without atmosphere to y = 10 with vy = 0;
  J1 = t_f, J2 = −vx(t_f); 4 elements of order 6; u ∈ [−π/2, π/2], t_f ∈ [100, 250]
  (t_f below ~109.1 is infeasible whatever the bound).
- ``orbit-raising``: maximum final specific energy; J1 = t_f,
  J2 = −((vr² + vt²)/2 − 1/r)(t_f); 30 elements of order 1; u ∈ [−π, π], t_f ∈ [20, 80].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ocpar.models import GoddardAscent, OrbitRaising
from ocpar.ocp import DfetShape


@dataclass(frozen=True)
class GoddardProblem:
    """Goddard-like ascent, min (t_f, −vx(t_f))."""

    model: GoddardAscent = field(default_factory=GoddardAscent)
    elements: int = 4
    order: int = 6
    name: str = "goddard"
    #: u ∈ [−π/2, π/2] is a true limit (no backward thrust), not one period of an angle
    periodic_controls: bool = False

    @property
    def shape(self) -> DfetShape:
        return DfetShape(self.model, self.elements, self.order, self.order,
                         ((-math.pi / 2, math.pi / 2),), (100.0, 250.0), (0.0, 0.0, 0.0, 0.0),
                         (2, 3), (self.model.height, 0.0))

    def objectives(self, xf, tf) -> tuple:
        """(J1, J2) from the final state (x, vx, y, vy) and t_f; SX or numbers."""
        return tf, -xf[1]


@dataclass(frozen=True)
class OrbitRaisingProblem:
    """Maximum-energy orbit raising, min (t_f, −E(t_f))."""

    model: OrbitRaising = field(default_factory=OrbitRaising)
    elements: int = 30
    order: int = 1
    name: str = "orbit-raising"
    #: the thrust angle is periodic: its bounds [−π, π] span one period, so a control node on
    #: one bound is the same thrust direction as on the other (see ``local_search``)
    periodic_controls: bool = True

    @property
    def shape(self) -> DfetShape:
        r0 = 1.1
        return DfetShape(self.model, self.elements, self.order, self.order, ((-math.pi, math.pi),),
                         (20.0, 80.0), (r0, 0.0, 0.0, 1 / math.sqrt(r0)), (), ())

    def objectives(self, xf, tf) -> tuple:
        """(J1, J2) from the final state (r, vr, θ, vt) and t_f; SX or numbers."""
        r, vr, vt = xf[0], xf[1], xf[3]
        return tf, -((vr**2 + vt**2) / 2 - 1 / r)


MacsProblem = GoddardProblem | OrbitRaisingProblem
PROBLEMS = {"goddard": GoddardProblem, "orbit-raising": OrbitRaisingProblem}


def make_problem(name: str) -> MacsProblem:
    """The problem called ``name`` (``goddard`` or ``orbit-raising``)."""
    try:
        return PROBLEMS[name]()
    except KeyError:
        raise ValueError(f"unknown problem {name!r}; choose one of {', '.join(PROBLEMS)}") from None
