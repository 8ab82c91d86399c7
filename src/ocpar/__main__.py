"""Command line: ``ocpar COMMAND`` (or ``python -m ocpar COMMAND``).

Commands: ``run`` (a configuration, here), ``submit`` (a configuration as a detached job on a
Dask cluster), ``jobs``, ``status``, ``result``, ``cancel`` (see :mod:`ocpar.service`).

``ocpar run CONFIG [--set KEY=VALUE ...] [--print-argv] [SCHEME OPTIONS ...]`` runs the
configuration file CONFIG (:mod:`ocpar.config`), or the packaged example of that name (``ocpar
run --list``), through its scheme's own command line: ``ocpar run formation-60 --output DIR``
is ``python -m ocpar.formation --problem point-mass-plane --agents 60 ... --output DIR``, the
same run and the same ``result.json``; a scheme option after CONFIG overrides the file's key.
Under ``mpirun -n P`` every rank does the same, as the schemes' command lines do.

Each command is a subparser with a ``handler(args) -> int``; bad usage is one line on stderr
and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace

from ocpar import driver
from ocpar.cli import OneLineParser, add_tls_arguments, check_tls_arguments, client_security, fail
from ocpar.config import ConfigError, examples, load_config, parse_overrides, scheme_class
from ocpar.service.client import SERVICE_OPTIONS
from ocpar.service.web import serve

#: Keys of a configuration that a submitted job sets itself: where it runs and writes.
SERVICE_KEYS = tuple(option[2:].replace("-", "_") for option in SERVICE_OPTIONS)

PROG = "ocpar"


def run(args: argparse.Namespace) -> int:
    prog = f"{PROG} run"
    if args.list:
        if args.config is not None or args.overrides or args.print_argv or args.scheme_flags:
            fail(prog, "--list takes no CONFIG, --set, --print-argv or scheme options")
        for name, header in examples().items():
            print(f"{name:34} {header}")
        return 0
    if args.config is None and args.overrides and "=" not in args.overrides[-1]:
        args.config = args.overrides.pop()  # CONFIG given after --set KEY=VALUE ...
    if args.config is None:
        fail(prog, "give CONFIG, a TOML file or an example name (ocpar run --list)")
    try:
        config = load_config(args.config, parse_overrides(args.overrides))
    except ConfigError as exc:
        fail(prog, str(exc))
    scheme = scheme_class(config.scheme)
    flags = args.scheme_flags  # the scheme's own options, after CONFIG: they override it
    config = config.without(config.flag_keys(flags))
    argv = config.argv() + flags
    if args.print_argv:
        driver.parse_options(scheme, argv)  # the scheme's own checks, one-line errors
        print(config.command(flags))
        return 0
    return driver.main(scheme, argv)


def submit(args: argparse.Namespace) -> int:
    from ocpar.service import client

    prog = f"{PROG} submit"
    try:
        config = load_config(args.config, parse_overrides(args.overrides))
    except ConfigError as exc:
        fail(prog, str(exc))
    config = replace(config, options={key: value for key, value in config.options.items()
                                      if key not in SERVICE_KEYS})
    flags = args.scheme_flags  # the scheme's own options, after CONFIG: they override it
    argv = config.without(config.flag_keys(flags)).argv() + flags
    job = _service_call(args, "submit", lambda security: client.submit(
        config.scheme, argv, args.scheduler, security=security))
    print(job)
    return 0


def _service_call(args: argparse.Namespace, action: str, call) -> object:
    """``call(security)`` with the TLS options' security (one line and exit 2 on an error)."""
    from ocpar.service.client import ServiceError

    prog = f"{PROG} {action}"
    check_tls_arguments(args, prog)
    security = client_security(args, prog)
    try:
        return call(security)
    except ServiceError as exc:
        fail(prog, str(exc))


def _describe(status: dict) -> str:
    age = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(status["submitted"]))
    cancel = "  (cancel requested)" if status["cancel_requested"] and \
        status["state"] == "running" else ""
    return (f"{status['id']:38} {status['state']:9} supersteps {status['supersteps']:5d}  "
            f"submitted {age}{cancel}")


def jobs(args: argparse.Namespace) -> int:
    from ocpar.service import client

    for status in _service_call(args, "jobs", lambda tls: client.list_jobs(args.scheduler, tls)):
        print(_describe(status))
    return 0


def status(args: argparse.Namespace) -> int:
    from ocpar.service import client

    state = _service_call(args, "status",
                          lambda tls: client.status(args.job, args.scheduler, tls))
    if args.json:
        print(json.dumps(state, indent=1))
    else:
        print(_describe(state))
        if state["progress"]:
            print(f"  {state['progress']}")
    return 0


def result(args: argparse.Namespace) -> int:
    from ocpar.service import client

    paths = _service_call(args, "result",
                          lambda tls: client.result(args.job, args.scheduler, args.output, tls))
    print("wrote " + " and ".join(str(p) for p in paths))
    return 0


