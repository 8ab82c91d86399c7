"""Run the tutorials' code and commands and check (or rewrite) the outputs they show.

Each tutorial (docs/tutorials/{formation,pursuit,macs,own-dynamics}.md) is read as the user
reads it: a fenced block named just before it (``Save this as `mytut/x.py`:``,
`` `x.toml`:``) or run by the next block (``python x.py``) is a file, written into a fresh
directory (with ``mytut/__init__.py``, as the set-up makes it); every ``bash`` block is a
command, run in that directory in one ``bash`` process per tutorial (so ``JOB=$(...)`` and
``export`` carry on, as in the user's shell); the fenced block after a command (after
"prints", or right after it) is what the command shows, compared line by line: words
exactly, numbers to ``RTOL`` relative (``ATOL`` absolute, for round-off such as a residual
of 6e-17), the wall time, memory, dates and job ids not at all.

Steps 4–6 (``mpirun``, a Dask cluster, detached jobs) need an MPI launcher and the cluster
of docs/tutorials/index.md (started and stopped by the set-up's own commands): they run with
``--cluster`` only (the slow test)::

    python scripts/tutorials.py                 # steps 1–3, 7, 8; exit 1 on a mismatch
    python scripts/tutorials.py pursuit --cluster   # every step of one tutorial
    python scripts/tutorials.py --update        # rewrite the shown outputs from this run
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs" / "tutorials"
TUTORIALS = ("formation", "pursuit", "macs", "own-dynamics")
#: Relative and absolute tolerance of a number shown against the run's (bit-for-bit results
#: differ in the last digits between machines and BLAS builds; residuals are round-off).
RTOL, ATOL = 1e-9, 1e-12
#: What a command's output holds that differs from run to run: replaced by ``…``.
VOLATILE = (
    (re.compile(r"wall time \d+\.\d+ s"), "wall time … s"),
    (re.compile(r"peak memory per worker \d+ MiB"), "peak memory per worker … MiB"),
    (re.compile(r"\b(formation|pursuit|macs)-\d{8}-\d{6}-[0-9a-f]{6}\b"), r"\1-JOB"),
    (re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d"), "DATE"),
    (re.compile(r"/\S*/jobs/"), "…/jobs/"),
    (re.compile(r"timings: .*"), "timings: …"),
)
#: Lines of a run's output that a tutorial does not show (log lines of Dask's processes).
NOISE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+ - |\S+Warning: |  warnings\.warn\()")
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
FENCE = re.compile(r"^```(\w*)\n(.*?)^```\n", re.S | re.M)
#: A command that needs ``--cluster``: an MPI launch, or anything that talks to the set-up's
#: Dask scheduler.
CLUSTER_COMMAND = re.compile(r"\bmpirun\b|--scheduler|\bocpar (submit|status|result|jobs|cancel)\b"
                             r"|tcp://127\.0\.0\.1:8786")
MARK = "@@@ tutorial command"
EXIT_MARK = "@@@ exit status"


@dataclass
class Command:
    """A ``bash`` block of a tutorial, the section it is in, and what the page shows it
    printing (None where it shows nothing); ``shown_at``: the shown block's offsets."""

    text: str
    section: str
    shown: str | None = None
    shown_at: tuple[int, int] | None = None

    @property
    def needs_cluster(self) -> bool:
        return bool(CLUSTER_COMMAND.search(self.text))


@dataclass
class Tutorial:
    """A tutorial page's files (name → text) and commands, in order."""

    path: Path
    files: dict[str, str] = field(default_factory=dict)
    commands: list[Command] = field(default_factory=list)


@dataclass
class Run:
    """A command as run: its output (stdout and stderr), exit status (of its last command;
    None if it did not end) and how long it took (s)."""

    command: Command
    printed: str
    exit_status: int | None
    seconds: float


