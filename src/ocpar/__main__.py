"""Command line: ``ocpar COMMAND`` (or ``python -m ocpar COMMAND``).

Commands: ``run`` (a configuration, here), ``submit`` (a configuration as a detached job),
``jobs``, ``status``, ``result``, ``cancel``, ``resume``, ``wait`` (see :mod:`ocpar.service`):
the job commands speak to an ``ocpar serve`` server over HTTP (``--server URL --token TOKEN``,
or ``$OCPAR_SERVER`` and ``$OCPAR_TOKEN``; :mod:`ocpar.service.http_client`) or, with
``--scheduler ADDR``, to a Dask cluster's scheduler (:mod:`ocpar.service.client`; no
``resume``, ``wait`` or ``status --follow`` there).

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
from pathlib import Path
from typing import Any

from ocpar import driver
from ocpar.cli import (
    OneLineParser,
    add_tls_arguments,
    check_tls_arguments,
    client_security,
    fail,
    freeze_objects_at_exit,
)
from ocpar.config import (
    ConfigError,
    examples,
    load_config,
    parse_overrides,
    read_config_data,
    scheme_class,
)
from ocpar.service.client import SERVICE_OPTIONS, ServiceError
from ocpar.service.web import serve

#: Keys of a configuration that a submitted job sets itself: where it runs and writes.
SERVICE_KEYS = tuple(option[2:].replace("-", "_") for option in SERVICE_OPTIONS)

PROG = "ocpar"
#: The example command lines of ``ocpar run --help``.
RUN_EXAMPLES = (
    "ocpar run --list",
    "ocpar run formation-60 --output runs/f60 --plot none",
    "ocpar run macs-goddard --set max_evals=2000 seed=1 --workers 2 --backend dask",
    "ocpar run my-run.toml --print-argv",
)
#: Exit status of ``ocpar wait --timeout S`` when the job is still running (as timeout(1)).
EXIT_TIMEOUT = 124


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
    if args.scheduler is None:
        return _submit_http(args, prog)
    try:
        config = load_config(args.config, parse_overrides(args.overrides))
    except ConfigError as exc:
        fail(prog, str(exc))
    if args.idempotency_key is not None:
        fail(prog, "--idempotency-key needs an ocpar server (--server), not --scheduler")
    config = replace(config, options={key: value for key, value in config.options.items()
                                      if key not in SERVICE_KEYS})
    flags = args.scheme_flags  # the scheme's own options, after CONFIG: they override it
    argv = config.without(config.flag_keys(flags)).argv() + flags
    job = _service_call(args, "submit", lambda security: client.submit(
        config.scheme, argv, args.scheduler, security=security))
    print(job)
    return 0


def _submit_http(args: argparse.Namespace, prog: str) -> int:
    """``ocpar submit`` to a server: a configuration file is sent as its keys (without those
    the service sets, as on the Dask path), anything else as an example's name; the server
    checks it (HTTP 422: one line, exit 2)."""
    if args.scheme_flags:
        fail(prog, f"unrecognized arguments: {' '.join(args.scheme_flags)} (a server takes the "
                   "configuration's keys: --set KEY=VALUE)")
    try:
        overrides = parse_overrides(args.overrides)
        config: str | dict = args.config
        if Path(args.config).is_file():
            config = {key: value for key, value in read_config_data(args.config).items()
                      if key not in SERVICE_KEYS}
    except ConfigError as exc:
        fail(prog, str(exc))
    record = _http_call(args, "submit", lambda server: server.submit(
        config, overrides, args.idempotency_key))
    print(record["id"])
    return 0


def _server(args: argparse.Namespace, prog: str):
    """The :class:`~ocpar.service.http_client.Server` of ``--server``/``--token`` (or their
    environment variables); exits 2 with one line if they are missing or malformed."""
    from ocpar.service.http_client import SERVER_ENV, TOKEN_ENV, Server

    url = args.server or os.environ.get(SERVER_ENV)
    if not url:
        fail(prog, f"give --server URL (or set {SERVER_ENV}) for an ocpar server"
                   + (", or --scheduler ADDR for a Dask cluster" if
                      hasattr(args, "scheduler") else ""))
    if args.tls_cert is not None or args.tls_key is not None:
        fail(prog, "--tls-cert and --tls-key are for a tls:// Dask scheduler; an https:// "
                   "server takes --tls-ca-file only")
    try:
        return Server(url, args.token or os.environ.get(TOKEN_ENV, ""),
                      ca_file=args.tls_ca_file)
    except ServiceError as exc:
        fail(prog, str(exc))


def _http_call(args: argparse.Namespace, action: str, call) -> Any:
    """``call(server)`` with the server of the arguments (one line and exit 2 on an error)."""
    prog = f"{PROG} {action}"
    with _server(args, prog) as server:
        try:
            return call(server)
        except ServiceError as exc:
            fail(prog, str(exc))


def _when(iso: str | None) -> str:
    """An ISO 8601 UTC time as ``YYYY-MM-DD HH:MM:SS`` (``-`` for none)."""
    return iso[:19].replace("T", " ") if iso else "-"


def _describe_record(record: dict) -> str:
    """One line of a server's job record: id, scheme, problem, state, supersteps, submitted,
    finished (UTC) and the headline (or why not)."""
    about = record.get("headline") or record.get("reason") or ""
    return (f"{record['id']:32}  {record['scheme']:9} {record.get('problem') or '-':18} "
            f"{record['state']:9} {record['supersteps'] or 0:5d}  {_when(record['submitted'])}  "
            f"{_when(record['finished']):19}  {about}").rstrip()


#: The columns of :func:`_describe_record`, printed above ``ocpar jobs`` of a server.
JOBS_HEADER = "id, scheme, problem, state, supersteps, submitted, finished (UTC), headline"


def _service_call(args: argparse.Namespace, action: str, call) -> object:
    """``call(security)`` with the TLS options' security (one line and exit 2 on an error)."""
    prog = f"{PROG} {action}"
    if args.token is not None:
        fail(prog, "--token is for an ocpar server (--server), not --scheduler")
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
    reason = f"  ({status['reason']})" if status.get("reason") else ""
    return (f"{status['id']:38} {status['state']:9} supersteps {status['supersteps']:5d}  "
            f"submitted {age}{cancel}{reason}")


