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
#: Most agents a run may ask for (the paper's examples have 60 and 30).
MAX_AGENTS = 100_000
#: Most agents for ``--ordering optimal``, which fills n × n tables of inner solves.
MAX_OPTIMAL_ORDERING_AGENTS = 1_000
#: ``--radius`` must lie within this factor of the problem's default radius (its length scale).
RADIUS_RANGE = 1e6


def build_parser() -> OneLineParser:
    """The command line's parser (its options are also the keys of a run configuration,
    :mod:`ocpar.config`)."""
    parser = OneLineParser(
        prog=PROG,
        description="Hierarchical formation reconfiguration (the paper's 60 point masses by "
        "default): outer SQP over the final angles, inner DMOC solves in parallel supersteps.",
    )
    parser.add_argument("--problem", choices=list(EXAMPLES), default="point-mass-plane",
                        help="; ".join(f"{name}: {e.description} (default {e.agents} agents, "
                                       f"radius {e.radius:g})" for name, e in EXAMPLES.items()))
    parser.add_argument("--agents", type=positive_int, default=None,
                        help=f"number of agents (2 to {MAX_AGENTS}; default: the problem's)")
    parser.add_argument("--radius", type=positive_float, default=None,
                        help="radius of the final circle, within a factor "
                             f"{RADIUS_RANGE:g} of the problem's default (default: the problem's)")
    parser.add_argument("--mode", choices=MODES, default="hierarchical",
                        help="hierarchical (default) or monolithic (one NLP, for reference)")
    parser.add_argument("--outer", choices=OUTER_SOLVERS, default=None,
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
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    example = EXAMPLES[args.problem]
    agents = example.agents if args.agents is None else args.agents
    if not 2 <= agents <= MAX_AGENTS:
        parser.error(f"--agents must be between 2 and {MAX_AGENTS}, got {agents}")
    if args.ordering == "optimal" and agents > MAX_OPTIMAL_ORDERING_AGENTS:
        parser.error(f"--ordering optimal solves n^2 inner problems per table: at most "
                     f"{MAX_OPTIMAL_ORDERING_AGENTS} agents, got {agents}")
    low, high = example.radius / RADIUS_RANGE, example.radius * RADIUS_RANGE
    if args.radius is not None and not low <= args.radius <= high:
        parser.error(f"--radius for {args.problem} must be between {low:g} and {high:g}, "
                     f"got {args.radius:g}")
    if args.outer is not None and args.mode != "hierarchical":
        parser.error(f"--outer only applies to --mode hierarchical, not {args.mode}")
    args.outer = args.outer or "sqp"
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
