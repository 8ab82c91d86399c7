"""Command line: ``python -m ocpar.macs`` (or under ``mpirun -n P``).

A thin layer over :func:`ocpar.macs.solve_macs`; see ``--help``.
"""

from __future__ import annotations

import argparse
import sys

from ocpar.cli import (
    OneLineParser,
    add_backend_arguments,
    choose_backend,
    non_negative_int,
    positive_int,
    prepare_output_dir,
    run_on_backend,
)
from ocpar.macs.algorithm import MacsSettings
from ocpar.macs.plot import plot_controls, plot_front
from ocpar.macs.problems import PROBLEMS, make_problem
from ocpar.macs.solve import solve_macs

PROG = "ocpar.macs"
#: Most agents: each runs one local search per superstep (the paper used 10).
MAX_POPULATION = 10_000


def build_parser() -> OneLineParser:
    """The command line's parser (its options are also the keys of a run configuration,
    :mod:`ocpar.config`)."""
    parser = OneLineParser(
        prog=PROG,
        description="MACSoc: multi-objective optimal control by multi-agent collaborative "
        "search on a DFET transcription; the agents' local searches run in parallel.",
    )
    parser.add_argument("--problem", choices=sorted(PROBLEMS), default="goddard")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--max-evals", type=positive_int, default=10_000,
                        help="budget of objective evaluations, more than --population "
                             "(default 10000)")
    parser.add_argument("--archive", type=positive_int, default=20,
                        help="archive size max_arch (default 20; the paper used 10)")
    parser.add_argument("--population", type=positive_int, default=10,
                        help=f"number of agents pop_size, 4 to {MAX_POPULATION} (default 10)")
    add_backend_arguments(parser)
    parser.add_argument("--output", default=None, metavar="DIR",
                        help="write DIR/result.json, DIR/front.png, DIR/controls.png")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.settings = MacsSettings(max_evaluations=args.max_evals, population=args.population,
                                     archive_size=args.archive, seed=args.seed)
    except ValueError as exc:
        parser.error(str(exc))
    if args.population > MAX_POPULATION:
        parser.error(f"--population must be at most {MAX_POPULATION}, got {args.population}")
    if args.max_evals <= args.population:
        parser.error(f"--max-evals {args.max_evals} leaves no iteration: initialising "
                     f"--population {args.population} agents takes {args.population} "
                     "evaluations")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    choose_backend(args, PROG)
    out = prepare_output_dir(args.output, PROG)
    problem = make_problem(args.problem)

    def solve(backend, say):
        say(f"{PROG}: {problem.name}, seed {args.seed}, {args.max_evals} evaluations, archive "
            f"{args.archive}, backend {backend.name} with {backend.workers} worker(s)")
        return solve_macs(problem, args.settings, backend, progress=say)

    result = run_on_backend(args, PROG, solve)
    if result is None:  # an MPI rank other than 0
        return 0
    print(result.summary(), flush=True)
    if out is not None:
        written = [result.write_json(out)]
        if len(result.front):
            written += [plot_front(result, out / "front.png"),
                        plot_controls(problem, result, out / "controls.png")]
        print("wrote " + ", ".join(str(p) for p in written))
    return 0 if len(result.front) else 1


if __name__ == "__main__":
    sys.exit(main())
