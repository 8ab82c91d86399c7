"""Hierarchical formation reconfiguration (Junge, Marsden, Ober-Blöbaum et al., DMOC).

The outer problem chooses each agent's final angle φ_i on a circle subject to the equidistance
constraint g(φ) = dG/dφ = 0; each inner problem moves one agent by DMOC to its point, and all
inner problems of one outer evaluation run in one superstep.

>>> from ocpar.formation import paper_example, solve_formation
>>> result = solve_formation(paper_example(agents=6))   # serial backend by default
>>> result.converged
True
"""

from ocpar.formation.problem import FormationProblem, paper_example
from ocpar.formation.result import FormationResult
from ocpar.formation.solve import MODES, FormationOptions, solve_formation

__all__ = [
    "MODES",
    "FormationOptions",
    "FormationProblem",
    "FormationResult",
    "paper_example",
    "solve_formation",
]
