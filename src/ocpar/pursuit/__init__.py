"""Local pursuit as a computational tool: pursuit-based multiple shooting (PBMS).

A train of agents, each a copy of the system, improves on its predecessor by repeatedly
solving small multiple-shooting problems to intercept it (Hristu-Varsakelis, Shao, Samaras).
All agents in flight at one time solve in one superstep.

>>> from ocpar.pursuit import OrbitTransferProblem, PursuitSettings, solve_pursuit
>>> result = solve_pursuit(OrbitTransferProblem(case=1, samples=301), mode="ms")
>>> round(result.final_mass_kg, 3)
523.975
"""

from ocpar.pursuit.problem import OrbitTransferProblem
from ocpar.pursuit.result import PursuitResult
from ocpar.pursuit.slp import PursuitSettings
from ocpar.pursuit.solve import MODES, solve_pursuit

__all__ = ["MODES", "OrbitTransferProblem", "PursuitResult", "PursuitSettings", "solve_pursuit"]
