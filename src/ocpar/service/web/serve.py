"""``ocpar serve``: run the HTTP job API, issue and list its tokens, print its OpenAPI schema.

::

    ocpar serve [--host 127.0.0.1] [--port 8000] [--state-dir DIR] [--backend dask|mpi|serial]
                [--workers N] [--scheduler ADDR] [--max-running N] [--allow-problem PATTERN]
                [--max-job-memory GB|none]
                [--ssl-certfile F --ssl-keyfile F]
    ocpar serve token add NAME [--max-jobs N] [--max-agents N] [--max-evaluations N]
                               [--wall-time S] [--state-dir DIR]   (N, S: a number or none)
    ocpar serve token list [--state-dir DIR]
    ocpar serve token revoke NAME [--state-dir DIR]
    ocpar serve openapi [--output FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from ocpar.cli import fail, positive_int
from ocpar.service.web.store import DEFAULT_LIMITS, DEFAULT_SOLVER_OPTIONS

PROG = "ocpar serve"
#: The state directory (database and jobs) unless --state-dir or $OCPAR_SERVER_DIR says.
DEFAULT_STATE_DIR = "~/.ocpar/server"
STATE_DIR_ENV = "OCPAR_SERVER_DIR"
#: Seconds a stopping server waits for open connections (event streams) to end.
SHUTDOWN_GRACE = 3


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def limit(kind: type) -> Any:
    """An argparse type: a positive ``kind`` (int or float), or ``none`` (unlimited: None)."""
    def parse(text: str) -> Any:
        if text.strip().lower() == "none":
            return None
        return positive_int(text) if kind is int else positive_float(text)
    parse.__name__ = f"positive {kind.__name__} or none"
    return parse


def state_dir(args: argparse.Namespace) -> Path:
    """The state directory the arguments (or the environment) name."""
    return Path(getattr(args, "state_dir", None) or os.environ.get(STATE_DIR_ENV)
                or DEFAULT_STATE_DIR).expanduser()


def register(commands: Any) -> None:
    """Add ``serve`` (with ``token add|list`` and ``openapi``) to the ``ocpar`` subparsers
    ``commands``."""
    from ocpar.service.web.runner import BACKENDS

    parser = commands.add_parser(
        "serve", prog=PROG, help="run the HTTP job API and its page",
        description="Serve the HTTP job API (and the page of jobs at /) on HOST:PORT, running "
        "jobs on an embedded Dask cluster of --workers processes (default), an existing one "
        "(--scheduler), mpirun -n WORKERS (--backend mpi) or serially (--backend serial); "
        "on Dask and serially each job runs in one of --max-running warm processes (imported "
        "once, one job at a time). Jobs and tokens live in --state-dir; jobs left running by "
        "a stopped server resume from their checkpoints when it starts again.")
    add_state_dir(parser, None)
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1: this host only)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    parser.add_argument("--backend", choices=BACKENDS, default="dask",
                        help="where jobs run (default dask: an embedded cluster)")
    parser.add_argument("--workers", type=positive_int, default=2, metavar="N",
                        help="dask: the embedded cluster's worker processes; mpi: ranks per "
                             "job (default 2)")
    parser.add_argument("--scheduler", metavar="ADDR",
                        help="an existing Dask cluster's scheduler (tcp://HOST:PORT) instead "
                             "of the embedded one")
    parser.add_argument("--max-running", type=positive_int, default=2, metavar="N",
                        help="jobs running at once over all tokens (default 2); the rest "
                             "wait, queued")
    parser.add_argument("--allow-problem", action="append", default=[], metavar="PATTERN",
                        help="allow problem references module:factory matching PATTERN "
                             "(fnmatch, e.g. 'mypkg.problems:*'); repeat for more. Built-in "
                             "examples are always allowed")
    parser.add_argument("--allow-solver-option", action="append", default=[],
                        metavar="PATTERN",
                        help="allow jobs to set the solver options SOLVER.NAME matching "
                             "PATTERN (fnmatch, e.g. 'ipopt.*tol'); repeat for more; 'none': "
                             "no solver option. Default: "
                             f"{' '.join(DEFAULT_SOLVER_OPTIONS)}; options that name files "
                             "or libraries on this host (ipopt.output_file, ipopt.hsllib, ...) "
                             "only by their exact name")
    parser.add_argument("--wall-time-grace", type=positive_float, default=30.0, metavar="S",
                        help="seconds a job over its token's wall time has to stop at a "
                             "superstep boundary before it is killed (default 30)")
    parser.add_argument("--max-job-memory", type=limit(float), metavar="GB", default=...,
                        help="refuse (422) a job whose estimated peak memory is above GB "
                             "gigabytes (10^9 bytes; none: no limit; default half of this "
                             "host's memory)")
    parser.add_argument("--ssl-certfile", metavar="FILE", help="serve HTTPS: certificate (PEM)")
    parser.add_argument("--ssl-keyfile", metavar="FILE", help="serve HTTPS: its key (PEM)")
    parser.set_defaults(handler=serve, action=None)
    actions = parser.add_subparsers(dest="action", metavar="ACTION")

    token = actions.add_parser("token", prog=f"{PROG} token",
                               help="issue, list or revoke tokens")
    token_actions = token.add_subparsers(dest="token_action", metavar="add|list|revoke",
                                         required=True)
    add = token_actions.add_parser(
        "add", prog=f"{PROG} token add", help="issue a token (printed once)",
        description="Issue a token named NAME and print it (once: only its SHA-256 hash is "
        "stored). Its jobs are limited as given; each limit not given is the default shown, "
        "and 'none' lifts it.")
    add.add_argument("name", metavar="NAME")
    for flag, kind, meta, text in (
            ("max_jobs", int, "N", "jobs running at once (the rest wait, queued)"),
            ("max_agents", int, "N", "agents per job (formation agents, pursuit max_agents)"),
            ("max_evaluations", int, "N", "MACS evaluations per job (max_evals)"),
            ("wall_time", float, "S", "seconds a job may run; then it is cancelled")):
        add.add_argument("--" + flag.replace("_", "-"), type=limit(kind), metavar=meta,
                         default=DEFAULT_LIMITS[flag],
                         help=f"{text} (default {DEFAULT_LIMITS[flag]:g}; none: unlimited)")
    add.add_argument("--allow-solver-option", action="append", default=[], metavar="PATTERN",
                     help="its jobs may set only the solver options SOLVER.NAME matching "
                          "PATTERN (fnmatch), within the server's --allow-solver-option; "
                          "repeat for more; 'none': no solver option (default: the server's)")
    add_state_dir(add, argparse.SUPPRESS)
    add.set_defaults(handler=token_add)
    listing = token_actions.add_parser("list", prog=f"{PROG} token list",
                                       help="list the tokens and their limits")
    add_state_dir(listing, argparse.SUPPRESS)
    listing.set_defaults(handler=token_list)
    revoking = token_actions.add_parser(
        "revoke", prog=f"{PROG} token revoke", help="revoke a token",
        description="Delete the token named NAME: it authenticates no more, its queued jobs "
        "are cancelled and its running jobs stop at their next superstep boundary (their "
        "files stay). Works while the server runs.")
    revoking.add_argument("name", metavar="NAME")
    add_state_dir(revoking, argparse.SUPPRESS)
    revoking.set_defaults(handler=token_revoke)

    schema = actions.add_parser("openapi", prog=f"{PROG} openapi",
                                help="print the API's OpenAPI schema (JSON)")
    schema.add_argument("--output", metavar="FILE", help="write it to FILE")
    schema.set_defaults(handler=openapi)


def add_state_dir(parser: argparse.ArgumentParser, default: Any) -> None:
    parser.add_argument("--state-dir", default=default, metavar="DIR",
                        help=f"the server's database and jobs (default ${STATE_DIR_ENV} or "
                             f"{DEFAULT_STATE_DIR})")


def serve(args: argparse.Namespace) -> int:
    """Run the server until it is interrupted."""
    import uvicorn

    from ocpar.service.web.app import create_app
    from ocpar.service.web.runner import Settings

    if args.scheduler is not None and args.backend != "dask":
        fail(PROG, "--scheduler only applies to --backend dask")
    if (args.ssl_certfile is None) != (args.ssl_keyfile is None):
        fail(PROG, "--ssl-certfile and --ssl-keyfile go together")
    for path in (args.ssl_certfile, args.ssl_keyfile):
        if path is not None and not os.path.isfile(path):
            fail(PROG, f"{path}: no such file")
    if not 0 <= args.port < 65536:
        fail(PROG, f"--port must be 0 to 65535, got {args.port}")
    from ocpar.service.web.memory import default_limit

    settings = Settings(state_dir=state_dir(args), backend=args.backend, workers=args.workers,
                        scheduler=args.scheduler, max_running=args.max_running,
                        allow_problem=tuple(args.allow_problem), grace=args.wall_time_grace,
                        allow_solver_option=solver_option_patterns(args.allow_solver_option),
                        max_job_memory=memory_limit(args.max_job_memory, default_limit()))
    app = create_app(settings)
    scheme = "https" if args.ssl_certfile else "http"
    host = f"[{args.host}]" if ":" in args.host else args.host
    print(f"{PROG}: {scheme}://{host}:{args.port}/ (jobs in {app.state.store.state_dir}, "
          f"backend {args.backend}{' ' + args.scheduler if args.scheduler else ''})",
          flush=True)
    # open event streams and half-open connections do not hold a stopping server for long
    uvicorn.run(app, host=args.host, port=args.port, ssl_certfile=args.ssl_certfile,
                ssl_keyfile=args.ssl_keyfile, log_level="warning",
                timeout_graceful_shutdown=SHUTDOWN_GRACE)
    return 0


def solver_option_patterns(given: list[str]) -> tuple[str, ...]:
    """The solver options' allow-list of ``--allow-solver-option`` (none given: the default;
    ``none``: no option)."""
    if not given:
        return DEFAULT_SOLVER_OPTIONS
    return () if given == ["none"] else tuple(given)


def memory_limit(gigabytes: Any, default: int) -> int | None:
    """The bytes of ``--max-job-memory GB`` (None: no limit; not given, ``...``:
    ``default``)."""
    if gigabytes is ...:
        return default
    return None if gigabytes is None else int(gigabytes * 1e9)


def token_add(args: argparse.Namespace) -> int:
    from ocpar.service.web.store import Store, Token
    from ocpar.service.web.tokens import issue

    token = Token(args.name, args.max_jobs, args.max_agents, args.max_evaluations,
                  args.wall_time, None if not args.allow_solver_option
                  else solver_option_patterns(args.allow_solver_option))
    try:
        secret = issue(Store(state_dir(args)), token)
    except ValueError as exc:
        fail(f"{PROG} token add", str(exc))
    print(secret)
    return 0


def token_revoke(args: argparse.Namespace) -> int:
    from ocpar.service.web.store import Store
    from ocpar.service.web.tokens import revoke

    try:
        done = revoke(Store(state_dir(args)), args.name)
    except ValueError as exc:
        fail(f"{PROG} token revoke", str(exc))
    print(f"revoked token {args.name!r}: {len(done.cancelled)} queued job(s) cancelled, "
          f"{len(done.stopping)} running job(s) stopping")
    return 0


def token_list(args: argparse.Namespace) -> int:
    from ocpar.service.web.store import Store

    for token in Store(state_dir(args)).tokens():
        limits = [f"{name.replace('_', '-')} "
                  f"{'none' if (value := getattr(token, name)) is None else f'{value:g}'}"
                  for name in ("max_jobs", "max_agents", "max_evaluations", "wall_time")]
        if token.solver_options is not None:
            limits.append(f"solver-options {' '.join(token.solver_options) or 'none'}")
        print(f"{token.name:24} {', '.join(limits)}")
    return 0


def openapi_schema() -> dict:
    """The API's OpenAPI schema (docs/openapi.json)."""
    from ocpar.service.web.app import create_app
    from ocpar.service.web.runner import Settings

    with tempfile.TemporaryDirectory() as tmp:
        return create_app(Settings(state_dir=Path(tmp))).openapi()


def openapi(args: argparse.Namespace) -> int:
    text = json.dumps(openapi_schema(), indent=1) + "\n"
    if args.output:
        Path(args.output).write_text(text)
    else:
        sys.stdout.write(text)
    return 0
