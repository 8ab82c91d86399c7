"""ODE agents against DMOC point masses on the batched path: a formation of n unicycles
(:class:`~ocpar.models.Unicycle`, RK4 multiple shooting) and one of n unit point masses
(DMOC), from the same starts (spread on the line y = -30 over [-27, 33], at rest; the
unicycles facing +y) onto the same circle (radius 10 about the origin), N = 10 intervals over
T = 10, serially; each one's solve time per agent per inner iteration (the
solve's wall time over its inner solves). Usage::

    python scripts/ode_agents_speed.py [--agents 10000] [--repeats 3]
"""

from __future__ import annotations

import argparse

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem, MsEndpointShape, solve_formation
from ocpar.models import PointMass, Unicycle


def problems(agents: int) -> dict[str, FormationProblem]:
    """The two formations (module docstring)."""
    circle = Circle(radius=10.0)
    line = np.column_stack([np.linspace(-27.0, 33.0, agents), np.full(agents, -30.0)])
    facing = np.full(agents, np.pi / 2)
    return {
        "point masses (DMOC)": FormationProblem(
            "masses", DmocShape(PointMass(dim=2), intervals=10, duration=10.0), circle, line),
        "unicycles (RK4 shooting)": FormationProblem(
            "unicycles", MsEndpointShape(Unicycle(), intervals=10, duration=10.0,
                                         free_end=(2,)), circle,
            np.column_stack([line, facing, np.zeros(agents)]),
            final_state=np.array([np.nan, 0.0])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    times = {}
    for name, problem in problems(args.agents).items():
        best = np.inf
        for _ in range(args.repeats):
            result = solve_formation(problem)
            assert result.status == "converged", result.message
            best = min(best, result.wall_time_s / result.inner_solves)
        times[name] = best
        print(f"{name:26s} {result.agents} agents, {result.outer_iterations} outer "
              f"iterations, {result.inner_solves} inner solves ({result.retries} retried): "
              f"{best * 1e6:.2f} µs per agent per inner iteration (best of {args.repeats})")
    ratio = times["unicycles (RK4 shooting)"] / times["point masses (DMOC)"]
    print(f"unicycles / point masses: {ratio:.2f}x")


if __name__ == "__main__":
    main()
