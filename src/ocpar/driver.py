"""The one driver of every scheme's run: options → problem → backend → result.json.

A scheme is a subclass of :class:`SchemeRun`: one frozen dataclass whose fields are all the
scheme's options (the solver's settings it inherits, the shared :class:`RuntimeOptions`, the
problem) and whose methods say what differs between schemes (build a built-in example, solve,
plot). :func:`main` is a scheme's whole command line; :func:`run_scheme` the same from Python::

    from ocpar.driver import run_scheme
    from ocpar.formation.run import FormationRun
    run_scheme(FormationRun(problem="mypkg.problems:make", output="runs/mine"))

The driver checks the options (one line, exit 2), chooses and opens the backend, loads the
problem (a built-in name, or ``package.module:factory`` checked against the scheme's problem
type before any worker starts), journals and checkpoints the supersteps, writes
``result.json``, the array file and ``trace.json`` (:mod:`ocpar.result_files`) and the
plots, and exits with the status's code (:data:`ocpar.results.EXIT_STATUS`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from ocpar.bsp import Backend
from ocpar.cli import (
    BACKEND_GROUP,
    OUTPUT_GROUP,
    CheckingParser,
    OneLineParser,
    Progress,
    RuntimeOptions,
    choose_backend,
    fail,
    freeze_objects_at_exit,
    interrupted,
    one_line_warnings,
    prepare_output_dir,
    run_on_backend,
)
from ocpar.options import add_options, option, option_specs, options_from_namespace
from ocpar.plotting import warm_up
from ocpar.references import REFERENCE, ProblemReferenceError, is_reference, load_problem
from ocpar.result_files import write_result, write_timings
from ocpar.results import RunResult
from ocpar.schemes import SCHEMES, scheme_class
from ocpar.timing import process_age, timings_line

PROBLEM_GROUP = "problem"
#: The heading of the options a newcomer needs (a scheme's :attr:`SchemeRun.essentials`).
ESSENTIALS_GROUP = "essentials: the problem, its size, where it runs, what it writes"
#: The width ``--help``'s description and examples are wrapped to (argparse's own default).
HELP_WIDTH = 78


@dataclass(frozen=True)
class SchemeRun(RuntimeOptions):
    """Base of a scheme's options: the runtime options, keyword arguments for a problem
    factory, and the hooks the driver calls. Each scheme adds its ``problem`` field (a
    built-in example name or ``package.module:factory``) and its own options."""

    problem_args: dict = option(  # noqa: RUF009 (option() is a dataclass field)
        default_factory=dict, help="a keyword argument of --problem package.module:factory "
        "(VALUE a TOML scalar: 4, 0.5, true, \"text\"; or else a string); repeat for more",
        name="problem_args",
        flag="--problem-arg", group=PROBLEM_GROUP)

    #: the scheme's command-line name and ``--help`` description
    prog: ClassVar[str]
    description: ClassVar[str]
    #: the scheme's public problem type(s): what a factory must return
    problem_type: ClassVar[type | tuple[type, ...]]
    #: the scheme's name (``scheme`` in configurations and result.json)
    scheme: ClassVar[str]
    #: the file names of the plots the scheme may write into its output directory
    plots: ClassVar[tuple[str, ...]]
    #: the keys of the options a newcomer needs, listed first by ``--help`` in this order
    essentials: ClassVar[tuple[str, ...]] = ("problem", "problem_args", "output", "plot",
                                             "backend", "workers")
    #: command lines ``--help`` shows as examples (each one a valid run)
    examples: ClassVar[tuple[str, ...]] = ()
    #: the ``--help`` heading of the scheme's own solver options
    solver_group: ClassVar[str] = "solver"

    def validate(self, given: frozenset[str]) -> None:
        """Cross-checks of the options (``given``: the keys set explicitly); raise ValueError
        with a one-line message naming the option."""
        if is_reference(self.problem) and not REFERENCE.match(self.problem):
            raise ValueError(f"--problem {self.problem!r}: expected a built-in name or "
                             "package.module:factory (Python names separated by dots, one "
                             "colon)")
        if self.problem_args and not is_reference(self.problem):
            raise ValueError(f"--problem-arg only applies to --problem package.module:factory, "
                             f"not the built-in {self.problem}")

    def check_problem(self, problem: Any) -> None:
        """Checks of the options against the loaded problem (ValueError, one line)."""

    def build_example(self) -> Any:  # pragma: no cover - provided by each scheme
        """The built-in example named by ``problem``."""
        raise NotImplementedError

    def describe(self, problem: Any) -> str:  # pragma: no cover - provided by each scheme
        """The first progress line: the problem and the scheme's main options."""
        raise NotImplementedError

    def solve(self, problem: Any, backend: Backend,
              progress: Progress) -> RunResult:  # pragma: no cover - provided by each scheme
        raise NotImplementedError

    def plot(self, problem: Any, result: RunResult,
             out: Path) -> list[Path]:  # pragma: no cover - provided by each scheme
        """Write the scheme's plots into ``out``; returns their paths."""
        raise NotImplementedError

    def plot_names(self, result: RunResult) -> tuple[str, ...]:
        """The file names :meth:`plot` writes for ``result`` (of :attr:`plots`)."""
        return self.plots