def jobs(args: argparse.Namespace) -> int:
    from ocpar.service import client

    if args.scheduler is None:
        records = _http_call(args, "jobs", lambda server: server.list_jobs())
        print(f"# {JOBS_HEADER}")
        for record in records:
            print(_describe_record(record))
        return 0
    for status in _service_call(args, "jobs", lambda tls: client.list_jobs(args.scheduler, tls)):
        print(_describe(status))
    return 0


def status(args: argparse.Namespace) -> int:
    from ocpar.service import client

    if args.scheduler is None:
        if args.follow:
            return _follow(args)
        record = _http_call(args, "status", lambda server: server.status(args.job))
        print(json.dumps(record, indent=1) if args.json else _describe_record(record))
        return 0
    if args.follow:
        fail(f"{PROG} status", "--follow needs an ocpar server (--server), not --scheduler")
    state = _service_call(args, "status",
                          lambda tls: client.status(args.job, args.scheduler, tls))
    if args.json:
        print(json.dumps(state, indent=1))
    else:
        print(_describe(state))
        if state["progress"]:
            print(f"  {state['progress']}")
    return 0


def _follow(args: argparse.Namespace) -> int:
    """``ocpar status JOB --follow``: every progress line of the job as it comes (from its
    start), a line at each change of state, until the job ends."""
    def follow(server) -> None:
        shown = None
        for event, data in server.follow(args.job):
            if event == "progress":
                print(data["line"], flush=True)
            elif data["state"] != shown:  # "state" and "end": the record
                print(_describe_record(data), flush=True)
                shown = data["state"]

    _http_call(args, "status", follow)
    return 0


