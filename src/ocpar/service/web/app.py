"""The HTTP job API of ``ocpar serve`` (FastAPI): :func:`create_app`.

Every ``/jobs`` endpoint needs ``Authorization: Bearer <token>`` (tokens from ``ocpar serve
token add``); a job belongs to the token that submitted it. ``POST /jobs`` checks the
configuration exactly as ``ocpar run`` does (:func:`ocpar.config.from_mapping`,
:meth:`~ocpar.config.RunConfig.with_overrides`, the scheme's own command line through
:func:`ocpar.driver.check_options`), the problem reference against the operator's allow-list
(loaded, so that a reference that does not give a problem is refused before a job id is
returned), the solver options against the operator's (:func:`solver_option_allowed`) and
the token's limits; nothing of a request is imported or unpickled but an
allowed reference, and the job's memory estimate against the server's limit
(:mod:`ocpar.service.web.memory`). ``GET /`` and ``/static`` serve the page (no token needed).

The reading endpoints are coroutines: they run on the event loop, whose reads of the store
(a read-only connection, never waiting for the write lock) and of a job's few files take well
under a millisecond, with no hop to a worker thread (which, on a busy machine, costs a
scheduler's time slice each). Those that write, check or draw run in worker threads.

(No ``from __future__ import annotations`` here: FastAPI reads the endpoints' annotations,
some of them local to :func:`create_app`.)
"""

import asyncio
import json
import shutil
import threading
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from datetime import UTC, datetime
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Header, HTTPException, Query, Request, Response, Security
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from ocpar import __version__
from ocpar.config import ConfigError, RunConfig, examples, from_mapping, load_config
from ocpar.config import scheme_class as options_class
from ocpar.driver import check_options, resolve_problem
from ocpar.ocp.solver_options import HOST_FILE_OPTIONS
from ocpar.references import is_reference
from ocpar.service.client import SERVICE_OPTIONS
from ocpar.service.jobs import JOB_ID, has_checkpoint, new_job_id, supersteps_done
from ocpar.service.web import memory
from ocpar.service.web.events import parse_progress
from ocpar.service.web.figures import DrawingFailed, Figures, pending
from ocpar.service.web.runner import Runner, Settings
from ocpar.service.web.store import FINAL, Store, Token
from ocpar.service.web.tokens import authenticate

#: Largest request body (bytes).
MAX_BODY = 64 * 1024
#: Configuration keys the server sets itself (where a job runs and writes; its workers).
SERVER_KEYS = frozenset(option[2:].replace("-", "_") for option in SERVICE_OPTIONS) | {
    "workers"}
#: Each scheme's key of "agents" or "evaluations" per job that a token may limit.
LIMITED = {"formation": ("agents", "agents", "agents"),
           "pursuit": ("max_agents", "max_agents", "agents"),
           "macs": ("max_evals", "max_evaluations", "evaluations")}
#: Most bytes of the log one ``GET /jobs/{id}/log`` returns.
LOG_CHUNK = 1 << 20
STATIC = Path(__file__).with_name("static")
#: A request of each scheme checked before the server answers, so that the first POST finds
#: what a check imports and builds loaded.
WARM_UP_REQUESTS = ({"config": "formation-60", "set": {"agents": 12}},
                    {"config": "pursuit-case1"}, {"config": "macs-goddard"})


class JobRecord(BaseModel):
    """A job as the API shows it."""

    id: str = Field(description="SCHEME-YYYYMMDD-HHMMSS-XXXXXX")
    scheme: str
    problem: str = Field(description="a built-in example or an allowed module:factory")
    state: str = Field(description="queued, running, succeeded, failed or cancelled")
    reason: str | None = Field(description="why it failed, was cancelled or restarted")
    supersteps: int = Field(description="supersteps recorded in its checkpoint")
    submitted: str | None = Field(description="ISO 8601 UTC")
    started: str | None
    finished: str | None
    result_status: str | None = Field(description="result.json's status")
    headline: str | None = Field(description="result.json's title")
    files: list[str] = Field(description="files of its output directory")


class JobList(BaseModel):
    jobs: list[JobRecord]


