"""Command line: ``python -m ocpar.macs`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.macs.run.MacsRun`;
:mod:`ocpar.driver` runs them.
"""

from __future__ import annotations

import argparse
import sys

from ocpar import driver
from ocpar.macs.run import MacsRun

PROG = MacsRun.prog


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (its options are also the keys of a run configuration)."""
    return driver.build_parser(MacsRun)


def parse_args(argv: list[str] | None = None) -> MacsRun:
    """The options of ``argv``, checked (exits 2 with one line on bad input)."""
    return driver.parse_options(MacsRun, argv)[0]


def main(argv: list[str] | None = None) -> int:
    return driver.main(MacsRun, argv)


if __name__ == "__main__":
    sys.exit(main())
