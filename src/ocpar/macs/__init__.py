"""Multi-objective optimal control with Multi Agent Collaborative Search (MACSoc).

The coordinator holds the MACS population and the Pareto archive; each superstep runs all
agents' local searches of one kind (Pascoletti–Serafini scalarised NLPs, or constraint
restorations of differential-evolution candidates) on the workers. Problems are transcribed
by DFET (Vasile & Ricciardi).

>>> from ocpar.macs import MacsSettings, make_problem, solve_macs
>>> result = solve_macs(make_problem("goddard"), MacsSettings(max_evaluations=500, seed=1))
>>> result.front.shape[1]
2
"""

from ocpar.macs.algorithm import MacsSettings
from ocpar.macs.problems import PROBLEMS, GoddardProblem, OrbitRaisingProblem, make_problem
from ocpar.macs.result import MacsResult
from ocpar.macs.solve import solve_macs

__all__ = [
    "PROBLEMS",
    "GoddardProblem",
    "MacsResult",
    "MacsSettings",
    "OrbitRaisingProblem",
    "make_problem",
    "solve_macs",
]