def build_parser(scheme: type[SchemeRun],
                 parser_class: type[OneLineParser] = OneLineParser) -> OneLineParser:
    """The scheme's command line, generated from its options dataclass."""
    parser = parser_class(prog=scheme.prog, usage=f"python -m {scheme.prog} [OPTION ...]",
                          description=help_text(scheme.description, scheme.examples),
                          formatter_class=argparse.RawDescriptionHelpFormatter,
                          add_help=False)
    groups = add_options(parser, scheme, first=scheme.essentials,
                         first_title=ESSENTIALS_GROUP,
                         order=(PROBLEM_GROUP, None, OUTPUT_GROUP, BACKEND_GROUP),
                         untitled=scheme.solver_group)
    groups[ESSENTIALS_GROUP].add_argument("-h", "--help", action="help",
                                          help="this help, then exit")
    return parser


def help_text(description: str, examples: Sequence[str]) -> str:
    """The top of a command's ``--help``: its ``description`` and its ``examples`` (command
    lines), wrapped to :data:`HELP_WIDTH` columns (for argparse's
    ``RawDescriptionHelpFormatter``)."""
    lines = textwrap.wrap(description, HELP_WIDTH)
    if examples:
        lines += ["", "examples:"]
        for example in examples:
            lines += textwrap.wrap(example, HELP_WIDTH, initial_indent="  ",
                                   subsequent_indent="      ", break_on_hyphens=False,
                                   break_long_words=False)
    return "\n".join(lines)


def check_options(scheme: type[SchemeRun], argv: Sequence[str]
                  ) -> tuple[SchemeRun, frozenset[str]]:
    """The options of command line ``argv`` and the keys it sets; bad input raises
    ValueError (:class:`~ocpar.cli.UsageError` from the parser) with one line."""
    namespace = build_parser(scheme, CheckingParser).parse_args(argv)
    options, given = options_from_namespace(scheme, namespace)
    options.validate(given)
    return options, given


def parse_options(scheme: type[SchemeRun], argv: Sequence[str] | None = None
                  ) -> tuple[SchemeRun, frozenset[str]]:
    """The options of command line ``argv`` and the keys it sets (exits 2 on bad input)."""
    try:
        return check_options(scheme, sys.argv[1:] if argv is None else argv)
    except ValueError as exc:
        fail(scheme.prog, str(exc))


def explicitly_set(options: SchemeRun) -> frozenset[str]:
    """The keys of ``options`` whose values differ from their defaults."""
    specs = option_specs(type(options))
    return frozenset(key for key, spec in specs.items()
                     if getattr(options, spec.field) != spec.default)


def build_example(options: SchemeRun) -> Any:
    """The built-in example ``options`` name."""
    return options.build_example()


def resolve_problem(options: SchemeRun) -> Any:
    """The problem ``options`` name: a built-in example, or the factory's problem checked
    against the scheme's problem type (ValueError with one line naming the cause)."""
    if is_reference(options.problem):
        return load_problem(options.problem, options.problem_args, options.problem_type)
    return build_example(options)


def checked_problem(options: SchemeRun) -> Any:
    """The problem ``options`` name (:func:`resolve_problem`), checked against the options
    (ValueError with one line naming the cause)."""
    problem = resolve_problem(options)
    options.check_problem(problem)
    return problem


