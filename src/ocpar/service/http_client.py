"""The Python API of an ``ocpar serve`` server over HTTP (docs/web-service.md), behind
``ocpar submit|jobs|status|result|cancel|resume|wait --server URL --token TOKEN``.

>>> server = Server("http://127.0.0.1:8000", token)                       # doctest: +SKIP
>>> job = server.submit("formation-60", {"agents": 12})["id"]             # doctest: +SKIP
>>> server.wait(job)["state"]                                             # doctest: +SKIP
'succeeded'
>>> server.result(job, "runs/fetched")                                    # doctest: +SKIP
[PosixPath('runs/fetched/result.json'), ...]

A job is the server's record, a dict: ``id``, ``scheme``, ``problem``, ``state`` (queued,
running, succeeded, failed, cancelled), ``reason``, ``supersteps``, ``submitted``,
``started``, ``finished`` (ISO 8601 UTC or None), ``result_status``, ``headline``, ``files``.
Every refusal is a :class:`ServerRefused` (a :class:`ServiceError`) with the server's one-line
detail and the HTTP status; a server that cannot be reached is a :class:`ServerUnreachable`
naming its URL.
"""

from __future__ import annotations

import json
import ssl
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx

from ocpar.results import EXIT_STATUS
from ocpar.service.client import ServiceError

#: The states a job ends in.
FINAL_STATES = ("succeeded", "failed", "cancelled")
#: Environment variables giving a client's defaults for ``--server`` and ``--token``.
SERVER_ENV, TOKEN_ENV = "OCPAR_SERVER", "OCPAR_TOKEN"
#: Seconds to connect, send and (outside event streams) wait for an answer.
TIMEOUT_S = 30.0
#: Seconds between reconnections of :meth:`Server.follow` when an event stream breaks.
RECONNECT_S = 1.0
#: Seconds :meth:`Server.follow` tries to reach a server that went away (e.g. restarting).
UNREACHABLE_S = 60.0


class ServerUnreachable(ServiceError):
    """The server cannot be reached (refused connection, unknown host, TLS failure); the
    message names its URL."""


