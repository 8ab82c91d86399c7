"""Shared pieces of the command lines: one-line errors, backend options, output directories."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn, TypeVar

from ocpar.bsp import (
    BACKENDS,
    BALANCE_POLICIES,
    Backend,
    BackendError,
    launched_by_mpirun,
    open_backend,
)

EXIT_USAGE = 2
R = TypeVar("R")
Progress = Callable[[str], None]


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports bad input as one line on stderr and exits with status 2."""

    def error(self, message: str) -> NoReturn:
        fail(self.prog, message)


def fail(prog: str, message: str) -> NoReturn:
    """Print ``prog: error: message`` (one line; under mpirun from rank 0 only) and exit 2."""
    rank = os.environ.get("PMI_RANK", os.environ.get("OMPI_COMM_WORLD_RANK", "0"))
    if rank == "0":
        print(f"{prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    sys.exit(EXIT_USAGE)


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text}")
    return value


def add_backend_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("parallel backend")
    group.add_argument("--backend", choices=BACKENDS, default=None,
                       help="serial (default), mpi (implied under mpirun), dask, or dask-mpi "
                            "(under mpirun -n P: a Dask cluster of P - 2 workers)")
    group.add_argument("--workers", type=positive_int, default=None,
                       help="number of workers (dask: local worker processes, or how many of "
                            "the cluster's workers to use; mpi: must equal the rank count)")
    group.add_argument("--scheduler", default=None, metavar="ADDR",
                       help="address of an existing Dask scheduler, e.g. tcp://HOST:8786")
    group.add_argument("--balance", choices=BALANCE_POLICIES, default="blocks",
                       help="task assignment: contiguous blocks (default), or lpt: longest "
                            "first on the previous superstep's times, tasks kept on their "
                            "worker where that does not hurt the balance")


def choose_backend(args: argparse.Namespace, prog: str) -> str:
    """The backend the arguments ask for, checked for consistency (exits 2 if not)."""
    under_mpi = launched_by_mpirun()
    backend = args.backend or ("mpi" if under_mpi else "dask" if args.scheduler else "serial")
    if backend == "mpi" and not under_mpi:
        fail(prog, "--backend mpi needs an MPI launcher: mpirun -n P python -m ...")
    if backend == "dask-mpi" and not under_mpi:
        fail(prog, "--backend dask-mpi needs an MPI launcher: mpirun -n P python -m ...")
    if under_mpi and backend not in ("mpi", "dask-mpi"):
        fail(prog, f"under mpirun the backend is mpi or dask-mpi, not {backend}")
    if args.scheduler is not None:
        if backend != "dask":
            fail(prog, "--scheduler only applies to --backend dask")
        if not args.scheduler.strip() or "://" not in args.scheduler:
            fail(prog, f"--scheduler must look like tcp://HOST:PORT, got {args.scheduler!r}")
    if backend == "serial" and args.workers not in (None, 1):
        fail(prog, "the serial backend has exactly 1 worker")
    return backend


def start_backend(args: argparse.Namespace, backend_name: str, prog: str) -> Backend:
    """Open the backend or exit 2 with a one-line message (e.g. unreachable scheduler)."""
    try:
        return open_backend(backend_name, workers=args.workers, scheduler=args.scheduler,
                            balance=args.balance)
    except BackendError as exc:
        fail(prog, str(exc))


def prepare_output_dir(path: str | None, prog: str) -> Path | None:
    """Create ``path`` if needed and check it is a writable directory (exits 2 if not)."""
    if path is None:
        return None
    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".ocpar-write-test-"):
            pass
    except OSError as exc:
        fail(prog, f"output directory {out} is not writable: {exc.strerror or exc}")
    if not os.access(out, os.W_OK):
        fail(prog, f"output directory {out} is not writable")
    return out


def run_on_backend(
    args: argparse.Namespace, prog: str, body: Callable[[Backend, Progress], R]
) -> R | None:
    """Start the backend the arguments ask for and run ``body(backend, progress)`` in the
    coordinator; other MPI ranks serve supersteps instead and get None. ``progress`` prints a
    line unless ``--quiet``."""
    name = choose_backend(args, prog)
    with start_backend(args, name, prog) as backend:
        if not backend.is_coordinator:
            backend.serve()
            return None
        if getattr(args, "quiet", False):
            return body(backend, lambda line: None)
        if link := getattr(backend, "dashboard_link", None):
            print(f"Dask dashboard: {link}", flush=True)
        return body(backend, lambda line: print(line, flush=True))