def previous_run_files(options: SchemeRun, out: Path, problem: Any) -> list[Path]:
    """The files of the run whose ``result.json`` is in ``out``, which this run replaces
    (none if there is none): its summary, array file, trace and plots. Another run's (of
    another scheme or problem) raise ValueError (one line) unless ``options.overwrite``."""
    try:
        summary = json.loads((out / "result.json").read_text())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:
        if options.overwrite:
            return [out / "result.json"]
        raise ValueError(f"--output {out}: its result.json is unreadable ({exc}); give "
                         "--overwrite to replace it, or another directory") from None
    summary = summary if isinstance(summary, dict) else {}
    scheme, name = summary.get("scheme"), summary.get("problem")
    if (scheme, name) != (options.scheme, getattr(problem, "name", None)) \
            and not options.overwrite:
        raise ValueError(f"--output {out} holds another run's files (a {scheme} run of "
                         f"{name}); give --overwrite to replace them, or another directory")
    plots = scheme_class(scheme).plots if isinstance(scheme, str) and scheme in SCHEMES else ()
    names = ["result.json", summary.get("arrays"), summary.get("trace_file"), *plots]
    return [out / Path(n).name for n in names if isinstance(n, str) and n]


def run_scheme(options: SchemeRun, given: frozenset[str] | None = None,
               kept: Callable[[Any, RunResult], None] | None = None) -> int:
    """Run ``options`` (on MPI, on every rank) and return the exit status; bad input exits 2
    with one line before any worker starts. ``kept(problem, result)`` is called once the
    result files are written (e.g. to draw the plots later: ``ocpar serve``)."""
    prog = options.prog
    started, entered = process_age(), time.perf_counter()
    given = explicitly_set(options) if given is None else given
    try:
        options.validate(given)
    except ValueError as exc:
        fail(prog, str(exc))
    choose_backend(options, prog)
    out = prepare_output_dir(options.output, prog)
    try:
        problem = checked_problem(options)
        previous = [] if out is None else previous_run_files(options, out, problem)
    except (ProblemReferenceError, ValueError) as exc:
        fail(prog, str(exc))
    built: list[float] = []
    said: list[Progress] = []

    def solve(backend: Backend, say: Progress) -> RunResult:
        built.append(time.perf_counter() - entered)
        said.append(say)
        if out is not None and options.picture != "none" and spare_core(backend.workers):
            warm_up()   # Matplotlib imported on a core the solve leaves idle
        say(f"{prog}: {options.describe(problem)}, backend {backend.name} with "
            f"{backend.workers} worker(s)")
        return options.solve(problem, backend, say)

    result = run_on_backend(options, prog, solve)
    if result is None:  # an MPI rank other than the coordinator's
        return 0
    # the scheme's own build (e.g. the workers' inner solvers) with the driver's
    result.timings |= {"build_s": built[0] + result.timings.get("build_s", 0.0)} | (
        {} if started is None else {"startup_s": started})
    print(result.summary(), flush=True)
    if out is not None:
        written = write_result(result, out)
        if kept is not None:
            kept(problem, result)
        if options.picture != "none":
            drawing = time.perf_counter()
            written += options.plot(problem, result, out)
            result.timings["picture_s"] = time.perf_counter() - drawing
        if (age := process_age()) is not None:
            result.timings["total_s"] = age
        write_timings(result, out)   # the summary written above, with the plots' time
        for stale in set(previous) - {out / "result.json", *written}:
            stale.unlink(missing_ok=True)  # the previous run's, which this one did not write
        print("wrote " + ", ".join(str(p) for p in written), flush=True)
    said[0](timings_line(result.all_timings()))
    return result.exit_status


def spare_core(busy: int) -> bool:
    """Whether a core stays idle while ``busy`` processes of this run compute: the cores this
    process may run on hold more than ``busy`` plus the machine's other runnable threads now
    (Linux's ``/proc/loadavg``, this thread counted among ``busy``); False where the system
    does not say."""
    try:
        cores = len(os.sched_getaffinity(0))
        with open("/proc/loadavg") as loadavg:
            running = int(loadavg.read().split()[3].split("/")[0])
    except (OSError, AttributeError, ValueError, IndexError):
        return False
    return cores > busy + max(running - 1, 0)


def main(scheme: type[SchemeRun], argv: Sequence[str] | None = None) -> int:
    """A scheme's command line: parse ``argv`` and run."""
    freeze_objects_at_exit()
    try:
        with one_line_warnings(scheme.prog):
            options, given = parse_options(scheme, argv)
            return run_scheme(options, given)
    except KeyboardInterrupt:  # outside the supersteps (there: run_on_backend says more)
        interrupted(scheme.prog)
