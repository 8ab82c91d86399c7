"""Local pursuit as a computational tool: pursuit-based multiple shooting (PBMS).

A train of agents, each a copy of the system, improves on its predecessor by repeatedly
solving small multiple-shooting problems to intercept it (Hristu-Varsakelis, Shao, Samaras).
All agents in flight at one time solve in one superstep. A problem is any ẋ = f(x, u) with
a running cost, a target set and agent 0's feasible plan (:class:`PursuitProblem`), over a
fixed horizon or a free one (``final_time``, solved by the full-horizon MS, ``mode="ms"``);
the paper's orbit transfer is :mod:`ocpar.examples.pursuit_orbit_transfer`, a minimum-time
double integrator :mod:`ocpar.examples.pursuit_min_time`.

>>> from ocpar.examples.pursuit_orbit_transfer import make
>>> from ocpar.pursuit import solve_pursuit
>>> result = solve_pursuit(make(case=1, samples=301), mode="ms")
>>> round(result.headline, 3)
523.975
"""

from ocpar.pursuit.problem import ControlLaw, FinalValue, PursuitProblem, SampledPlan
from ocpar.pursuit.result import PursuitResult
from ocpar.pursuit.slp import PursuitSettings
from ocpar.pursuit.solve import MODES, solve_pursuit

__all__ = ["MODES", "ControlLaw", "FinalValue", "PursuitProblem", "PursuitResult",
           "PursuitSettings", "SampledPlan", "solve_pursuit"]