def read_tutorial(path: Path) -> Tutorial:
    """The files and commands of the tutorial page ``path`` (see the module docstring)."""
    text = path.read_text()
    tutorial = Tutorial(path)
    blocks, end = [], 0
    for match in FENCE.finditer(text):
        blocks.append((text[end:match.start()], match.group(1), match.group(2), match.span(2)))
        end = match.end()
    section = ""
    for i, (before, lang, body, _span) in enumerate(blocks):
        headings = re.findall(r"^## (.*)$", before, re.M)
        section = headings[-1] if headings else section
        if lang in ("python", "toml"):
            named = re.search(r"`([\w/.-]+\.(?:py|toml))`:\s*$", before)
            run_next = (re.match(r"python (\S+\.py)\s*$", blocks[i + 1][2])
                        if i + 1 < len(blocks) and blocks[i + 1][1] == "bash" else None)
            name = named.group(1) if named else run_next.group(1) if run_next else None
            if name is None:
                raise ValueError(f"{path}: a {lang} block in {section!r} has no file name")
            tutorial.files[name] = body
        elif lang == "bash":
            command = Command(body, section)
            if i + 1 < len(blocks) and blocks[i + 1][1] == "":
                following = blocks[i + 1][0].strip()
                if following in ("", "prints") or following.endswith(("e.g.", ":")):
                    command.shown, command.shown_at = blocks[i + 1][2], blocks[i + 1][3]
            tutorial.commands.append(command)
    return tutorial


def setup_commands() -> list[str]:
    """The set-up's commands (docs/tutorials/index.md), less its ``mkdir``/``cd`` (the
    directory is made here): the cluster's start, and its stop."""
    commands = read_tutorial(DOCS / "index.md").commands
    return [c.text for c in commands if not c.text.startswith("mkdir")]


def script(tutorial: Tutorial, cluster: bool, port: int = 8786) -> tuple[str, list[Command]]:
    """One bash script of the tutorial's commands (those that need a cluster only with
    ``cluster``, between the set-up's start and stop of it, its scheduler on ``port``
    instead of the pages' 8786), each after a marker line."""
    commands = [c for c in tutorial.commands if cluster or not c.needs_cluster]
    lines = ["set -u"]
    start, stop = setup_commands()[-2:] if cluster else ("", "")
    if cluster:
        lines.append(start)
    for i, command in enumerate(commands):
        lines += [f"echo '{MARK} {i}' $(date +%s.%N)", command.text.rstrip("\n"),
                  f"echo '{EXIT_MARK}' $?"]
    if cluster:
        lines += [f"echo '{MARK} end' $(date +%s.%N)", stop, "wait"]
    return "\n".join(lines).replace(":8786", f":{port}").replace("--port 8786",
                                                                  f"--port {port}") + "\n", commands


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def run_tutorial(name: str, directory: Path, cluster: bool = False,
                 timeout_s: float = 600) -> list[Run]:
    """Write tutorial ``name``'s files into ``directory`` and run its commands there in one
    bash process (with ``cluster`` also steps 4–6, on a cluster of the set-up's commands on
    a free port); each command as run."""
    tutorial = read_tutorial(DOCS / f"{name}.md")
    (directory / "mytut").mkdir(parents=True, exist_ok=True)
    (directory / "mytut" / "__init__.py").touch()
    for file, text in tutorial.files.items():
        (directory / file).write_text(text)
    text, commands = script(tutorial, cluster, free_port() if cluster else 8786)
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(directory), str(REPO / "src")]
                                          + ([os.environ["PYTHONPATH"]]
                                             if os.environ.get("PYTHONPATH") else [])),
               PATH=os.pathsep.join([str(Path(sys.executable).parent), os.environ["PATH"]]))
    done = subprocess.run(["bash", "-c", text], cwd=directory, env=env, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout_s)
    parts = re.split(rf"^{MARK} (\S+) (\S+)\n", done.stdout + f"{MARK} done {time.time()}\n",
                     flags=re.M)
    outputs = dict(zip(parts[1::3], parts[3::3], strict=True))
    started = [float(t) for t in parts[2::3]]
    durations = dict(zip(parts[1::3], [b - a for a, b in itertools.pairwise(started)],
                         strict=False))
    runs = []
    for i, command in enumerate(commands):
        printed, _, status = outputs.get(str(i), "").rpartition(f"{EXIT_MARK} ")
        if not _:  # it did not end: killed by the time-out
            printed, status = outputs.get(str(i), ""), ""
        runs.append(Run(command, printed, int(status) if status.strip().isdigit() else None,
                        durations.get(str(i), math.nan)))
    return runs


