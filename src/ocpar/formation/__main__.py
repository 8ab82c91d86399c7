"""Command line: ``python -m ocpar.formation`` (or ``mpirun -n P python -m ocpar.formation``).

A thin layer over :func:`ocpar.formation.solve_formation`; see ``--help``.
"""

from __future__ import annotations

import argparse
import sys

from ocpar.cli import (
    OneLineParser,
    add_backend_arguments,
    choose_backend,
    positive_float,
    positive_int,
    prepare_output_dir,
    run_on_backend,
)
from ocpar.formation.examples import EXAMPLES, make_example
from ocpar.formation.plot import plot_formation
from ocpar.formation.solve import (
    MODES,
    ORDERINGS,
    OUTER_SOLVERS,
    FormationOptions,
    solve_formation,
)

PROG = "ocpar.formation"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = OneLineParser(
        prog=PROG,
        description="Hierarchical formation reconfiguration (the paper's 60 point masses by "
        "default): outer SQP over the final angles, inner DMOC solves in parallel supersteps.",
    )
    parser.add_argument("--problem", choices=list(EXAMPLES), default="point-mass-plane",
                        help="; ".join(f"{name}: {e.description} (default {e.agents} agents, "
                                       f"radius {e.radius:g})" for name, e in EXAMPLES.items()))
    parser.add_argument("--agents", type=positive_int, default=None,
                        help="number of agents (>= 2; default: the problem's)")
    parser.add_argument("--radius", type=positive_float, default=None,
                        help="radius of the final circle (default: the problem's)")
    parser.add_argument("--mode", choices=MODES, default="hierarchical",
                        help="hierarchical (default) or monolithic (one NLP, for reference)")
    parser.add_argument("--outer", choices=OUTER_SOLVERS, default="sqp",
                        help="hierarchical outer solver: sqp (SLSQP in all angles, default) or "
                             "offset (the common offset of equidistant angles: same optimum, "
                             "far fewer supersteps for many agents)")
    parser.add_argument("--ordering", choices=ORDERINGS, default="keep",
                        help="which agent goes to which place on the circle: keep (the initial "
                             "guess's order, the paper's) or optimal (assignment over a table "
                             "of n^2 inner costs, alternated with the common offset)")
    add_backend_arguments(parser)
    parser.add_argument("--output", default=None, metavar="DIR",
                        help="write DIR/result.json and DIR/formation.png")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    args = parser.parse_args(argv)
    if args.agents is not None and args.agents < 2:
        parser.error(f"--agents must be at least 2, got {args.agents}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    choose_backend(args, PROG)
    out = prepare_output_dir(args.output, PROG)
    problem = make_example(args.problem, args.agents, args.radius)
    options = FormationOptions(mode=args.mode, outer=args.outer, ordering=args.ordering)

    def solve(backend, say):
        say(f"{PROG}: {problem.name}, {problem.agents} agents, mode {args.mode}, ordering "
            f"{args.ordering}, backend {backend.name} with {backend.workers} worker(s)")
        return solve_formation(problem, backend, options, progress=say)

    result = run_on_backend(args, PROG, solve)
    if result is None:  # an MPI rank other than 0
        return 0
    print(result.summary(), flush=True)
    if out is not None:
        json_path = result.write_json(out)
        png_path = plot_formation(problem, result, out / "formation.png")
        print(f"wrote {json_path} and {png_path}")
    return 0 if result.converged else 1

if __name__ == "__main__":
    sys.exit(main())
