"""Transcriptions of inner optimal control problems into parametric CasADi NLPs, behind one
contract (:mod:`ocpar.ocp.contract`).

A *shape* (frozen, hashable: everything that fixes the NLP's structure) builds its
transcription once per process (:func:`transcription`); a task (:class:`OcpTask`: the shape,
the parameters p and the guesses to try, numbers only) is solved by the one engine kernel
:func:`solve_task`, which applies the failure policy and returns a solution with the common
fields of :class:`InnerSolution` plus the transcription's payload; :func:`solve_tasks` is its
batched form (one mapped solver call per chunk where the transcription offers
``solve_batch``, :mod:`ocpar.ocp.batch`). Every transcription offers
``solve(params, guess, multipliers)``, ``failure(params, status, elapsed)``,
``default_guess(params)``, ``fallback_guesses(params)`` and ``warm_start(solution)``.

- :mod:`ocpar.ocp.dmoc`: discrete mechanics and optimal control (Lagrangian systems),
  p = (q_0, q̇_0, q_N, q̇_N);
- :mod:`ocpar.ocp.multiple_shooting`: direct multiple shooting, Euler or RK4 (ODE models,
  fixed or free final time), p = (x_0, target); :mod:`ocpar.ocp.ms_endpoint` the same between
  two given states, a formation's ODE agent, p = (x_0, x̄_N);
- :mod:`ocpar.ocp.dfet_ocp`: direct finite elements in time (ODE models, free or fixed final
  time), p = (x_0, target); :mod:`ocpar.ocp.dfet` holds its weak form and the state solver
  that MACS uses.
"""

from ocpar.ocp.contract import (
    INVALID_GUESS,
    INVALID_PARAMS,
    BatchTranscription,
    InnerSolution,
    OcpTask,
    Shape,
    Transcription,
    cache_report,
    solve_task,
    solve_tasks,
    transcription,
)
from ocpar.ocp.dfet import DfetShape, DfetTranscription, dfet_problem
from ocpar.ocp.dfet_ocp import DfetOcpShape, DfetOcpTranscription, DfetSolution, dfet_ocp_problem
from ocpar.ocp.dmoc import DmocShape, DmocSolution, DmocTranscription, dmoc_problem
from ocpar.ocp.ms_endpoint import MsEndpointShape, MsEndpointSolution, MsEndpointTranscription
from ocpar.ocp.multiple_shooting import MsShape, MsSolution, MsTranscription, ms_problem

__all__ = [
    "INVALID_GUESS",
    "INVALID_PARAMS",
    "BatchTranscription",
    "DfetOcpShape",
    "DfetOcpTranscription",
    "DfetShape",
    "DfetSolution",
    "DfetTranscription",
    "DmocShape",
    "DmocSolution",
    "DmocTranscription",
    "InnerSolution",
    "MsEndpointShape",
    "MsEndpointSolution",
    "MsEndpointTranscription",
    "MsShape",
    "MsSolution",
    "MsTranscription",
    "OcpTask",
    "Shape",
    "Transcription",
    "cache_report",
    "dfet_ocp_problem",
    "dfet_problem",
    "dmoc_problem",
    "ms_problem",
    "solve_task",
    "solve_tasks",
    "transcription",
]
