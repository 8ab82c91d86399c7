#!/usr/bin/env python
"""Each inner kernel compiled (:mod:`ocpar.ocp.compiled`) against CasADi's virtual machine:
time per call (medians, the two alternating), the same bits or the largest relative
difference, and the compilation's time (into a fresh cache).

    python scripts/compiled_kernels.py --output runs/compiled_kernels.json
    python scripts/compiled_kernels.py --kernels dmoc-point-mass-newton dmoc-halo-newton

Kernels (a call on a block of 256 columns where batched):

* ``dmoc-point-mass-newton``: :class:`~ocpar.ocp.batch.KktNewton`'s Newton step of the
  formation's point masses (N = 10; a constant KKT matrix, one factorisation per call);
* ``dmoc-point-mass-gradient``: its cost gradient's norm at each column;
* ``dmoc-halo-newton``: the rigid halo spacecraft's Newton step (N = 10; a sparse QR per
  column);
* ``dmoc-point-mass-sqpmethod``, ``dmoc-halo-sqpmethod``: the mapped ``sqpmethod`` +
  ``qrqp`` of the same NLPs (:class:`~ocpar.ocp.batch.MappedNlp`), from the default guesses;
* ``ms-pursuit-newton``: the pursuit's multiple-shooting Newton function (orbit transfer, case
  1, a 60-interval window; two steps, sparse QR), one agent per call;
* ``dfet-goddard-ipopt``: an IPOPT solve of MACS Goddard's DFET restoration NLP (from the
  transcription's default guess), its NLP functions on the virtual machine against CasADi's
  ``jit`` (the same generated C, this compiler and flags); ``nlp_share``: the part of IPOPT's
  time spent in the NLP functions on the virtual machine, the most compiling them can save.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np

from ocpar.ocp.batch import MAX_COLUMNS, BufferedFunction
from ocpar.ocp.compiled import FLAGS, compiled

Call = Callable[[], list[np.ndarray]]


def _dmoc(example: str, solver: str = "newton"):
    """The DMOC transcription of the formation ``example`` with ``solver``, and its tasks."""
    from ocpar.examples.formation_halo import make as halo
    from ocpar.examples.formation_point_masses import make as point_masses
    from ocpar.ocp import dmoc_problem
    problem = point_masses(8) if example == "point-mass" else halo(agents=4, intervals=10)
    nlp = dmoc_problem(dataclasses.replace(problem.shape, solver=solver))
    params = np.array([task.params for task in problem.tasks(problem.initial_phi()).items()])
    rng = np.random.default_rng(0)
    params = params[np.arange(MAX_COLUMNS) % len(params)] * (
        1 + 0.01 * rng.standard_normal((MAX_COLUMNS, params.shape[1])))
    return nlp, params


def _buffered(function: ca.Function, args: list[np.ndarray]) -> tuple[Call, Call]:
    """(VM call, compiled call) of ``function`` on ``args`` through buffers."""
    vm, cc = BufferedFunction(function), BufferedFunction(compiled(function))
    return (lambda: vm(*args)), (lambda: cc(*args))


def newton_kernel(example: str) -> tuple[Call, Call]:
    nlp, params = _dmoc(example)
    solver = nlp.batch_solver
    function = (solver._per_column.map(MAX_COLUMNS, "serial")
                if solver.constant_matrix is None else solver.system.batched_newton(
                    solver.name, solver.steps, solver.constant_matrix, MAX_COLUMNS))
    x0 = nlp.default_guesses(params)
    return _buffered(function, [x0.ravel(), np.zeros(MAX_COLUMNS * nlp.ng), params.ravel()])


def gradient_kernel() -> tuple[Call, Call]:
    nlp, params = _dmoc("point-mass")
    solver = nlp.batch_solver
    return _buffered(solver.gradient.map(MAX_COLUMNS, "serial"),
                     [nlp.default_guesses(params).ravel(), params.ravel()])


def sqp_kernel(example: str) -> tuple[Call, Call]:
    nlp, params = _dmoc(example, "sqpmethod")
    function = nlp.batch_solver.solver.map(MAX_COLUMNS, "serial")
    fast = compiled(function)
    args = {"x0": nlp.default_guesses(params).T, "p": params.T,
            "lam_g0": np.zeros((nlp.ng, MAX_COLUMNS)), "lbg": nlp.lbg, "ubg": nlp.ubg,
            "lbx": nlp.lbx, "ubx": nlp.ubx}
    return ((lambda: [np.asarray(v) for v in function(**args).values()]),
            (lambda: [np.asarray(v) for v in fast(**args).values()]))


def ms_kernel() -> tuple[Call, Call]:
    from ocpar.examples.pursuit_orbit_transfer import make
    from ocpar.ocp import transcription
    from ocpar.pursuit.slp import PursuitSettings, window_shape
    nlp = transcription(window_shape(make(1, 301), PursuitSettings(), 60))
    function = nlp._newton_function
    rng = np.random.default_rng(0)
    args = [nlp.lbw + (nlp.ubw - nlp.lbw).clip(max=1.0) * rng.uniform(size=nlp.lbw.size),
            np.zeros(function.nnz_in(1)), rng.uniform(0.5, 1.5, function.nnz_in(2))]
    return _buffered(function, args)


def ipopt_kernel() -> tuple[Call, Call, float]:
    from ocpar.examples.macs_goddard import make
    from ocpar.macs.local_search import InnerSolvers
    inner = InnerSolvers(make())
    dfet = inner.dfet
    nlp = {"x": dfet.z, "f": 0, "g": inner._g}
    settings = inner.settings["restore"]
    jit = {"jit": True, "compiler": "shell",
           "jit_options": {"flags": [FLAGS[0], FLAGS[-1]], "verbose": False}}
    plain = ca.nlpsol("restore", "ipopt", nlp, settings)
    fast = ca.nlpsol("restore", "ipopt", nlp, settings | jit)
    lower, upper = dfet.lbz[dfet.decision_slice], dfet.ubz[dfet.decision_slice]
    decision = np.where(np.isfinite(lower + upper), (lower + upper) / 2,
                        np.clip(0.0, lower, upper))
    args = {"x0": dfet.guess_from_decision(decision), "lbx": dfet.lbz, "ubx": dfet.ubz,
            "lbg": inner.lbg, "ubg": inner.ubg}
    plain(**args)
    start = time.perf_counter()
    plain(**args)                       # a second solve: IPOPT's set-up done
    wall = time.perf_counter() - start
    nlp_time = sum(v for k, v in plain.stats().items() if k.startswith("t_wall_nlp_"))
    return ((lambda: [np.asarray(plain(**args)["x"])]),
            (lambda: [np.asarray(fast(**args)["x"])]), nlp_time / wall)


KERNELS: dict[str, Callable[[], tuple]] = {
    "dmoc-point-mass-newton": lambda: newton_kernel("point-mass"),
    "dmoc-point-mass-gradient": gradient_kernel,
    "dmoc-halo-newton": lambda: newton_kernel("halo"),
    "dmoc-point-mass-sqpmethod": lambda: sqp_kernel("point-mass"),
    "dmoc-halo-sqpmethod": lambda: sqp_kernel("halo"),
    "ms-pursuit-newton": ms_kernel,
    "dfet-goddard-ipopt": ipopt_kernel,
}


def compare(vm: Call, cc: Call, repeat: int) -> dict:
    """Medians of ``repeat`` calls each, alternating, and how far the outputs differ."""
    ref, out = vm(), cc()
    bitwise = all(np.array_equal(a, b, equal_nan=True) for a, b in zip(ref, out, strict=True))
    relative = max(float(np.nanmax(np.abs(a - b) / np.maximum(np.abs(a), 1e-300),
                                   initial=0.0)) for a, b in zip(ref, out, strict=True))
    times: dict[str, list[float]] = {"vm": [], "compiled": []}
    for _ in range(repeat):
        for name, call in (("vm", vm), ("compiled", cc)):
            start = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - start)
    vm_s, cc_s = (float(np.median(times[k])) for k in ("vm", "compiled"))
    return {"vm_ms": vm_s * 1e3, "compiled_ms": cc_s * 1e3, "vm_over_compiled": vm_s / cc_s,
            "bitwise": bitwise, "max_relative_difference": relative}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kernels", nargs="+", choices=list(KERNELS), default=list(KERNELS))
    parser.add_argument("--repeat", type=int, default=15, help="calls of each (default 15)")
    parser.add_argument("--output", type=Path, help="the JSON file (default: stdout only)")
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as cache:
        os.environ["OCPAR_CACHE"] = cache     # cold: every compilation measured
        for name in args.kernels:
            start = time.perf_counter()
            built = KERNELS[name]()
            entry = {"build_and_compile_s": time.perf_counter() - start}
            entry |= compare(built[0], built[1], args.repeat)
            if len(built) > 2:
                entry["nlp_share"] = built[2]
            results[name] = entry
            print(f"{name:28s} VM {entry['vm_ms']:9.3f} ms  compiled {entry['compiled_ms']:9.3f}"
                  f" ms  x{entry['vm_over_compiled']:.2f}  bitwise {entry['bitwise']}  built"
                  f" {entry['build_and_compile_s']:.1f} s"
                  + (f"  NLP functions {entry['nlp_share']:.0%} of IPOPT"
                     if "nlp_share" in entry else ""))
    record = {"kernels": results, "casadi": ca.__version__, "compiler": shutil.which(
        os.environ.get("CC", "cc")), "flags": list(FLAGS), "machine": platform.machine(),
        "load_1min": os.getloadavg()[0]}
    if args.output:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(record, indent=1))
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