class ServerRefused(ServiceError):
    """The server answered with an error: ``status`` is the HTTP status (401, 403, 404, 409,
    413, 422, ...), the message its one-line detail."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"{detail} (HTTP {status})")
        self.status = status
        self.detail = detail


def exit_status(record: Mapping[str, Any]) -> int:
    """The exit status of a job in a final state, as ``ocpar wait`` returns it: 0 if it
    succeeded; else its run's exit status (:data:`ocpar.results.EXIT_STATUS` of its result's
    status: 1 not converged, 3 failed, 4 cancelled, 5, 6), 4 for a job cancelled before it
    wrote a result and 1 for a job that failed without one."""
    if record["state"] == "succeeded":
        return 0
    if record.get("result_status") in EXIT_STATUS:
        return EXIT_STATUS[record["result_status"]] or 1
    return EXIT_STATUS["cancelled"] if record["state"] == "cancelled" else 1


def _detail(response: httpx.Response) -> str:
    """The one-line detail of an error response (FastAPI's ``{"detail": ...}``)."""
    try:
        detail = response.json().get("detail")
    except (ValueError, AttributeError):
        detail = None
    if isinstance(detail, list):  # FastAPI's own validation errors: the first one's message
        first = detail[0] if detail and isinstance(detail[0], Mapping) else {}
        where = ".".join(str(part) for part in first.get("loc", ()) if part != "body")
        detail = f"{where}: {first.get('msg', '')}" if where else first.get("msg")
    text = str(detail) if detail else response.text or response.reason_phrase
    return " ".join(text.split())[:500]


def _path(job: str, *parts: str) -> str:
    """``/jobs/JOB/PART/...`` with each piece quoted: a job id or file name is one segment,
    never a way to another endpoint (``../x``, ``..``: a ServiceError)."""
    for piece in (job, *parts):
        if piece in ("", ".", ".."):
            raise ServiceError(f"not a job id or file name: {piece!r}")
    return "/".join(["/jobs", *(quote(piece, safe="") for piece in (job, *parts))])


def parse_events(lines: Iterator[str]) -> Iterator[tuple[str, dict]]:
    """The ``(event, data)`` pairs of a server-sent event stream given as its lines (``data``
    parsed as JSON; comments and events without data are skipped)."""
    event, data = "message", []
    for line in lines:
        if not line:
            if data:
                yield event, json.loads("\n".join(data))
            event, data = "message", []
        elif line.startswith(":"):
            continue
        else:
            field, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if field == "event":
                event = value
            elif field == "data":
                data.append(value)
    if data:
        yield event, json.loads("\n".join(data))


class Server:
    """An ``ocpar serve`` server at ``url`` (``http://HOST:PORT``, or ``https://`` with
    ``ca_file`` the CA that signed a self-signed certificate) used with the bearer ``token``.
    Use it as a context manager, or call :meth:`close`."""

    def __init__(self, url: str, token: str, *, ca_file: str | None = None,
                 timeout_s: float = TIMEOUT_S) -> None:
        if not url.startswith(("http://", "https://")):
            raise ServiceError(f"server {url!r}: expected http://HOST:PORT or https://HOST:PORT")
        if not token:
            raise ServiceError(f"no token for {url}: give --token or set {TOKEN_ENV}")
        self.url = url.rstrip("/")
        verify: ssl.SSLContext | bool = (ssl.create_default_context(cafile=ca_file)
                                         if ca_file else True)
        self._http = httpx.Client(base_url=self.url, timeout=timeout_s, verify=verify,
                                  headers={"Authorization": f"Bearer {token}"})

    def __enter__(self) -> Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connections."""
        self._http.close()

    def _request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            response = self._http.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        if response.status_code >= 400:
            raise ServerRefused(response.status_code, _detail(response))
        return response

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        """The JSON answer of a request (a ServiceError if it is none: not an ocpar
        server)."""
        response = self._request(method, path, **kwargs)
        try:
            return response.json()
        except ValueError:
            raise ServiceError(f"{self.url}{path} answered {response.status_code} without "
                               "JSON: is it an ocpar server?") from None

    def _unreachable(self, exc: Exception) -> ServerUnreachable:
        return ServerUnreachable(f"cannot reach the ocpar server at {self.url}: "
                            f"{' '.join(str(exc).split()) or type(exc).__name__}")

    def submit(self, config: str | Mapping[str, Any],
               overrides: Mapping[str, Any] | None = None,
               idempotency_key: str | None = None) -> dict:
        """Submit ``config`` (a packaged example's name, or the keys of a TOML
        configuration) with ``overrides`` (keys as ``ocpar run --set``); returns the new job's
        record, or the first job's if ``idempotency_key`` was used before by this token."""
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        body = {"config": config, "set": dict(overrides or {})}
        return self._json("POST", "/jobs", json=body, headers=headers)

    def list_jobs(self) -> list[dict]:
        """This token's jobs, newest first."""
        return self._json("GET", "/jobs")["jobs"]

    def status(self, job: str) -> dict:
        """The record of ``job``."""
        return self._json("GET", _path(job))

    def events(self, job: str, read_timeout_s: float | None = None
               ) -> Iterator[tuple[str, dict]]:
        """The job's event stream from its start: ``("progress", {"line", "superstep",
        "figures"})`` per progress line, ``("state", record)`` per change of state and last
        ``("end", record)``. The stream may stop early if the connection breaks;
        ``read_timeout_s`` (None: no limit) bounds the wait for the next bytes (then
        :class:`httpx.ReadTimeout`)."""
        timeout = httpx.Timeout(TIMEOUT_S, read=read_timeout_s)
        try:
            with self._http.stream("GET", _path(job, "events"), timeout=timeout) as response:
                if response.status_code >= 400:
                    response.read()
                    raise ServerRefused(response.status_code, _detail(response))
                yield from parse_events(response.iter_lines())
        except (httpx.ConnectError, httpx.ConnectTimeout) as exc:
            raise self._unreachable(exc) from None
        except httpx.RemoteProtocolError:  # the server went away mid-stream
            return

    def follow(self, job: str, timeout_s: float | None = None
               ) -> Iterator[tuple[str, dict]]:
        """The events of ``job`` (as :meth:`events`) until its ``("end", record)``, each
        progress line once: a broken stream is opened again (after :data:`RECONNECT_S`; a
        server that went away is tried for :data:`UNREACHABLE_S`) and the lines already
        given are skipped. :class:`TimeoutError` after ``timeout_s`` seconds (None: no
        limit)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        seen = 0  # progress events given so far
        lost = None  # since when the server cannot be reached
        while True:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise TimeoutError(f"job {job} has not ended after {timeout_s:g} s")
            count = 0
            try:
                for event, data in self.events(job, read_timeout_s=remaining):
                    lost = None
                    if event == "progress":
                        count += 1
                        if count <= seen:
                            continue
                        seen = count
                    yield event, data
                    if event == "end":
                        return
                    if deadline is not None and time.monotonic() > deadline:
                        break
            except (httpx.ReadTimeout, httpx.ReadError):
                pass
            except ServerUnreachable:
                lost = time.monotonic() if lost is None else lost
                if time.monotonic() - lost > UNREACHABLE_S:
                    raise
            time.sleep(max(0.0, min(RECONNECT_S, remaining if remaining is not None else
                                    RECONNECT_S)))

    def wait(self, job: str, timeout_s: float | None = None) -> dict:
        """Block until ``job`` is in a final state; returns its final record.
        :class:`TimeoutError` after ``timeout_s`` seconds (None: no limit)."""
        record = self.status(job)
        if record["state"] in FINAL_STATES:
            return record
        for event, data in self.follow(job, timeout_s):
            if event == "end":
                record = data
        return record

    def log(self, job: str, offset: int = 0) -> dict:
        """The job's log from byte ``offset``: ``{"offset", "next_offset", "text"}``."""
        return self._json("GET", _path(job, "log"), params={"offset": offset})

    def files(self, job: str) -> list[dict]:
        """The files of the job's output directory: ``[{"name", "size"}, ...]`` (size in
        bytes; None for a plot the server draws when it is first downloaded)."""
        return self._json("GET", _path(job, "files"))["files"]

    def download(self, job: str, name: str, path: str | Path) -> Path:
        """Write the job's output file ``name`` to ``path``; returns ``path``."""
        path = Path(path)
        try:
            with self._http.stream("GET", _path(job, "files", name)) as response:
                if response.status_code >= 400:
                    response.read()
                    raise ServerRefused(response.status_code, _detail(response))
                with open(path, "wb") as out:
                    for chunk in response.iter_bytes():
                        out.write(chunk)
        except httpx.TransportError as exc:
            raise self._unreachable(exc) from None
        return path

    def result(self, job: str, output_dir: str | Path) -> list[Path]:
        """Download every file of the job's output (``result.json``, the array file, the
        trace, the plots) into ``output_dir`` (created); returns their paths. A
        ServiceError if the job has no ``result.json`` yet."""
        files = self.files(job)
        if not any(entry["name"] == "result.json" for entry in files):
            state = self.status(job)["state"]
            raise ServiceError(f"job {job} has no result yet (state {state})")
        out = Path(output_dir)
        out.mkdir(parents=True, exist_ok=True)
        return [self.download(job, entry["name"], out / Path(entry["name"]).name)
                for entry in files]

    def cancel(self, job: str) -> None:
        """Ask ``job`` to stop at its next superstep boundary (a queued job is cancelled at
        once); its checkpoint stays for :meth:`resume`."""
        self._request("DELETE", _path(job))

    def resume(self, job: str) -> dict:
        """Run a cancelled or failed ``job`` on from its checkpoint with its own options;
        returns its record."""
        return self._json("POST", _path(job, "resume"))
