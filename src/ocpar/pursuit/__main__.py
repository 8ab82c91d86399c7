"""Command line: ``python -m ocpar.pursuit`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.pursuit.run.PursuitRun`;
:mod:`ocpar.driver` runs them.
"""

from __future__ import annotations

import argparse
import sys

from ocpar import driver
from ocpar.pursuit.run import PursuitRun

PROG = PursuitRun.prog


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (its options are also the keys of a run configuration)."""
    return driver.build_parser(PursuitRun)


def parse_args(argv: list[str] | None = None) -> PursuitRun:
    """The options of ``argv``, checked (exits 2 with one line on bad input)."""
    return driver.parse_options(PursuitRun, argv)[0]


def main(argv: list[str] | None = None) -> int:
    return driver.main(PursuitRun, argv)


if __name__ == "__main__":
    sys.exit(main())
