"""Command line: ``python -m ocpar.pursuit`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.pursuit.run.PursuitRun`;
:mod:`ocpar.driver` runs them.
"""

import sys

from ocpar import driver
from ocpar.pursuit.run import PursuitRun

if __name__ == "__main__":
    sys.exit(driver.main(PursuitRun))
