"""The formation examples by name, as the command line offers them: the factories of
:mod:`ocpar.examples`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ocpar.examples import formation_halo, formation_point_masses
from ocpar.formation.problem import FormationProblem


@dataclass(frozen=True)
class Example:
    """A named example: its builder ``build(agents, radius, intervals, duration)`` and the
    defaults of the first two."""

    build: Callable[[int, float, int, float], FormationProblem]
    agents: int
    radius: float
    description: str


#: The DMOC intervals N and the duration T of every built-in example unless told otherwise
#: (``--intervals``, ``--duration``).
INTERVALS, DURATION = 10, 1.0

EXAMPLES = {
    "point-mass-plane": Example(
        lambda n, r, k, t: formation_point_masses.make(agents=n, radius=r, intervals=k,
                                                       duration=t), 60, 10.0,
        "the paper's planar point masses"),
    "crtbp-rigid": Example(
        lambda n, r, k, t: formation_halo.make(agents=n, radius_km=r, intervals=k,
                                               duration=t), 30, 1.0,
        "rigid spacecraft about the Sun-Earth L2 halo, radius in km"),
}


def make_example(name: str, agents: int | None = None, radius: float | None = None,
                 intervals: int = INTERVALS, duration: float = DURATION) -> FormationProblem:
    """The example ``name`` (see :data:`EXAMPLES`) with ``agents`` agents and circle
    ``radius`` (its defaults where None), DMOC with ``intervals`` intervals over
    [0, ``duration``] (the model's time unit)."""
    if name not in EXAMPLES:
        raise ValueError(f"unknown problem {name!r}; choose one of {', '.join(EXAMPLES)}")
    example = EXAMPLES[name]
    return example.build(example.agents if agents is None else agents,
                         example.radius if radius is None else radius, intervals, duration)
