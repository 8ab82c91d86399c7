"""Command line: ``python -m ocpar.macs`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.macs.run.MacsRun`;
:mod:`ocpar.driver` runs them.
"""

import sys

from ocpar import driver
from ocpar.macs.run import MacsRun

if __name__ == "__main__":
    sys.exit(driver.main(MacsRun))
