"""Transcriptions of inner optimal control problems into parametric CasADi NLPs.

Each transcription is built once per problem shape per process (:func:`dmoc_problem`,
:func:`ms_problem`) and then solved many times with different numbers (boundary data,
parameters, warm starts).

- :mod:`ocpar.ocp.dmoc`: discrete mechanics and optimal control (Lagrangian systems);
- :mod:`ocpar.ocp.multiple_shooting`: direct multiple shooting, Euler or RK4 (ODE models);
- :mod:`ocpar.ocp.dfet`: direct finite elements in time, free final time (ODE models).
"""

from ocpar.ocp.dfet import DfetShape, DfetTranscription, dfet_problem
from ocpar.ocp.dmoc import (
    DmocShape,
    DmocSolution,
    DmocTask,
    DmocTranscription,
    dmoc_problem,
    solve_dmoc_task,
)
from ocpar.ocp.multiple_shooting import (
    MsShape,
    MsSolution,
    MsTask,
    MsTranscription,
    ms_problem,
    solve_ms_task,
)

__all__ = [
    "DfetShape",
    "DfetTranscription",
    "DmocShape",
    "DmocSolution",
    "DmocTask",
    "DmocTranscription",
    "MsShape",
    "MsSolution",
    "MsTask",
    "MsTranscription",
    "dfet_problem",
    "dmoc_problem",
    "ms_problem",
    "solve_dmoc_task",
    "solve_ms_task",
]