def wait(args: argparse.Namespace) -> int:
    """``ocpar wait JOB``: block until the job ends, print its record's line; exit status 0
    if it succeeded, else its run's exit status (:func:`ocpar.service.http_client.exit_status`);
    one line and exit status 124 after ``--timeout`` seconds."""
    from ocpar.service.http_client import exit_status

    try:
        record = _http_call(args, "wait", lambda server: server.wait(args.job, args.timeout))
    except TimeoutError as exc:
        print(f"{PROG} wait: {exc}", file=sys.stderr)
        return EXIT_TIMEOUT
    print(_describe_record(record))
    return exit_status(record)


def resume(args: argparse.Namespace) -> int:
    """``ocpar resume JOB``: run a cancelled or failed job on from its checkpoint."""
    record = _http_call(args, "resume", lambda server: server.resume(args.job))
    print(f"{args.job}: resumed from its checkpoint (state {record['state']})")
    return 0


def result(args: argparse.Namespace) -> int:
    from ocpar.service import client

    if args.scheduler is None:
        paths = _http_call(args, "result", lambda server: server.result(args.job, args.output))
        print("wrote " + ", ".join(str(p) for p in paths))
        return 0
    paths = _service_call(args, "result",
                          lambda tls: client.result(args.job, args.scheduler, args.output, tls))
    print("wrote " + " and ".join(str(p) for p in paths))
    return 0


def cancel(args: argparse.Namespace) -> int:
    from ocpar.service import client

    if args.scheduler is None:
        _http_call(args, "cancel", lambda server: server.cancel(args.job))
        print(f"{args.job}: cancel requested; it stops at its next superstep boundary "
              "(a queued job at once) and keeps its checkpoint (ocpar resume)")
        return 0
    state = _service_call(args, "cancel",
                          lambda tls: client.cancel(args.job, args.scheduler, tls))
    print(f"{args.job}: cancel requested; it stops at its next superstep boundary (state "
          f"{state['state']}, {state['supersteps']} supersteps done, checkpoint "
          f"{state['checkpoint']})")
    return 0


