"""The formation examples by name, as the command line offers them: the factories of
:mod:`ocpar.examples`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ocpar.examples import (
    formation_cw,
    formation_halo,
    formation_minimum_time,
    formation_point_masses,
    formation_unicycles,
)
from ocpar.formation.problem import FormationProblem


@dataclass(frozen=True)
class Example:
    """A named example: its builder ``build(agents, radius, **grid)`` (``grid``: the
    ``intervals`` N and ``duration`` T given, each the example's own where absent) and the
    defaults of the first two."""

    build: Callable[..., FormationProblem]
    agents: int
    radius: float
    description: str


EXAMPLES = {
    "point-mass-plane": Example(
        lambda n, r, **grid: formation_point_masses.make(agents=n, radius=r, **grid), 60, 10.0,
        "the paper's planar point masses (N = 10 over T = 1)"),
    "crtbp-rigid": Example(
        lambda n, r, **grid: formation_halo.make(agents=n, radius_km=r, **grid), 30, 1.0,
        "rigid spacecraft about the Sun-Earth L2 halo, radius in km (N = 10 over T = 1)"),
    "unicycles": Example(
        lambda n, r, **grid: formation_unicycles.make(agents=n, radius=r, **grid), 6, 3.0,
        "ground robots with unicycle kinematics (multiple shooting) from a line onto a "
        "circle, stopping there (N = 20 over T = 6 s)"),
    "cw-ring": Example(
        lambda n, r, **grid: formation_cw.make(agents=n, radius=r, **grid), 6, 100.0,
        "Clohessy-Wiltshire spacecraft in low Earth orbit from the V-bar onto a ring of hold "
        "points about the target in half an orbit, radius in m (N = 20 over T = 46.3 min)"),
    "point-mass-minimum-time": Example(
        lambda n, r, **grid: formation_minimum_time.make(agents=n, radius=r, **grid), 10, 5.0,
        "point masses under a thrust limit |u| <= 2, for --final-time minimum (N = 10)"),
}


def make_example(name: str, agents: int | None = None, radius: float | None = None,
                 intervals: int | None = None, duration: float | None = None
                 ) -> FormationProblem:
    """The example ``name`` (see :data:`EXAMPLES`) with ``agents`` agents and circle
    ``radius``, its inner problems with ``intervals`` intervals over [0, ``duration``] (the
    model's time unit); the example's own where None."""
    if name not in EXAMPLES:
        raise ValueError(f"unknown problem {name!r}; choose one of {', '.join(EXAMPLES)}")
    example = EXAMPLES[name]
    grid = {key: value for key, value in (("intervals", intervals), ("duration", duration))
            if value is not None}
    return example.build(example.agents if agents is None else agents,
                         example.radius if radius is None else radius, **grid)