class JobRequest(BaseModel):
    """The body of ``POST /jobs``."""

    config: str | dict[str, Any] = Field(
        description="a packaged example's name (formation-60) or a configuration's keys "
        "({\"scheme\": \"formation\", \"agents\": 12})")
    set: dict[str, Any] = Field(default_factory=dict,
                                description="keys overridden, as ocpar run --set KEY=VALUE")


class LogChunk(BaseModel):
    offset: int
    next_offset: int
    text: str


class FileEntry(BaseModel):
    name: str
    size: int | None = Field(description="bytes; null for a plot drawn when first fetched")


class Health(BaseModel):
    ready: bool = Field(description="whether a job submitted now starts at once on warm "
                        "processes (the cluster up, every runner warmed up)")


class FileList(BaseModel):
    files: list[FileEntry]


class Problem(BaseModel):
    detail: str


class BodyLimit:
    """ASGI middleware: 413 for a request whose body exceeds ``limit`` bytes (declared or
    streamed)."""

    def __init__(self, app: Any, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            await _too_large(self.limit)(scope, receive, send)
            return
        seen = 0

        async def counted() -> dict:
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.limit:
                raise _BodyTooLarge
            return message

        try:
            await self.app(scope, counted, send)
        except _BodyTooLarge:
            await _too_large(self.limit)(scope, receive, send)


class _BodyTooLarge(Exception):
    pass


def _too_large(limit: int) -> JSONResponse:
    return JSONResponse({"detail": f"request body over {limit // 1024} KiB"}, status_code=413)


def iso(t: float | None) -> str | None:
    """``t`` (s since the epoch) as ISO 8601 UTC, or None."""
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat(
        timespec="milliseconds").replace("+00:00", "Z")


def refuse(detail: str, status: int = 422) -> HTTPException:
    return HTTPException(status, " ".join(str(detail).split()))


def solver_option_allowed(name: str, patterns: tuple[str, ...]) -> bool:
    """Whether the solver option ``name`` (``SOLVER.NAME``) matches one of the operator's
    ``patterns``; one that names files or libraries on the server
    (:data:`~ocpar.ocp.solver_options.HOST_FILE_OPTIONS`) only a pattern equal to it."""
    if name in HOST_FILE_OPTIONS:
        return name in patterns
    return any(fnmatchcase(name, pattern) for pattern in patterns)


def create_app(settings: Settings) -> FastAPI:
    """The server's application: the job API over the store in ``settings.state_dir``, whose
    jobs a :class:`~ocpar.service.web.runner.Runner` starts while the application runs."""
    store = Store(settings.state_dir)
    runner = Runner(store, settings)
    figures = Figures(runner.pool)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await run_in_threadpool(runner.start)
        for request in WARM_UP_REQUESTS:
            await run_in_threadpool(checked, request, Token("warm-up", None, None, None, None))
        yield
        await run_in_threadpool(runner.stop)

    app = FastAPI(
        title="ocpar job service", version=__version__, lifespan=lifespan,
        description="Runs ocpar configurations (formation, pursuit, MACS) as jobs: submit, "
        "follow (server-sent events), fetch results, cancel, resume. Every /jobs endpoint "
        "needs Authorization: Bearer <token> (ocpar serve token add NAME).")
    app.state.store, app.state.runner, app.state.settings = store, runner, settings
    app.add_middleware(BodyLimit, limit=MAX_BODY)
    bearer = HTTPBearer(auto_error=False, description="a token of ocpar serve token add")
    errors = {401: {"model": Problem}, 403: {"model": Problem}, 404: {"model": Problem}}

    @app.exception_handler(RequestValidationError)
    async def one_line(request: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
        where = ".".join(str(part) for part in first.get("loc", ())[1:]) or "request"
        return JSONResponse({"detail": f"{where}: {first.get('msg')}"}, status_code=422)

    async def caller(credentials: Annotated[HTTPAuthorizationCredentials | None,
                                      Security(bearer)]) -> Token:
        token = authenticate(store, credentials.credentials) if credentials else None
        if token is None:
            raise HTTPException(401, "a valid token is needed: Authorization: Bearer <token>",
                                headers={"WWW-Authenticate": "Bearer"})
        return token

    Caller = Annotated[Token, Depends(caller)]

    def owned(job_id: str, token: Token) -> dict:
        row = store.job(job_id) if JOB_ID.fullmatch(job_id) else None
        if row is None:
            raise HTTPException(404, f"no job {job_id[:60]}")
        if row["owner"] != token.name:
            raise HTTPException(403, f"job {job_id} belongs to another token")
        return row

    def record(row: dict) -> dict:
        path = store.job_dir(row["id"])
        return {"id": row["id"], "scheme": row["scheme"], "problem": row["problem"],
                "state": row["state"], "reason": row["reason"],
                "supersteps": supersteps_done(path), "submitted": iso(row["submitted"]),
                "started": iso(row["started"]), "finished": iso(row["finished"]),
                "result_status": row["result_status"], "headline": row["headline"],
                "files": [entry["name"] for entry in output_files(path)]}

    def prepare(data: Any, token: Token) -> tuple[RunConfig, list[str], str]:
        """The checked configuration of a request body, its command line and problem."""
        if not isinstance(data, dict):
            raise refuse("body: expected a JSON object {\"config\": ..., \"set\": {...}}")
        for key in data:
            if key not in ("config", "set"):
                raise refuse(f"body: {key}: unknown key (expected config and set)")
        config, overrides = data.get("config"), data.get("set") or {}
        if not isinstance(overrides, dict):
            raise refuse("set: expected an object of KEY: VALUE")
        given = config if isinstance(config, dict) else {}
        for where, keys in (("config", given), ("set", overrides)):
            for key, value in keys.items():
                if key in SERVER_KEYS:
                    raise refuse(f"{where}: {key}: set by the server for a job; leave it out")
                if value is None:
                    raise refuse(f"{where}: {key}: null is not a value; leave the key out")
        try:
            if isinstance(config, str):
                if config not in examples():
                    raise refuse(f"config: no packaged example named {config[:60]!r} (one of "
                                 f"{', '.join(examples())}), or give an object of keys")
                run = load_config(config)
                run = run.without(frozenset(SERVER_KEYS))
            elif isinstance(config, dict):
                run = from_mapping(config, "config")
            else:
                raise refuse("config: missing: an example name or an object of keys"
                             if config is None else
                             "config: expected an example name or an object of keys")
            run = run.with_overrides(overrides, "set")
            # before the options are checked: a check may load what an option names
            for name in run.options.get("solver_options", {}):
                if not solver_option_allowed(name, settings.allow_solver_option):
                    raise refuse(f"solver_options: {name} is not allowed on this server (the "
                                 "operator allows solver options with ocpar serve "
                                 "--allow-solver-option)")
                if token.solver_options is not None and not solver_option_allowed(
                        name, token.solver_options):
                    raise refuse(f"solver_options: {name} is not allowed to this token (ocpar "
                                 "serve token add --allow-solver-option)")
            argv = run.argv()
            options, _ = check_options(options_class(run.scheme), argv)
        except (ConfigError, ValueError) as exc:
            raise refuse(str(exc)) from None
        except SystemExit:  # argparse's --help and the like: not a run
            raise refuse("config: not a run configuration") from None
        if is_reference(options.problem) and not any(
                fnmatchcase(options.problem, pattern) for pattern in settings.allow_problem):
            raise refuse(f"problem: {options.problem!r} is not allowed on this server (the "
                         "operator allows references with ocpar serve --allow-problem)")
        check_limits(run.scheme, options, None, token)
        try:
            memory.check(run.scheme, options, None, settings.max_job_memory)
            problem = resolve_problem(options)
            options.check_problem(problem)
            memory.check(run.scheme, options, problem, settings.max_job_memory)
        except ValueError as exc:
            raise refuse(str(exc)) from None
        check_limits(run.scheme, options, problem, token)
        return run, argv, options.problem

    checking = threading.Lock()

    def checked(data: Any, token: Token) -> tuple[RunConfig, list[str], str]:
        """:func:`prepare`, one request at a time (problems are built with CasADi, whose
        symbolic construction is not meant for several threads at once)."""
        with checking:
            return prepare(data, token)

    def check_limits(scheme: str, options: Any, problem: Any, token: Token) -> None:
        key, field, what = LIMITED[scheme]
        limit = token.max_evaluations if what == "evaluations" else token.max_agents
        value = getattr(options, field)
        if value is None and problem is not None:
            value = getattr(problem, "agents", None)
        if limit is not None and value is not None and value > limit:
            raise refuse(f"{key}: {value} {what} exceeds this token's limit of {limit} "
                         f"{what} per job")

    @app.post("/jobs", status_code=201, response_model=JobRecord, tags=["jobs"],
              summary="submit a run configuration",
              responses={200: {"model": JobRecord, "description": "the job submitted before "
                               "with the same Idempotency-Key"},
                         413: {"model": Problem}, 422: {"model": Problem}, 401: errors[401]},
              openapi_extra={"requestBody": {"required": True, "content": {
                  "application/json": {"schema": JobRequest.model_json_schema()}}}})
    async def submit(request: Request, response: Response, token: Caller,
                     idempotency_key: Annotated[str | None, Header(max_length=200)] = None) -> dict:
        if idempotency_key is not None and (earlier := store.job_by_key(token.name,
                                                                        idempotency_key)):
            response.status_code = 200
            return record(earlier)
        body = await request.body()
        try:
            data = json.loads(body)
        except (ValueError, UnicodeDecodeError) as exc:
            raise refuse(f"body: not JSON: {exc}") from None
        run, argv, problem = await run_in_threadpool(checked, data, token)
        job_id = new_job_id(run.scheme)
        path = store.job_dir(job_id)
        path.mkdir(parents=True)
        earlier = store.add_job({
            "id": job_id, "owner": token.name, "scheme": run.scheme, "problem": problem,
            "config": {"scheme": run.scheme, **run.options}, "argv": argv, "state": "queued",
            "submitted": time.time(), "idempotency_key": idempotency_key})
        if earlier is not None:  # a concurrent request with the same key won
            shutil.rmtree(path, ignore_errors=True)
            response.status_code = 200
            return record(earlier)
        runner.wake.set()
        return record(store.job(job_id))

    @app.get("/jobs", response_model=JobList, tags=["jobs"], summary="the caller's jobs",
             responses={401: errors[401]})
    async def list_jobs(token: Caller) -> dict:
        return {"jobs": [record(row) for row in store.jobs(owner=token.name)]}

    @app.get("/jobs/{job_id}", response_model=JobRecord, tags=["jobs"], summary="one job",
             responses=errors)
    async def get_job(job_id: str, token: Caller) -> dict:
        return record(owned(job_id, token))

    @app.get("/jobs/{job_id}/events", tags=["jobs"], responses={
        **errors, 200: {"content": {"text/event-stream": {}}, "description":
                        "event: progress (data {line, superstep, figures}) per log line, "
                        "event: state (data: the record) on each change, event: end (data: "
                        "the record) once final"}},
             summary="progress lines and state changes as server-sent events")
    async def events(job_id: str, token: Caller) -> StreamingResponse:
        owned(job_id, token)
        log_path = store.job_dir(job_id) / "log.txt"

        async def stream() -> AsyncIterator[str]:
            offset, partial, last = 0, b"", None
            while True:
                row = store.job(job_id)
                data, offset = _read(log_path, offset, LOG_CHUNK)
                final = row["state"] in FINAL and len(data) < LOG_CHUNK
                *lines, partial = (partial + data).split(b"\n")
                if final and partial:
                    lines, partial = [*lines, partial], b""
                for raw in lines:
                    line = raw.decode(errors="replace").rstrip("\r")
                    if line.strip():
                        superstep, figures = parse_progress(line)
                        yield _event("progress", {"line": line, "superstep": superstep,
                                                  "figures": figures})
                current = record(row)
                if row["state"] != last:
                    last = row["state"]
                    yield _event("state", current)
                if final:
                    yield _event("end", current)
                    return
                await asyncio.sleep(0.25)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache"})

    @app.get("/jobs/{job_id}/log", response_model=LogChunk, tags=["jobs"], responses=errors,
             summary="the job's log from a byte offset")
    async def get_log(job_id: str, token: Caller,
                offset: Annotated[int, Query(ge=0)] = 0) -> dict:
        owned(job_id, token)
        data, end = _read(store.job_dir(job_id) / "log.txt", offset, LOG_CHUNK)
        return {"offset": offset, "next_offset": end, "text": data.decode(errors="replace")}

    @app.get("/jobs/{job_id}/files", response_model=FileList, tags=["jobs"], responses=errors,
             summary="the files of the job's output directory")
    async def list_files(job_id: str, token: Caller) -> dict:
        owned(job_id, token)
        return {"files": output_files(store.job_dir(job_id))}

    @app.get("/jobs/{job_id}/files/{name}", tags=["jobs"], responses={
        **errors, 200: {"content": {"application/octet-stream": {}}},
        500: {"model": Problem, "description": "a plot that could not be drawn"}},
             summary="one file of the job's output directory (a plot is drawn when first "
                     "fetched)")
    def get_file(job_id: str, name: str, token: Caller) -> FileResponse:
        row = owned(job_id, token)
        path = store.job_dir(job_id)
        if name not in {entry["name"] for entry in output_files(path)}:
            raise HTTPException(404, f"job {job_id} has no file {name[:80]!r}")
        if name in pending(path):
            try:
                figures.draw(path, row["scheme"], json.loads(row["argv"]))
            except DrawingFailed as exc:
                raise HTTPException(500, f"job {job_id}: {name}: {exc}") from None
        return FileResponse(path / "output" / name)

    @app.get("/health", response_model=Health, tags=["server"],
             responses={503: {"model": Health, "description": "not ready yet"}},
             summary="whether the server is ready: jobs start at once on warm processes")
    async def health(response: Response) -> dict:
        ready = runner.ready
        if not ready:
            response.status_code = 503
        return {"ready": ready}

    @app.delete("/jobs/{job_id}", status_code=204, tags=["jobs"],
                responses={**errors, 409: {"model": Problem}},
                summary="cancel: a running job stops at its next superstep boundary")
    def cancel(job_id: str, token: Caller) -> Response:
        row = owned(job_id, token)
        if row["state"] in FINAL:
            raise HTTPException(409, f"job {job_id} is already {row['state']}")
        if not store.update(job_id, only_if="queued", state="cancelled", finished=time.time(),
                            reason="cancelled by request before it started"):
            (store.job_dir(job_id) / "cancel").touch()  # running: the run reads it
        return Response(status_code=204)

    @app.post("/jobs/{job_id}/resume", status_code=202, response_model=JobRecord,
              tags=["jobs"], responses={**errors, 409: {"model": Problem}},
              summary="run a cancelled or failed job on from its checkpoint")
    def resume(job_id: str, token: Caller) -> dict:
        row = owned(job_id, token)
        path = store.job_dir(job_id)
        if row["state"] not in ("cancelled", "failed") or not has_checkpoint(path):
            raise HTTPException(409, f"job {job_id} is {row['state']}"
                                f"{'' if has_checkpoint(path) else ' without a checkpoint'}; "
                                "only a cancelled or failed job with a checkpoint resumes")
        (path / "cancel").unlink(missing_ok=True)
        if not store.update(job_id, only_if=("cancelled", "failed"), state="queued", resume=1,
                            reason=None, finished=None, stop_reason=None):
            raise HTTPException(409, f"job {job_id} changed state; try again")
        runner.wake.set()
        return record(store.job(job_id))

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app


def output_files(path: Path) -> list[dict]:
    """Name and size of every file in the output directory of the job in ``path``, and its
    plots still to be drawn (size None, :func:`~ocpar.service.web.figures.pending`)."""
    output = path / "output"
    if not output.is_dir():
        return []
    files = [{"name": p.name, "size": p.stat().st_size} for p in output.iterdir()
             if p.is_file() and not p.name.startswith(".")]
    return sorted(files + [{"name": name, "size": None} for name in pending(path)],
                  key=lambda entry: entry["name"])


def _read(path: Path, offset: int, limit: int) -> tuple[bytes, int]:
    """Up to ``limit`` bytes of ``path`` from ``offset``, and the offset after them."""
    try:
        with open(path, "rb") as f:
            f.seek(offset)
            data = f.read(limit)
    except FileNotFoundError:
        data = b""
    return data, offset + len(data)


def _event(name: str, data: dict) -> str:
    return f"event: {name}\ndata: {json.dumps(data)}\n\n"