def cancel(args: argparse.Namespace) -> int:
    from ocpar.service import client

    state = _service_call(args, "cancel",
                          lambda tls: client.cancel(args.job, args.scheduler, tls))
    print(f"{args.job}: cancel requested; it stops at its next superstep boundary (state "
          f"{state['state']}, {state['supersteps']} supersteps done, checkpoint "
          f"{state['checkpoint']})")
    return 0


def _add_scheduler(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scheduler", required=True, metavar="ADDR",
                        help="the Dask scheduler that keeps the jobs, e.g. tcp://HOST:8786 "
                             "(tls://HOST:8786 with this client's certificate)")
    add_tls_arguments(parser)


def build_parser() -> OneLineParser:
    parser = OneLineParser(
        prog=PROG,
        description="ocpar: large optimal control problems solved as many small ones in "
        "parallel supersteps. Each scheme also has its own command line: python -m "
        "ocpar.formation|pursuit|macs.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    parser.subcommands = commands.choices  # name → subparser
    run_parser = commands.add_parser(
        "run", prog=f"{PROG} run", help="run a configuration file",
        usage=f"{PROG} run CONFIG [--set KEY=VALUE ...] [--print-argv] [SCHEME OPTIONS ...]",
        description="Run the configuration CONFIG: a TOML file (scheme = \"formation\", "
        "\"pursuit\" or \"macs\", and one key per option of that scheme's command line, "
        "e.g. max_evals for --max-evals), or the name of a packaged example (--list). Any "
        "option of the scheme's command line given after CONFIG (--output DIR, --workers 2, "
        "--problem-arg KEY=VALUE ...) overrides the file's key (--problem-arg replaces its "
        "whole [problem_args] table).")
    run_parser.add_argument("config", nargs="?", metavar="CONFIG",
                            help="a TOML file, or an example name such as formation-60")
    run_parser.add_argument("--set", nargs="+", default=[], dest="overrides",
                            metavar="KEY=VALUE",
                            help="override keys of CONFIG; VALUE is a TOML value (workers=2, "
                                 "quiet=true), taken as a string if it is not one "
                                 "(backend=dask)")
    run_parser.add_argument("--print-argv", action="store_true",
                            help="check CONFIG, print the equivalent scheme command line and "
                                 "exit")
    run_parser.add_argument("--list", action="store_true",
                            help="list the packaged example configurations")
    run_parser.set_defaults(handler=run)

    submit_parser = commands.add_parser(
        "submit", prog=f"{PROG} submit", help="start a configuration as a detached job",
        description="Start CONFIG as a job on a Dask cluster and print its id at once: its "
        "coordinator runs on the scheduler's host (no worker slot), survives this process, "
        "checkpoints every superstep and writes its results where the scheduler keeps jobs "
        "($OCPAR_JOBS_DIR there, default ~/.ocpar/jobs). Keys about where a run goes "
        f"({', '.join(SERVICE_KEYS)}) are set by the service and ignored. Other options of "
        "the scheme's command line after CONFIG override its keys.")
    submit_parser.add_argument("config", metavar="CONFIG",
                               help="a TOML file, or an example name (ocpar run --list)")
    _add_scheduler(submit_parser)
    submit_parser.add_argument("--set", nargs="+", default=[], dest="overrides",
                               metavar="KEY=VALUE", help="override keys of CONFIG")
    submit_parser.set_defaults(handler=submit)

    jobs_parser = commands.add_parser("jobs", prog=f"{PROG} jobs", help="list the jobs",
                                      description="List the cluster's jobs: id, state "
                                      "(queued, running, finished, failed, cancelled), "
                                      "supersteps done.")
    _add_scheduler(jobs_parser)
    jobs_parser.set_defaults(handler=jobs)

    for name, handler, text in (("status", status, "show one job: state, supersteps done and "
                                 "its latest progress line (the scheme's headline figure)"),
                                ("result", result, "fetch a finished job's result.json and "
                                 "plots"),
                                ("cancel", cancel, "stop a job at its next superstep "
                                 "boundary, keeping its checkpoint")):
        sub = commands.add_parser(name, prog=f"{PROG} {name}", help=text, description=text)
        sub.add_argument("job", metavar="JOB", help="the job id that ocpar submit printed")
        _add_scheduler(sub)
        if name == "status":
            sub.add_argument("--json", action="store_true", help="print the status as JSON")
        if name == "result":
            sub.add_argument("--output", required=True, metavar="DIR",
                             help="where to write result.json and the plots")
        sub.set_defaults(handler=handler)
    serve.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    parser.subcommands[args.command].refuse_repeated(argv[1:])
    if extra and args.command not in ("run", "submit"):
        parser.subcommands[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
    args.scheme_flags = extra
    try:
        status = args.handler(args)
        sys.stdout.flush()
    except BrokenPipeError:  # the reader left early (`ocpar status --json | grep -q ...`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no error at exit
        return 1
    return status


if __name__ == "__main__":
    sys.exit(main())
