"""A formation run's options: the one schema of ``python -m ocpar.formation``, of a
configuration's keys and of :func:`ocpar.driver.run_scheme` (see :mod:`ocpar.driver`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from ocpar.bsp import Backend
from ocpar.cli import Progress
from ocpar.driver import PROBLEM_GROUP, SchemeRun
from ocpar.formation.examples import EXAMPLES, make_example
from ocpar.formation.problem import FormationProblem
from ocpar.formation.result import FormationResult
from ocpar.formation.solve import FormationOptions, check_applicable, solve_formation
from ocpar.formation.targets.slots import Slots
from ocpar.options import option, project
from ocpar.references import is_reference

#: The scheme's public problem type: what a ``--problem package.module:factory`` returns.
PROBLEM_TYPE = FormationProblem
#: Most agents a built-in example may be given (the paper's examples have 60 and 30; 1,000,000
#: point masses run on ``mpirun -n 2``, docs/results.md; the bound keeps a typo from asking for
#: more memory than a machine has).
MAX_AGENTS = 10_000_000
#: Most agents for ``--ordering optimal``, which fills n × n tables of inner solves.
MAX_OPTIMAL_ORDERING_AGENTS = 1_000
#: Most DMOC intervals of a built-in example (each agent's NLP grows with N).
MAX_INTERVALS = 10_000
#: ``--radius`` must lie within this factor of the example's default radius (its length scale).
RADIUS_RANGE = 1e6


@dataclass(frozen=True)
class FormationRun(SchemeRun, FormationOptions):
    """Everything one formation run needs: the problem, the solver's
    :class:`~ocpar.formation.FormationOptions` and where it runs."""

    prog: ClassVar[str] = "ocpar.formation"
    scheme: ClassVar[str] = "formation"
    plots: ClassVar[tuple[str, ...]] = ("formation.png",)
    description: ClassVar[str] = (
        "Hierarchical formation reconfiguration (the paper's 60 point masses by default): "
        "an outer solver over the final angles (projected Newton by default, or the paper's "
        "SQP), inner DMOC solves in parallel supersteps.")
    examples: ClassVar[tuple[str, ...]] = (
        "python -m ocpar.formation --output runs/paper",
        "python -m ocpar.formation --agents 1000 --intervals 20 --output runs/f1000 "
        "--plot none",
        "mpirun -n 2 python -m ocpar.formation --problem crtbp-rigid --agents 1000 --quiet",
        "python -m ocpar.formation --problem mypkg.ships:make --problem-arg agents=8 "
        "--solver-option ipopt.tol=1e-10 --output runs/mine",
    )
    essentials: ClassVar[tuple[str, ...]] = (
        "problem", "agents", "problem_args", "output", "plot", "backend", "workers")
    solver_group: ClassVar[str] = "formation solvers"
    problem_type: ClassVar[type] = PROBLEM_TYPE

    problem: str = option(
        "point-mass-plane", "a built-in example (" + ", ".join(EXAMPLES) + "; each one "
        "described in docs/schemes/formation.md), or package.module:factory returning a "
        "FormationProblem (docs/user-problems.md)", metavar="NAME", group=PROBLEM_GROUP)
    agents: int | None = option(None, "built-in example: number of agents (default: the "
                                "example's)", low=2, high=MAX_AGENTS, metavar="N",
                                group=PROBLEM_GROUP)
    radius: float | None = option(None, "built-in example: radius of the final circle, within "
                                  f"a factor {RADIUS_RANGE:g} of its default (default: the "
                                  "example's)", above=0, group=PROBLEM_GROUP)
    intervals: int | None = option(None, "built-in example: intervals N of each agent's "
                                   "path (default: the example's)", low=1,
                                   high=MAX_INTERVALS, metavar="N", group=PROBLEM_GROUP)
    duration: float | None = option(None, "built-in example: the manoeuvre's duration T (the "
                                    "model's time unit; default: the example's)", above=0,
                                    metavar="T", group=PROBLEM_GROUP)

    def validate(self, given: frozenset[str]) -> None:
        super().validate(given)
        if "outer" in given and self.mode != "hierarchical":
            raise ValueError(f"--outer only applies to --mode hierarchical, not {self.mode}")
        if is_reference(self.problem):
            for key in ("agents", "radius", "intervals", "duration"):
                if key in given:
                    raise ValueError(f"--{key} only applies to the built-in examples; pass "
                                     f"--problem-arg {key}=... to your factory instead")
            return
        if self.problem not in EXAMPLES:
            raise ValueError(f"--problem: unknown example {self.problem!r}; choose one of "
                             f"{', '.join(EXAMPLES)}, or give package.module:factory")
        example = EXAMPLES[self.problem]
        low, high = example.radius / RADIUS_RANGE, example.radius * RADIUS_RANGE
        if self.radius is not None and not low <= self.radius <= high:
            raise ValueError(f"--radius for {self.problem} must be between {low:g} and "
                             f"{high:g}, got {self.radius:g}")
        self._check_ordering(example.agents if self.agents is None else self.agents)

    def check_problem(self, problem: FormationProblem) -> None:
        self._check_ordering(problem.agents)
        check_applicable(problem, project(self, FormationOptions))

    def _check_ordering(self, agents: int) -> None:
        if self.ordering == "optimal" and agents > MAX_OPTIMAL_ORDERING_AGENTS:
            raise ValueError(f"--ordering optimal solves n^2 inner problems per table: at most "
                             f"{MAX_OPTIMAL_ORDERING_AGENTS} agents, got {agents}")

    def build_example(self) -> FormationProblem:
        return make_example(self.problem, self.agents, self.radius, self.intervals,
                            self.duration)

    def describe(self, problem: FormationProblem) -> str:
        choice = (f"onto {problem.curve.count} slots" if isinstance(problem.curve, Slots)
                  else f"ordering {self.ordering}")
        return f"{problem.name}, {problem.agents} agents, mode {self.mode}, {choice}"

    def solve(self, problem: FormationProblem, backend: Backend,
              progress: Progress) -> FormationResult:
        return solve_formation(problem, backend, project(self, FormationOptions),
                               progress=progress,
                               output=None if self.output is None else Path(self.output))

    def plot(self, problem: FormationProblem, result: FormationResult,
             out: Path) -> list[Path]:
        from ocpar.formation.plot import plot_formation

        return [plot_formation(problem, result, out / "formation.png")]
