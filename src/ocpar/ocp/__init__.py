"""Transcriptions of inner optimal control problems into parametric CasADi NLPs.

Each transcription is built once per problem shape per process (see :func:`dmoc_problem`) and
then solved many times with different numbers (boundary data, parameters).
"""

from ocpar.ocp.dmoc import (
    DmocShape,
    DmocSolution,
    DmocTask,
    DmocTranscription,
    dmoc_problem,
    solve_dmoc_task,
)

__all__ = [
    "DmocShape",
    "DmocSolution",
    "DmocTask",
    "DmocTranscription",
    "dmoc_problem",
    "solve_dmoc_task",
]
