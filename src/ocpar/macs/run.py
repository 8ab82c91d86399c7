"""A MACS run's options: the one schema of ``python -m ocpar.macs``, of a configuration's
keys and of :func:`ocpar.driver.run_scheme` (see :mod:`ocpar.driver`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from ocpar.bsp import Backend
from ocpar.cli import Progress
from ocpar.driver import PROBLEM_GROUP, SchemeRun
from ocpar.macs.algorithm import MacsSettings
from ocpar.macs.problem import MacsProblem
from ocpar.macs.problems import PROBLEMS, make_problem
from ocpar.macs.result import MacsResult
from ocpar.macs.solve import solve_macs
from ocpar.options import option, project
from ocpar.references import is_reference

#: The scheme's public problem type: what a ``--problem package.module:factory`` returns.
PROBLEM_TYPE = MacsProblem
#: Most DFET elements of a built-in problem (its NLP grows with N).
MAX_ELEMENTS = 1_000


@dataclass(frozen=True)
class MacsRun(SchemeRun, MacsSettings):
    """Everything one MACS run needs: the problem, the algorithm's
    :class:`~ocpar.macs.MacsSettings` and where it runs."""

    prog: ClassVar[str] = "ocpar.macs"
    scheme: ClassVar[str] = "macs"
    plots: ClassVar[tuple[str, ...]] = ("front.png", "controls.png")
    description: ClassVar[str] = (
        "MACSoc: multi-objective optimal control by multi-agent collaborative search on a DFET "
        "transcription; the agents' local searches run in parallel.")
    examples: ClassVar[tuple[str, ...]] = (
        "python -m ocpar.macs --output runs/goddard",
        "python -m ocpar.macs --problem orbit-raising --max-evals 3000 --seed 1 "
        "--output runs/orbit --plot none",
        "python -m ocpar.macs --backend dask --workers 2 --population 20",
        "python -m ocpar.macs --problem mypkg.rocket:make --problem-arg stages=2 "
        "--solver-option ipopt.tol=1e-10 --output runs/mine",
    )
    essentials: ClassVar[tuple[str, ...]] = (
        "problem", "max_evals", "seed", "problem_args", "output", "plot", "backend", "workers")
    solver_group: ClassVar[str] = "MACS algorithm"
    problem_type: ClassVar[Any] = PROBLEM_TYPE

    problem: str = option(
        "goddard", f"a built-in problem ({', '.join(sorted(PROBLEMS))}), or "
        "package.module:factory returning a MacsProblem (docs/user-problems.md)",
        metavar="NAME", group=PROBLEM_GROUP)
    elements: int | None = option(
        None, "built-in problem: DFET elements N (default: the problem's: goddard 4, "
        "orbit-raising 30, double-integrator 4; t_f is an objective, free)", low=1,
        high=MAX_ELEMENTS, metavar="N", group=PROBLEM_GROUP)

    def validate(self, given: frozenset[str]) -> None:
        super().validate(given)
        if is_reference(self.problem) and self.elements is not None:
            raise ValueError("--elements only applies to the built-in problems; pass "
                             "--problem-arg elements=... to your factory instead")
        if not is_reference(self.problem) and self.problem not in PROBLEMS:
            raise ValueError(f"--problem: unknown problem {self.problem!r}; choose one of "
                             f"{', '.join(sorted(PROBLEMS))}, or give package.module:factory")
        if self.max_evaluations <= self.population:
            raise ValueError(f"--max-evals {self.max_evaluations} leaves no iteration: "
                             f"initialising --population {self.population} agents takes "
                             f"{self.population} evaluations")

    def build_example(self) -> MacsProblem:
        return make_problem(self.problem, self.elements)

    def describe(self, problem: MacsProblem) -> str:
        return (f"{problem.name}, seed {self.seed}, {self.max_evaluations} evaluations, "
                f"archive {self.archive_size}")

    def solve(self, problem: MacsProblem, backend: Backend, progress: Progress) -> MacsResult:
        return solve_macs(problem, project(self, MacsSettings), backend, progress=progress)

    def plot(self, problem: MacsProblem, result: MacsResult, out: Path) -> list[Path]:
        """front.png (titled failed and why when the archive is empty), and controls.png of
        a few members if there are any."""
        from ocpar.macs.plot import plot_controls, plot_front

        written = [plot_front(result, out / "front.png")]
        if "controls.png" in self.plot_names(result):
            written.append(plot_controls(problem, result, out / "controls.png"))
        return written

    def plot_names(self, result: MacsResult) -> tuple[str, ...]:
        """front.png, and controls.png if the archive has members."""
        return self.plots if len(result.front) else self.plots[:1]
