"""Multi-objective optimal control with Multi Agent Collaborative Search (MACSoc).

A problem is a :class:`MacsProblem`: any ODE model, m ≥ 2 objectives (:class:`Objective`, a
Mayer term in (x(t_f), t_f) and/or the integral of a running cost), free or fixed t_f, control
bounds, boundary conditions. The coordinator holds the MACS population and the Pareto archive;
each superstep runs all agents' local searches of one kind (Pascoletti–Serafini scalarised
NLPs, or constraint restorations of differential-evolution candidates) on the workers.
Problems are transcribed by DFET (Vasile & Ricciardi).

>>> from ocpar.macs import MacsSettings, make_problem, solve_macs
>>> result = solve_macs(make_problem("goddard"), MacsSettings(max_evaluations=500, seed=1))
>>> result.front.shape[1]
2
"""

from ocpar.macs.algorithm import MacsSettings
from ocpar.macs.problem import MacsProblem, Objective
from ocpar.macs.problems import PROBLEMS, make_problem
from ocpar.macs.reference import reference_front
from ocpar.macs.result import MacsResult
from ocpar.macs.solve import solve_macs

__all__ = [
    "PROBLEMS",
    "MacsProblem",
    "MacsResult",
    "MacsSettings",
    "Objective",
    "make_problem",
    "reference_front",
    "solve_macs",
]
