"""Property-based tests of the three command lines: malformed options and configurations get
exit status 2 and one line ``PROG: error: ...`` on stderr, never a traceback, and are refused
before any problem is built, backend started or solve run.

``main(argv)`` runs in-process with the problem builders, ``run_on_backend`` and the solve
functions replaced by a guard that fails the test if called; one subprocess test per command
line checks that the real ``python -m ...`` behaves the same.
"""

from __future__ import annotations

import importlib
from types import SimpleNamespace

import pytest
from conftest import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ocpar import driver
from ocpar.config import scheme_class
from ocpar.formation.solve import MODES, ORDERINGS, OUTER_SOLVERS
from ocpar.macs.algorithm import MAX_POPULATION

SCHEMES = {scheme: scheme_class(scheme) for scheme in ("formation", "pursuit", "macs")}
#: Each scheme's options module (its limits) beside the names it takes choices from.
FORMATION = SimpleNamespace(**vars(importlib.import_module("ocpar.formation.run")),
                            MODES=MODES, OUTER_SOLVERS=OUTER_SOLVERS, ORDERINGS=ORDERINGS)
PURSUIT = importlib.import_module("ocpar.pursuit.run")
MACS = SimpleNamespace(**vars(importlib.import_module("ocpar.macs.run")),
                       MAX_POPULATION=MAX_POPULATION)
#: What must not run for a malformed command line: building a built-in example (a reference
#: is loaded, and refused with one line, before anything starts), the backend and the solve.
GUARDED = ("build_example", "run_on_backend")

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture
def guarded(monkeypatch):
    """The schemes' options classes, with everything after validation replaced by a failing
    guard."""
    for name in GUARDED:
        monkeypatch.setattr(driver, name, _guard(name))
    return SCHEMES


def _guard(name: str):
    def called(*args, **kwargs):
        raise AssertionError(f"{name} called: the input passed validation")
    return called


