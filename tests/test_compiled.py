"""Compiled inner kernels (:mod:`ocpar.ocp.compiled`; the full blocks of
:class:`~ocpar.ocp.batch.KktNewton`): the same bits as CasADi's virtual machine on DMOC point
masses (a constant KKT matrix, factorised once per block) and rigid spacecraft (one
factorisation per column); compiled once per host (a second process finds the library in the
cache and never calls the compiler; two processes at once compile it once between them);
without a compiler, one line on stderr and the virtual machine's result."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ocpar.examples.formation_halo import make as halo_example
from ocpar.examples.formation_point_masses import make as point_masses
from ocpar.ocp import dmoc_problem
from ocpar.ocp.batch import COMPILED_BLOCKS, BatchSolve, KktNewton, MappedNlp
from ocpar.ocp.compiled import COMPILE_ENV

COMPILER = shutil.which(os.environ.get("CC", "cc"))
needs_compiler = pytest.mark.skipif(COMPILER is None, reason="no C compiler on this host")


@pytest.fixture(autouse=True)
def compiling(monkeypatch):
    """Compiling on (the suite turns it off: conftest.py)."""
    monkeypatch.delenv(COMPILE_ENV, raising=False)
#: Tasks per solve: one full (compiled) block of each size and a rest the virtual machine
#: solves.
TASKS = sum(COMPILED_BLOCKS) + 3


def solve_fresh(problem, solver: str = "newton", seed: int = 0) -> BatchSolve:
    """``problem``'s DMOC NLP solved by a new :class:`KktNewton` (``newton``) or
    :class:`MappedNlp` (``sqpmethod``), no kernel built before in this process, on
    :data:`TASKS` tasks near its own, from the default guesses."""
    nlp = dmoc_problem(problem.shape)
    w, p = nlp._w, nlp._p
    f, g = nlp.cost(w, p), nlp.constraints(w, p)
    params = np.array([task.params for task in problem.tasks(problem.initial_phi()).items()])
    rng = np.random.default_rng(seed)
    params = params[np.arange(TASKS) % len(params)] + 0.01 * rng.standard_normal(
        (TASKS, params.shape[1]))
    guesses, multipliers = nlp.default_guesses(params), np.zeros((TASKS, nlp.ng))
    if solver == "sqpmethod":
        shape = problem.shape
        return MappedNlp("dmoc_sqp", w, p, f, g, shape.kkt_tol, shape.max_iter, shape.kkt_tol,
                         post=nlp.end_hessian).solve(guesses, params, multipliers, nlp.lbg,
                                                     nlp.ubg, nlp.lbx, nlp.ubx)
    newton = KktNewton("dmoc", w, p, f, g, 1, nlp.solver_settings["newton"]["kkt_tol"],
                       post=nlp.end_hessian)
    return newton.solve(guesses, params, multipliers, nlp.lbx, nlp.ubx,
                        rounds=nlp.solver_settings["newton"]["max_iter"])


def digest(solve: BatchSolve) -> str:
    """A hash of every number a batched solve returns (bitwise comparison)."""
    arrays = (solve.x, solve.f, solve.lam_g, solve.lam_p, solve.success, solve.extra,
              solve.iterations, solve.lam_x)
    return hashlib.sha256(b"".join(np.asarray(a).tobytes() for a in arrays
                                   if a is not None)).hexdigest()


@needs_compiler
@pytest.mark.parametrize(("example", "solver"), [("point-masses", "newton"),
                                                 ("halo", "newton"),
                                                 ("point-masses", "sqpmethod")])
def test_compiled_kernels_give_the_virtual_machines_bits(example, solver, tmp_path,
                                                         monkeypatch):
    """Compiled (into an empty cache: one library per kernel) and on the virtual machine
    (``CC`` a missing compiler), every output of the batched solve (Newton steps; the mapped
    ``sqpmethod``) is the same bits; every task converged."""
    problem = point_masses(4) if example == "point-masses" else halo_example(agents=3,
                                                                             intervals=4)
    monkeypatch.setenv("OCPAR_CACHE", str(tmp_path))
    compiled = solve_fresh(problem, solver)
    libraries = list((tmp_path / "compiled").glob("*.so"))
    assert len(libraries) >= 2 * len(COMPILED_BLOCKS)   # solver, gradient or residuals
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    virtual = solve_fresh(problem, solver)
    assert compiled.success.all() and virtual.success.all()
    assert digest(compiled) == digest(virtual)


SCRIPT = """
import sys
from ocpar.examples.formation_point_masses import make
sys.path.insert(0, sys.argv[1])
from test_compiled import digest, solve_fresh
print(digest(solve_fresh(make(4))))
"""


def start_solve(cache: Path, compiler: str) -> subprocess.Popen:
    """:func:`solve_fresh` of four point masses started in a new process with
    ``OCPAR_CACHE`` and ``CC`` set; its stdout the result's digest."""
    env = {k: v for k, v in os.environ.items() if k != COMPILE_ENV} | {
        "OCPAR_CACHE": str(cache), "CC": compiler}
    return subprocess.Popen([sys.executable, "-c", SCRIPT, str(Path(__file__).parent)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def outputs(*processes: subprocess.Popen) -> list[tuple[str, str]]:
    """Each process's (stdout, stderr), once it exited with status 0."""
    out = [process.communicate(timeout=300) for process in processes]
    assert all(process.returncode == 0 for process in processes), out
    return out


@needs_compiler
def test_processes_of_one_host_compile_once_and_a_host_without_compiler_says_so(tmp_path):
    """Two processes started together on an empty cache (the compiler a wrapper that logs its
    calls) compile each library once between them; a third process with the same cache loads
    the libraries and never calls the compiler; with ``CC`` a missing binary a process says
    so in one line on stderr and returns the same bits from the virtual machine."""
    log = tmp_path / "calls.log"
    wrapper = tmp_path / "logging-cc"
    wrapper.write_text(f'#!/bin/sh\necho "$@" >> {log}\nexec {COMPILER} "$@"\n')
    wrapper.chmod(0o755)
    cache = tmp_path / "cache"
    (first, first_err), (other, _) = outputs(start_solve(cache, str(wrapper)),
                                             start_solve(cache, str(wrapper)))
    calls = log.read_text().count("\n")
    assert calls == len(list((cache / "compiled").glob("*.so"))) >= 2 * len(COMPILED_BLOCKS)
    assert first == other and first_err == ""
    (again, _), = outputs(start_solve(cache, str(wrapper)))
    assert log.read_text().count("\n") == calls and again == first
    (without, without_err), = outputs(start_solve(cache, str(tmp_path / "no-such-compiler")))
    assert without == first
    lines = without_err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("ocpar: no C compiler")


def test_compiling_turned_off_runs_on_the_virtual_machine(tmp_path, monkeypatch):
    """With ``OCPAR_COMPILE=0`` nothing is compiled (the cache stays empty) and the batch
    solves as on a host without a compiler, to the same bits."""
    monkeypatch.setenv("OCPAR_CACHE", str(tmp_path))
    monkeypatch.setenv(COMPILE_ENV, "0")
    off = solve_fresh(point_masses(4), "newton")
    assert not list(tmp_path.glob("**/*.so"))
    monkeypatch.delenv(COMPILE_ENV)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    without_compiler = solve_fresh(point_masses(4), "newton")
    assert off.success.all()
    for name in ("x", "f", "lam_g", "lam_p"):
        assert np.array_equal(getattr(off, name), getattr(without_compiler, name))

