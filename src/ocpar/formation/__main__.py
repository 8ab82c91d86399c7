"""Command line: ``python -m ocpar.formation`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.formation.run.FormationRun`;
:mod:`ocpar.driver` runs them.
"""

from __future__ import annotations

import argparse
import sys

from ocpar import driver
from ocpar.formation.run import FormationRun

PROG = FormationRun.prog


def build_parser() -> argparse.ArgumentParser:
    """The command line's parser (its options are also the keys of a run configuration)."""
    return driver.build_parser(FormationRun)


def parse_args(argv: list[str] | None = None) -> FormationRun:
    """The options of ``argv``, checked (exits 2 with one line on bad input)."""
    return driver.parse_options(FormationRun, argv)[0]


def main(argv: list[str] | None = None) -> int:
    return driver.main(FormationRun, argv)


if __name__ == "__main__":
    sys.exit(main())