def normalised(text: str) -> list[str]:
    """``text``'s lines with the volatile parts masked, Dask's log lines left out."""
    lines = []
    for line in text.rstrip("\n").split("\n"):
        if NOISE.match(line):
            continue
        for pattern, replacement in VOLATILE:
            line = pattern.sub(replacement, line)
        lines.append(line.rstrip())
    return lines


def differences(shown: str, printed: str) -> list[str]:
    """Where ``printed`` differs from ``shown`` (empty if it matches): words exactly,
    numbers to ``RTOL``/``ATOL``."""
    want, got = normalised(shown), normalised(printed)
    if len(want) != len(got):
        return [f"{len(got)} lines printed, {len(want)} shown:\n" + "\n".join(got)]
    found = []
    for a, b in zip(want, got, strict=True):
        if NUMBER.split(a) != NUMBER.split(b) or len(NUMBER.findall(a)) != len(NUMBER.findall(b)):
            found.append(f"shown   {a}\nprinted {b}")
            continue
        for x, y in zip(NUMBER.findall(a), NUMBER.findall(b), strict=True):
            if not math.isclose(float(x), float(y), rel_tol=RTOL, abs_tol=ATOL):
                found.append(f"shown   {a}\nprinted {b}   ({x} != {y})")
                break
    return found


def update(name: str, results: list[Run]) -> int:
    """Replace the outputs tutorial ``name`` shows by those of ``results``; how many."""
    path = DOCS / f"{name}.md"
    text = path.read_text()
    changed = 0
    for run in sorted(results, key=lambda r: -(r.command.shown_at or (0, 0))[0]):
        command, printed = run.command, run.printed
        if command.shown_at is None or not differences(command.shown, printed):
            continue
        start, end = command.shown_at
        body = "\n".join(line for line in printed.rstrip("\n").split("\n")
                         if not NOISE.match(line)) + "\n"
        text = text[:start] + body + text[end:]
        changed += 1
    path.write_text(text)
    return changed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tutorials", nargs="*", metavar="TUTORIAL",
                        help=f"{', '.join(TUTORIALS)} (default: all)")
    parser.add_argument("--cluster", action="store_true",
                        help="also steps 4-6: mpirun, a local Dask cluster, detached jobs")
    parser.add_argument("--update", action="store_true",
                        help="rewrite the outputs shown from this run's")
    args = parser.parse_args(argv)
    if unknown := set(args.tutorials) - set(TUTORIALS):
        parser.error(f"no tutorial {sorted(unknown)[0]!r}; choose from {', '.join(TUTORIALS)}")
    failed = 0
    for name in args.tutorials or TUTORIALS:
        directory = Path(tempfile.mkdtemp(prefix=f"ocpar-tutorial-{name}-"))
        try:
            results = run_tutorial(name, directory, cluster=args.cluster)
        finally:
            shutil.rmtree(directory, ignore_errors=True)
        for run in results:
            command = run.command
            print(f"{name}.md, {command.section}: {run.seconds:5.1f} s  "
                  f"{command.text.strip().splitlines()[0][:80]}", file=sys.stderr)
            found = differences(command.shown, run.printed) if command.shown is not None else []
            if run.exit_status != 0:
                found.append(f"exit status {run.exit_status}:\n{run.printed}")
            failed += bool(found)
            for difference in found:
                print(f"{name}.md, {command.section}: {command.text.strip()}\n{difference}")
        if args.update:
            print(f"{name}.md: {update(name, results)} output(s) rewritten")
    return 1 if failed and not args.update else 0


if __name__ == "__main__":
    sys.exit(main())