def _add_endpoint(parser: argparse.ArgumentParser, dask: bool = True) -> None:
    """``--server`` and ``--token`` (an ocpar server), or ``--scheduler`` (a Dask cluster)."""
    where = parser.add_mutually_exclusive_group() if dask else parser
    where.add_argument("--server", metavar="URL",
                       help="the ocpar server (ocpar serve), e.g. http://127.0.0.1:8000 "
                            "(default $OCPAR_SERVER)")
    parser.add_argument("--token", metavar="TOKEN",
                        help="this client's token from ocpar serve token add (default "
                             "$OCPAR_TOKEN, which keeps it out of the process list)")
    if dask:
        where.add_argument("--scheduler", metavar="ADDR",
                           help="instead of a server: the Dask scheduler that keeps the jobs, "
                                "e.g. tcp://HOST:8786 (tls://HOST:8786 with this client's "
                                "certificate)")
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
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=driver.help_text(
            "Run the configuration CONFIG: a TOML file (scheme = \"formation\", \"pursuit\" "
            "or \"macs\", and one key per option of that scheme's command line, e.g. "
            "max_evals for --max-evals), or the name of a packaged example (--list). Any "
            "option of the scheme's command line given after CONFIG (--output DIR, --workers "
            "2, --problem-arg KEY=VALUE ...) overrides the file's key (--problem-arg replaces "
            "its whole [problem_args] table).", RUN_EXAMPLES))
    run_parser.add_argument("config", nargs="?", metavar="CONFIG",
                            help="a TOML file, or an example name such as formation-60")
    run_parser.add_argument("--set", nargs="+", action="extend", default=[],
                            dest="overrides", metavar="KEY=VALUE",
                            help="override keys of CONFIG; VALUE is a TOML value (workers=2, "
                                 "quiet=true), taken as a string if it is not one "
                                 "(backend=dask); may repeat (--set backend=dask --set "
                                 "workers=2)")
    run_parser.add_argument("--print-argv", action="store_true",
                            help="check CONFIG, print the equivalent scheme command line and "
                                 "exit")
    run_parser.add_argument("--list", action="store_true",
                            help="list the packaged example configurations")
    run_parser.set_defaults(handler=run)

    submit_parser = commands.add_parser(
        "submit", prog=f"{PROG} submit", help="start a configuration as a detached job",
        description="Start CONFIG as a job and print its id once the configuration and its "
        "problem are checked. On an ocpar server (--server): CONFIG's keys (a TOML file) or "
        "an example's name are sent with the --set keys; the server checks them (one line, "
        "exit 2, if it refuses). On a Dask cluster (--scheduler): the job's coordinator runs "
        "on the scheduler's host (no worker slot), survives this process, checkpoints every "
        "superstep and writes its results where the scheduler keeps jobs ($OCPAR_JOBS_DIR "
        "there, default ~/.ocpar/jobs); a package.module:factory problem is loaded there "
        "first. Keys about where a run goes "
        f"({', '.join(SERVICE_KEYS)}) are set by the service (a server refuses them; the "
        "Dask path ignores them). On the Dask path other options of the scheme's command "
        "line after CONFIG override its keys.")
    submit_parser.add_argument("config", metavar="CONFIG",
                               help="a TOML file, or an example name (ocpar run --list)")
    _add_endpoint(submit_parser)
    submit_parser.add_argument("--set", nargs="+", action="extend", default=[],
                               dest="overrides", metavar="KEY=VALUE",
                               help="override keys of CONFIG; may repeat")
    submit_parser.add_argument("--idempotency-key", metavar="KEY",
                               help="(server) a key of this submission: submitted again with "
                                    "the same key, the server returns the first job")
    submit_parser.set_defaults(handler=submit)

    jobs_parser = commands.add_parser("jobs", prog=f"{PROG} jobs", help="list the jobs",
                                      description="List the jobs. A server's (this "
                                      "token's, newest first): id, scheme, problem, state "
                                      "(queued, running, succeeded, failed, cancelled), "
                                      "supersteps, submitted, finished and the headline (or "
                                      "why not). A Dask cluster's: id, state (queued, running, "
                                      "finished, failed, cancelled), supersteps done.")
    _add_endpoint(jobs_parser)
    jobs_parser.set_defaults(handler=jobs)

    for name, handler, text in (("status", status, "show one job: its state, supersteps "
                                 "done and headline (a server's), or its latest progress line "
                                 "(a Dask cluster's)"),
                                ("result", result, "fetch a finished job's files: result.json, "
                                 "the array file, the trace and the plots (a Dask cluster's: "
                                 "result.json and plots)"),
                                ("cancel", cancel, "stop a job at its next superstep "
                                 "boundary, keeping its checkpoint"),
                                ("resume", resume, "(server) run a cancelled or failed job on "
                                 "from its checkpoint with its own options"),
                                ("wait", wait, "(server) block until a job ends and print its "
                                 "line; exit status 0 if it succeeded, else its run's exit "
                                 "status (1 not converged or failed without a result, 3 "
                                 "failed, 4 cancelled, 5 separation not met, 6 obstacles not "
                                 f"cleared), {EXIT_TIMEOUT} after --timeout")):
        sub = commands.add_parser(name, prog=f"{PROG} {name}", help=text, description=text)
        sub.add_argument("job", metavar="JOB", help="the job id that ocpar submit printed")
        _add_endpoint(sub, dask=name not in ("resume", "wait"))
        if name == "status":
            sub.add_argument("--json", action="store_true", help="print the status as JSON")
            sub.add_argument("--follow", action="store_true",
                             help="(server) print the job's progress lines from its start "
                                  "as they come, and its state as it changes, until it ends")
        if name == "result":
            sub.add_argument("--output", required=True, metavar="DIR",
                             help="where to write the files")
        if name == "wait":
            sub.add_argument("--timeout", type=float, metavar="S",
                             help=f"give up after S seconds (exit status {EXIT_TIMEOUT})")
        sub.set_defaults(handler=handler)
    serve.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    freeze_objects_at_exit()
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