def assert_refused(scheme: type, argv: list[str], capsys) -> str:
    """Run the scheme's command line on ``argv``: exit status 2, nothing on stdout, exactly
    one non-empty line ``PROG: error: ...`` on stderr and no traceback. Returns that line."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        driver.main(scheme, argv)
    out, err = capsys.readouterr()
    assert exc.value.code == 2, (argv, exc.value.code, err)
    assert out == "", (argv, out)
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), (argv, err)
    assert lines[0].startswith(f"{scheme.prog}: error: "), (argv, err)
    assert lines[0].strip() != f"{scheme.prog}: error:", (argv, err)
    assert "Traceback (most recent call last)" not in err, (argv, err)
    return lines[0]


# -- values ----------------------------------------------------------------------------------


def _fails(convert):
    def check(text: str) -> bool:
        try:
            convert(text)
        except ValueError:
            return True
        return False
    return check


INT_JUNK = ["", " ", "nan", "NaN", "inf", "-inf", "2.5", "3.0", "1e3", "0x10", "ten", "1,000",
            "2 3", "½", "None", "true", "+", "9" * 5000]
FLOAT_JUNK = ["", " ", "nan", "NaN", "-nan", "inf", "-inf", "+inf", "Infinity", "1e309",
              "-1e309", "0x1p3", "1,5", "1/2", "ten", "None", "e", "."]
ZEROS = ["0", "-0", "+0", "00", "0_0"]
#: Finite floats as text (repr), never an integer literal.
float_texts = st.floats(allow_nan=True, allow_infinity=True).map(repr)


def not_an_int() -> st.SearchStrategy[str]:
    return st.one_of(st.sampled_from(INT_JUNK), float_texts,
                     st.text(max_size=12).filter(_fails(int)))


def bad_int(positive: bool = True) -> st.SearchStrategy[str]:
    """Text that an integer option with a lower bound (1, or 0 without ``positive``) refuses."""
    negative = st.integers(max_value=-1).map(str)
    return st.one_of(not_an_int(), negative, *([st.sampled_from(ZEROS)] if positive else []))


def bad_float() -> st.SearchStrategy[str]:
    """Text that a positive number option refuses: junk, NaN, ±inf, zero, negatives."""
    return st.one_of(st.sampled_from(FLOAT_JUNK + ZEROS + ["0.0", "-0.0"]),
                     st.text(max_size=12).filter(_fails(float)),
                     st.floats(max_value=0.0, allow_nan=False).map(repr))


def ints(low: int, high: int) -> st.SearchStrategy[str]:
    return st.integers(low, high).map(str)


def floats(low: float, high: float) -> st.SearchStrategy[str]:
    return st.floats(low, high, allow_nan=False, allow_infinity=False).map(repr)


def bad_choice(choices) -> st.SearchStrategy[str]:
    allowed = {str(c) for c in choices}
    return st.one_of(st.sampled_from(["", " ", "SERIAL", "none", "0", "3", "-1"]),
                     st.text(max_size=12)).filter(lambda s: s not in allowed)


# -- pieces of a command line ------------------------------------------------------------------
# A piece is (tokens, option names it sets). A command line is one malformed piece plus a few
# valid context pieces that set none of its options, in any order.

Piece = tuple[list[str], frozenset[str]]


def option(name: str, values: st.SearchStrategy[str]) -> st.SearchStrategy[Piece]:
    """``--name VALUE`` or ``--name=VALUE`` (the only way to pass a value starting with -)."""
    return st.builds(
        lambda value, joined: ([f"{name}={value}"] if joined or value.startswith("-")
                               else [name, value], frozenset([name])),
        values, st.booleans())


def together(*pieces: st.SearchStrategy[Piece]) -> st.SearchStrategy[Piece]:
    """Several options given together (an inconsistent combination)."""
    return st.tuples(*pieces).map(lambda ps: ([t for p in ps for t in p[0]],
                                              frozenset().union(*(p[1] for p in ps))))


def flag(name: str) -> st.SearchStrategy[Piece]:
    return st.just(([name], frozenset([name])))


def fixed(name: str, value: str) -> st.SearchStrategy[Piece]:
    return st.just(([name, value], frozenset([name])))


def unknown() -> st.SearchStrategy[Piece]:
    """Unknown options (never a prefix of a real one), stray words and options with their
    value missing."""
    slug = st.from_regex(r"[a-z0-9][a-z0-9_-]{0,12}", fullmatch=True)
    flags = st.one_of(
        slug.map(lambda s: f"--no-such-{s}"),
        st.builds(lambda s, v: f"--no-such-{s}={v}", slug, st.text(max_size=8)),
        st.sampled_from(["-x", "-Z", "-1x", "---quiet", "-agents", "-quiet", "--QUIET",
                         "--quiet-", "--mode-", "--radius_", "--backend-name", "—quiet"]),
    )
    words = st.text(max_size=12).filter(lambda s: not s.startswith("-"))
    return st.one_of(flags, words).map(lambda t: ([t], frozenset()))


def missing_value(names: list[str]) -> st.SearchStrategy[Piece]:
    return st.sampled_from(names).map(lambda n: ([n], frozenset([n])))


BACKEND_NAMES = frozenset(["--backend", "--workers", "--scheduler"])
BACKEND_CONTEXT = [fixed("--backend", "serial"), fixed("--workers", "1"),
                   option("--balance", st.sampled_from(["blocks", "lpt"])), flag("--quiet")]
no_scheme = st.text(max_size=20).filter(lambda a: "://" not in a)


def backend_errors() -> st.SearchStrategy[Piece]:
    """Bad backend options, the same for the three command lines (checked by cli.py)."""
    many = ints(2, 10**30)
    return st.one_of(
        option("--workers", bad_int()),
        option("--workers", many),  # the serial default has exactly 1 worker
        together(fixed("--backend", "serial"), option("--workers", many)),
        option("--backend", bad_choice(["serial", "mpi", "dask", "dask-mpi"])),
        option("--backend", st.sampled_from(["mpi", "dask-mpi"])),  # not under mpirun
        option("--balance", bad_choice(["blocks", "lpt"])),
        option("--scheduler", no_scheme),  # implies dask: must look like tcp://HOST:PORT
        together(option("--backend", st.sampled_from(["serial", "mpi", "dask-mpi"])),
                 option("--scheduler", st.just("tcp://127.0.0.1:8786"))),
        together(fixed("--backend", "dask"),
                 option("--scheduler", no_scheme)),
    ).map(lambda p: (p[0], p[1] | BACKEND_NAMES))


@st.composite
def command_line(draw, malformed: st.SearchStrategy[Piece],
                 context: list[st.SearchStrategy[Piece]]) -> list[str]:
    bad_tokens, bad_names = draw(malformed)
    pieces, used = [bad_tokens], set(bad_names)
    for tokens, names in draw(st.lists(st.one_of(context), max_size=4)):
        if not names & used:
            pieces.append(tokens)
            used |= names
    return [t for piece in draw(st.permutations(pieces)) for t in piece]


# -- formation -------------------------------------------------------------------------------

FORMATION_CONTEXT = [
    option("--problem", st.sampled_from(["point-mass-plane", "crtbp-rigid"])),
    option("--agents", ints(2, 60)),
    option("--radius", floats(0.5, 50.0)),
    fixed("--mode", "hierarchical"),
    option("--outer", st.sampled_from(["sqp", "offset"])),
    option("--ordering", st.sampled_from(["keep", "optimal"])),
    *BACKEND_CONTEXT,
]


def radius_out_of_range() -> st.SearchStrategy[Piece]:
    """A finite positive radius outside the problem's range (FORMATION.RADIUS_RANGE around
    its default)."""
    def piece(problem: str) -> st.SearchStrategy[Piece]:
        default = FORMATION.EXAMPLES[problem].radius
        low, high = default / FORMATION.RADIUS_RANGE, default * FORMATION.RADIUS_RANGE
        radius = st.one_of(floats(high * 1.0001, 1.7e308), floats(5e-324, low * 0.9999))
        return together(fixed("--problem", problem), option("--radius", radius))
    return st.sampled_from(sorted(FORMATION.EXAMPLES)).flatmap(piece)


FORMATION_ERRORS = st.one_of(
    option("--agents", bad_int()),
    option("--agents", st.just("1")),
    option("--agents", ints(FORMATION.MAX_AGENTS + 1, 10**40)),
    together(fixed("--ordering", "optimal"),
             option("--agents", ints(FORMATION.MAX_OPTIMAL_ORDERING_AGENTS + 1,
                                     FORMATION.MAX_AGENTS))),
    option("--radius", bad_float()),
    radius_out_of_range(),
    option("--problem", bad_choice(FORMATION.EXAMPLES)),
    option("--mode", bad_choice(FORMATION.MODES)),
    option("--outer", bad_choice(FORMATION.OUTER_SOLVERS)),
    option("--ordering", bad_choice(FORMATION.ORDERINGS)),
    together(fixed("--mode", "monolithic"),
             option("--outer", st.sampled_from(FORMATION.OUTER_SOLVERS))),
    st.text(max_size=4).map(lambda v: ([f"--quiet={v}"], frozenset(["--quiet"]))),
    missing_value(["--problem", "--agents", "--radius", "--mode", "--outer", "--ordering",
                   "--backend", "--workers", "--scheduler", "--balance", "--output"]),
    unknown(),
    backend_errors(),
)

# -- pursuit ---------------------------------------------------------------------------------

PURSUIT_CONTEXT = [
    option("--case", st.sampled_from(["1", "2"])),
    fixed("--mode", "pbms"),
    option("--epsilon", floats(1e-12, 1.0)),
    option("--max-agents", ints(2, 10**6)),
    flag("--no-reference"),
    *BACKEND_CONTEXT,
]


@st.composite
def inconsistent_window(draw) -> Piece:
    """N, N_Δ, N_δ breaking 1 <= N_δ < N_Δ < N (each within its own type's range)."""
    samples = draw(st.integers(3, 2001))
    if draw(st.booleans()):
        window = draw(st.integers(samples, 10**9))
        update = draw(st.integers(1, 10**9))
    else:
        window = draw(st.integers(1, samples - 1))
        update = draw(st.integers(max(window, 1), 10**9))
    tokens = ["--samples", str(samples), "--window", str(window), "--update", str(update)]
    return tokens, frozenset(["--samples", "--window", "--update"])


PURSUIT_ERRORS = st.one_of(
    option("--samples", bad_int()),
    option("--samples", ints(1, 2)),
    option("--samples", ints(PURSUIT.MAX_SAMPLES + 1, 10**40)),
    option("--window", bad_int()),
    option("--window", st.one_of(ints(1, 32), ints(301, 10**30))),  # update 32, samples 301
    option("--update", bad_int()),
    option("--update", ints(60, 10**30)),  # window 60
    inconsistent_window(),
    option("--epsilon", bad_float()),
    option("--max-agents", bad_int()),
    option("--max-agents", st.just("1")),
    option("--case", st.one_of(not_an_int(), st.integers().filter(lambda c: c not in (1, 2))
                               .map(str))),
    option("--mode", bad_choice(PURSUIT.MODES)),
    together(fixed("--mode", "ms"), flag("--no-reference")),
    missing_value(["--case", "--samples", "--window", "--update", "--mode", "--epsilon",
                   "--max-agents", "--backend", "--workers", "--output"]),
    unknown(),
    backend_errors(),
)

# -- macs ------------------------------------------------------------------------------------

MACS_CONTEXT = [
    option("--problem", st.sampled_from(["goddard", "orbit-raising"])),
    option("--seed", ints(0, 10**40)),
    option("--archive", ints(2, 10**6)),
    *BACKEND_CONTEXT,
]


@st.composite
def budget_too_small(draw) -> Piece:
    """--max-evals at most --population: initialisation alone uses up the budget."""
    population = draw(st.integers(4, MACS.MAX_POPULATION))
    evals = draw(st.integers(1, population))
    return (["--population", str(population), "--max-evals", str(evals)],
            frozenset(["--population", "--max-evals"]))


MACS_ERRORS = st.one_of(
    option("--seed", bad_int(positive=False)),
    option("--max-evals", bad_int()),
    option("--max-evals", ints(1, 10)),  # population 10
    option("--archive", bad_int()),
    option("--archive", st.just("1")),
    option("--population", bad_int()),
    option("--population", ints(1, 3)),
    together(option("--population", ints(MACS.MAX_POPULATION + 1, 10**30)),
             fixed("--max-evals", str(10**31))),
    budget_too_small(),
    option("--problem", bad_choice(MACS.PROBLEMS)),
    missing_value(["--problem", "--seed", "--max-evals", "--archive", "--population",
                   "--backend", "--workers", "--output"]),
    unknown(),
    backend_errors(),
)

COMMAND_LINES = {
    "formation": command_line(FORMATION_ERRORS, FORMATION_CONTEXT),
    "pursuit": command_line(PURSUIT_ERRORS, PURSUIT_CONTEXT),
    "macs": command_line(MACS_ERRORS, MACS_CONTEXT),
}


@pytest.mark.parametrize("scheme", sorted(COMMAND_LINES))
@FUZZ
@given(data=st.data())
def test_malformed_command_lines_are_refused(scheme, data, guarded, capsys):
    argv = data.draw(COMMAND_LINES[scheme], label="argv")
    assert_refused(guarded[scheme], argv, capsys)


@pytest.mark.parametrize(
    ("scheme", "argv", "needle"),
    [
        # the gaps this suite found, one example each
        ("formation", ["--agents", "99999999999999999999"], "--agents"),
        ("formation", ["--radius", "1e300"], "--radius"),
        ("formation", ["--radius", "1e-300"], "--radius"),
        ("formation", ["--problem", "crtbp-rigid", "--radius", "2e6"], "--radius"),
        ("formation", ["--mode", "monolithic", "--outer", "offset"], "--outer"),
        ("formation", ["--ordering", "optimal", "--agents", "5000"], "--ordering"),
        ("pursuit", ["--samples", "99999999999999999999"], "--samples"),
        ("pursuit", ["--mode", "ms", "--no-reference"], "--no-reference"),
        ("macs", ["--max-evals", "10"], "--max-evals"),
        ("macs", ["--population", "20", "--max-evals", "15"], "--max-evals"),
        ("macs", ["--population", "99999999999999", "--max-evals", "999999999999999"],
         "--population"),
        # already refused before; kept as regression examples
        ("formation", ["--agents", "1"], "--agents"),
        ("formation", ["--radius", "nan"], "--radius"),
        ("formation", ["--radius=-inf"], "--radius"),
        ("pursuit", ["--samples", "50"], "N_Δ"),
        ("pursuit", ["--window", "20", "--update", "20"], "N_δ"),
        ("macs", ["--population", "3"], "population"),
        ("macs", ["--seed", "1.5"], "--seed"),
    ],
)
def test_examples_are_refused(scheme, argv, needle, guarded, capsys):
    assert needle in assert_refused(guarded[scheme], argv, capsys)


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_output_that_is_a_file_is_refused(scheme, guarded, capsys, tmp_path):
    blocker = tmp_path / "result.json"
    blocker.write_text("a file, not a directory")
    line = assert_refused(guarded[scheme], ["--output", str(blocker)], capsys)
    assert str(blocker) in line


@pytest.mark.parametrize("scheme", sorted(SCHEMES))
def test_valid_command_lines_reach_the_solver(scheme, guarded, capsys):
    """The guard itself: a valid command line gets past validation (to the guard)."""
    with pytest.raises(AssertionError, match="passed validation"):
        driver.main(guarded[scheme], ["--quiet"])


@pytest.mark.parametrize(
    "argv",
    [
        pytest.param(["--quiet", "--output", ""], id="empty-output-is-cwd"),
        pytest.param(["--backend", "dask", "--scheduler", "tcp://"], id="scheduler-no-host"),
        pytest.param(["--backend", "dask", "--workers", "1000000000"], id="huge-dask-workers"),
        pytest.param(["--problem", "goddard", "--problem", "orbit-raising"],
                     id="option-given-twice"),
        pytest.param(["--max-ev", "2000"], id="abbreviated-option"),
        pytest.param(["--checkpoint", "a", "--resume", "b"], id="checkpoint-and-resume"),
    ],
)
def test_shared_options_refuse_what_argparse_lets_through(argv, guarded, capsys):
    assert_refused(guarded["macs"], argv, capsys)


@pytest.mark.parametrize(
    ("module", "argv", "needle"),
    [
        ("ocpar.formation", ["--radius", "nan", "--agents", "4"], "--radius"),
        ("ocpar.pursuit", ["--samples", "101", "--window", "101"], "N_Δ"),
        ("ocpar.macs", ["--max-evals", "5", "--quiet"], "--max-evals"),
    ],
)
def test_real_process_matches(module, argv, needle):
    proc = run_cli("-m", module, *argv, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"{module}: error: ") and needle in lines[0]
    assert "Traceback" not in proc.stderr
