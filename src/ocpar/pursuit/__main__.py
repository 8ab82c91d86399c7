"""Command line: ``python -m ocpar.pursuit`` (or under ``mpirun -n P``).

A thin layer over :func:`ocpar.pursuit.solve_pursuit`; see ``--help``.
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
from ocpar.models.orbit_transfer import KG_PER_T
from ocpar.pursuit.plot import plot_convergence, plot_trajectories
from ocpar.pursuit.problem import CASE_RADIUS, OrbitTransferProblem
from ocpar.pursuit.slp import PursuitSettings
from ocpar.pursuit.solve import MODES, solve_pursuit

PROG = "ocpar.pursuit"
#: Largest N: PBMS keeps about N/N_Δ agents of N samples each in flight (the README's largest
#: runs have N = 2001).
MAX_SAMPLES = 100_001


def build_parser() -> OneLineParser:
    """The command line's parser (its options are also the keys of a run configuration,
    :mod:`ocpar.config`)."""
    parser = OneLineParser(
        prog=PROG,
        description="Pursuit-based multiple shooting (PBMS) on the paper's orbit transfer: a "
        "train of agents, each intercepting its predecessor; agents in flight solve in parallel.",
    )
    parser.add_argument("--case", type=int, choices=sorted(CASE_RADIUS), default=1,
                        help="1: R_T = 12.7778 Mm (guess eq. 16); 2: R_T = 23.642 Mm (eq. 20)")
    parser.add_argument("--samples", type=positive_int, default=301, metavar="N",
                        help=f"samples N over T = 300 min (h = T/(N-1)), at most {MAX_SAMPLES}, "
                             "default 301")
    parser.add_argument("--window", type=positive_int, default=60, metavar="N_DELTA",
                        help="samples per catch-up problem N_Δ (Δ = (N_Δ-1)h), default 60")
    parser.add_argument("--update", type=positive_int, default=32, metavar="N_UPDATE",
                        help="samples applied per update N_δ (δ = N_δ h), default 32")
    parser.add_argument("--mode", choices=MODES, default="pbms",
                        help="pbms (default) or ms (one NLP over the whole horizon)")
    parser.add_argument("--epsilon", type=positive_float, default=1e-5, metavar="KG",
                        help="stop when an agent improves on its leader by less (kg, below "
                             "the spacecraft's initial mass), default 1e-5")
    parser.add_argument("--max-agents", type=positive_int, default=100_000,
                        help="stop after this many agents (default 100000)")
    parser.add_argument("--no-reference", action="store_true",
                        help="with pbms: do not also solve the full-horizon MS for comparison")
    add_backend_arguments(parser)
    parser.add_argument("--output", default=None, metavar="DIR",
                        help="write DIR/result.json, DIR/pursuit.png, DIR/convergence.png")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.samples > MAX_SAMPLES:
        parser.error(f"--samples must be at most {MAX_SAMPLES}, got {args.samples}")
    if args.no_reference and args.mode != "pbms":
        parser.error(f"--no-reference only applies to --mode pbms, not {args.mode}")
    try:
        args.problem = OrbitTransferProblem(case=args.case, samples=args.samples)
        args.settings = PursuitSettings(args.window, args.update, args.epsilon, args.max_agents)
        args.settings.check(args.samples)
    except ValueError as exc:
        parser.error(str(exc))
    mass_kg = args.problem.initial_mass * KG_PER_T
    if args.epsilon >= mass_kg:
        parser.error(f"--epsilon must be below the spacecraft's initial mass {mass_kg:g} kg, "
                     f"got {args.epsilon:g}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    choose_backend(args, PROG)
    out = prepare_output_dir(args.output, PROG)
    problem = args.problem

    def solve(backend, say):
        say(f"{PROG}: case {args.case}, N = {args.samples}, mode {args.mode}, "
            f"N_Δ = {args.window}, N_δ = {args.update}, backend {backend.name} with "
            f"{backend.workers} worker(s)")
        return solve_pursuit(problem, args.settings, backend, args.mode,
                             reference=not args.no_reference, progress=say)

    result = run_on_backend(args, PROG, solve)
    if result is None:  # an MPI rank other than 0
        return 0
    print(result.summary(), flush=True)
    if out is not None:
        written = [result.write_json(out), plot_trajectories(problem, result, out / "pursuit.png")]
        if args.mode == "pbms":
            written.append(plot_convergence(result, out / "convergence.png"))
        print("wrote " + ", ".join(str(p) for p in written))
    return 0 if result.converged else 1


if __name__ == "__main__":
    sys.exit(main())
