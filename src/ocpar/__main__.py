"""Command line: ``ocpar COMMAND`` (or ``python -m ocpar COMMAND``).

``ocpar run CONFIG [--set KEY=VALUE ...] [--print-argv]`` runs the configuration file CONFIG
(:mod:`ocpar.config`), or the packaged example of that name (``ocpar run --list``), through
its scheme's own command line: ``ocpar run formation-60`` is ``python -m ocpar.formation
--problem point-mass-plane --agents 60 ...``, the same run and the same ``result.json``. Under
``mpirun -n P`` every rank does the same, as the schemes' command lines do.

Each command is a subparser with a ``handler(args) -> int``; bad usage is one line on stderr
and exit status 2.
"""

from __future__ import annotations

import argparse
import sys

from ocpar.cli import OneLineParser, fail
from ocpar.config import ConfigError, examples, load_config, parse_overrides, scheme_module

PROG = "ocpar"


def run(args: argparse.Namespace) -> int:
    prog = f"{PROG} run"
    if args.list:
        if args.config is not None or args.overrides or args.print_argv:
            fail(prog, "--list takes no CONFIG, --set or --print-argv")
        for name, header in examples().items():
            print(f"{name:34} {header}")
        return 0
    if args.config is None and args.overrides and "=" not in args.overrides[-1]:
        args.config = args.overrides.pop()  # CONFIG given after --set KEY=VALUE ...
    if args.config is None:
        fail(prog, "give CONFIG, a TOML file or an example name (ocpar run --list)")
    try:
        config = load_config(args.config, parse_overrides(args.overrides))
    except ConfigError as exc:
        fail(prog, str(exc))
    scheme = scheme_module(config.scheme)
    argv = config.argv()
    if args.print_argv:
        scheme.parse_args(argv)  # the scheme's own checks, with its one-line errors
        print(config.command())
        return 0
    return scheme.main(argv)


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog=PROG,
        description="ocpar: large optimal control problems solved as many small ones in "
        "parallel supersteps. Each scheme also has its own command line: python -m "
        "ocpar.formation|pursuit|macs.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    run_parser = commands.add_parser(
        "run", prog=f"{PROG} run", help="run a configuration file",
        description="Run the configuration CONFIG: a TOML file (scheme = \"formation\", "
        "\"pursuit\" or \"macs\", and one key per option of that scheme's command line, "
        "e.g. max_evals for --max-evals), or the name of a packaged example (--list).")
    run_parser.add_argument("config", nargs="?", metavar="CONFIG",
                            help="a TOML file, or an example name such as formation-60")
    run_parser.add_argument("--set", nargs="+", default=[], dest="overrides",
                            metavar="KEY=VALUE",
                            help="override keys of CONFIG; VALUE is a TOML value (workers=2, "
                                 "quiet=true), taken as a string if it is not one "
                                 "(backend=dask)")
    run_parser.add_argument("--print-argv", action="store_true",
                            help="check CONFIG, print the equivalent scheme command line and "
                                 "exit")
    run_parser.add_argument("--list", action="store_true",
                            help="list the packaged example configurations")
    run_parser.set_defaults(handler=run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
