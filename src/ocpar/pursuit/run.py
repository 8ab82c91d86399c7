"""A pursuit run's options: the one schema of ``python -m ocpar.pursuit``, of a
configuration's keys and of :func:`ocpar.driver.run_scheme` (see :mod:`ocpar.driver`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from ocpar.bsp import Backend
from ocpar.cli import Progress
from ocpar.driver import PROBLEM_GROUP, SchemeRun
from ocpar.examples import pursuit_min_time, pursuit_orbit_transfer
from ocpar.options import option, project
from ocpar.pursuit.problem import PursuitProblem
from ocpar.pursuit.result import PursuitResult
from ocpar.pursuit.slp import PursuitSettings
from ocpar.pursuit.solve import MODES, check_mode, solve_pursuit
from ocpar.references import is_reference

#: The scheme's public problem type: what a ``--problem package.module:factory`` returns.
PROBLEM_TYPE = PursuitProblem
#: The built-in example (the paper's orbit transfer, by ``--case`` and ``--samples``).
EXAMPLE = "orbit-transfer"
#: The built-in free-final-time example (a double integrator, by ``--samples`` and
#: ``--energy``; ``--mode ms``).
MIN_TIME = "min-time"
#: Each built-in example's own options (``samples`` applies to both).
EXAMPLE_OPTIONS = {EXAMPLE: ("case",), MIN_TIME: ("energy",)}
#: Largest N: PBMS keeps about N/N_Δ agents of N samples each in flight.
MAX_SAMPLES = 100_001


@dataclass(frozen=True)
class PursuitRun(SchemeRun, PursuitSettings):
    """Everything one pursuit run needs: the problem, the SLP's
    :class:`~ocpar.pursuit.PursuitSettings`, the mode and where it runs."""

    prog: ClassVar[str] = "ocpar.pursuit"
    scheme: ClassVar[str] = "pursuit"
    plots: ClassVar[tuple[str, ...]] = ("pursuit.png", "convergence.png")
    description: ClassVar[str] = (
        "Pursuit-based multiple shooting (PBMS) on the paper's orbit transfer: a train of "
        "agents, each intercepting its predecessor; agents in flight solve in parallel.")
    examples: ClassVar[tuple[str, ...]] = (
        "python -m ocpar.pursuit --output runs/transfer",
        "python -m ocpar.pursuit --case 2 --samples 601 --output runs/case2 --plot none",
        "python -m ocpar.pursuit --problem min-time --mode ms --energy 0.5",
        "mpirun -n 2 python -m ocpar.pursuit --samples 1201 --quiet",
        "python -m ocpar.pursuit --problem mypkg.vdp:make --problem-arg samples=301 "
        "--solver-option ipopt.tol=1e-10 --output runs/mine",
    )
    essentials: ClassVar[tuple[str, ...]] = (
        "problem", "samples", "problem_args", "output", "plot", "backend", "workers")
    solver_group: ClassVar[str] = "pursuit solver"
    problem_type: ClassVar[type] = PROBLEM_TYPE

    problem: str = option(
        EXAMPLE, f"{EXAMPLE} (the paper's, by --case and --samples), {MIN_TIME} (a double "
        "integrator to rest in free final time, by --samples and --energy; --mode ms), or "
        "package.module:factory returning a PursuitProblem (docs/user-problems.md)",
        metavar="NAME", group=PROBLEM_GROUP)
    case: int = option(1, f"{EXAMPLE}: 1: R_T = 12.7778 Mm (guess eq. 16); 2: R_T = 23.642 Mm "
                       "(eq. 20)", choices=sorted(pursuit_orbit_transfer.CASE_RADIUS),
                       group=PROBLEM_GROUP)
    samples: int = option(301, f"built-in examples: samples N (h = T/(N-1); {EXAMPLE}: over "
                          "T = 300 min)", low=1, high=MAX_SAMPLES, metavar="N",
                          group=PROBLEM_GROUP)
    energy: float = option(0.0, f"{MIN_TIME}: weight c of the energy c*integral(u^2/2) beside "
                           "the final time (0: minimum time)", low=0, metavar="C",
                           group=PROBLEM_GROUP)
    mode: str = option("pbms", "pbms, or ms (one NLP over the whole horizon)", choices=MODES)
    no_reference: bool = option(False, "with pbms: do not also solve the full-horizon MS for "
                                "comparison")

    def validate(self, given: frozenset[str]) -> None:
        super().validate(given)
        if self.no_reference and self.mode != "pbms":
            raise ValueError(f"--no-reference only applies to --mode pbms, not {self.mode}")
        if is_reference(self.problem):
            for key in ("case", "samples", "energy"):
                if key in given:
                    raise ValueError(f"--{key} only applies to the built-in examples; pass "
                                     f"--problem-arg {key}=... to your factory instead")
            return
        if self.problem not in EXAMPLE_OPTIONS:
            raise ValueError(f"--problem: unknown example {self.problem!r}; give "
                             f"{' or '.join(EXAMPLE_OPTIONS)}, or package.module:factory")
        for example, keys in EXAMPLE_OPTIONS.items():
            for key in keys:
                if key in given and example != self.problem:
                    raise ValueError(f"--{key} only applies to the built-in {example}")
        self.check_problem(self.build_example())

    def check_problem(self, problem: PursuitProblem) -> None:
        check_mode(problem, self.mode, self.settings())

    def settings(self) -> PursuitSettings:
        """The SLP's settings alone."""
        return project(self, PursuitSettings)

    def build_example(self) -> PursuitProblem:
        if self.problem == MIN_TIME:
            return pursuit_min_time.make(samples=self.samples, energy=self.energy)
        return pursuit_orbit_transfer.make(case=self.case, samples=self.samples)

    def describe(self, problem: PursuitProblem) -> str:
        levels = f", {self.levels} levels" if self.levels > 1 else ""
        free = (f", free final time in [{problem.final_time[0]:g}, {problem.final_time[1]:g}]"
                if problem.final_time is not None else "")
        return (f"{problem.name}, N = {problem.samples}{free}, mode {self.mode}, N_Δ = "
                f"{self.window}, N_δ = {self.update}{levels}")

    def solve(self, problem: PursuitProblem, backend: Backend,
              progress: Progress) -> PursuitResult:
        return solve_pursuit(problem, self.settings(), backend, self.mode,
                             reference=not self.no_reference, progress=progress)

    def plot(self, problem: PursuitProblem, result: PursuitResult,
             out: Path) -> list[Path]:
        from ocpar.pursuit.plot import plot_convergence, plot_trajectories

        written = [plot_trajectories(problem, result, out / "pursuit.png")]
        if "convergence.png" in self.plot_names(result):
            written.append(plot_convergence(result, out / "convergence.png"))
        return written

    def plot_names(self, result: PursuitResult) -> tuple[str, ...]:
        """pursuit.png, and convergence.png in mode pbms."""
        return self.plots if self.mode == "pbms" else self.plots[:1]
