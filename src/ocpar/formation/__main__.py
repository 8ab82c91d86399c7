"""Command line: ``python -m ocpar.formation`` (or under ``mpirun -n P``); see ``--help``.

The options are the fields of :class:`ocpar.formation.run.FormationRun`;
:mod:`ocpar.driver` runs them.
"""

import sys

from ocpar import driver
from ocpar.formation.run import FormationRun

if __name__ == "__main__":
    sys.exit(driver.main(FormationRun))
