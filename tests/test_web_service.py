"""The HTTP job API (``ocpar serve``) as a client sees it: real server processes on 127.0.0.1
(``python -m ocpar serve``), requests over HTTP with httpx.

The module's server runs on the default backend, its embedded Dask cluster of 2 workers, which
the formation and MACS jobs share (a resident set's chunks of one job and another job's queue
on the same workers; pursuit jobs run serially in their warm runners); the restart test's
server runs each job as one serial process. Results are compared with ``ocpar run`` of the
same configuration, run here in this process at the same time (the machine is busy). The 20
concurrent jobs take about 50 s on 2 shared cores."""

from __future__ import annotations

import json
import os
import signal
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest
from conftest import computed, free_port, user_environment
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import ocpar
from ocpar.__main__ import main as ocpar_main
from ocpar.config import scheme_options
from ocpar.service.web import memory
from ocpar.service.web.app import SERVER_KEYS
from ocpar.service.web.events import parse_progress
from ocpar.service.web.serve import openapi_schema
from ocpar.service.web.store import FINAL, Store, Token
from ocpar.service.web.tokens import issue, revoke

REPO = Path(__file__).resolve().parents[1]
#: The five configurations each of the four tokens submits (20 jobs at once).
CONFIGS = [
    {"config": "formation-60", "set": {"agents": 8}},
    {"config": {"scheme": "formation", "agents": 10, "radius": 5.0, "outer": "sqp"}},
    {"config": "formation-60", "set": {"agents": 12, "ordering": "keep"}},
    {"config": "macs-goddard", "set": {"max_evals": 120, "seed": 1}},
    {"config": "pursuit-case1", "set": {"samples": 31, "window": 10, "update": 5,
                                       "max_agents": 20}},
]
#: A job long enough to cancel and kill (19 supersteps, ~0.25 s each serially).
LONG = {"config": "macs-goddard", "set": {"max_evals": 1000, "seed": 7}}
#: A job that outlasts a wall-time limit of 3 s on 2 Dask workers (~90 supersteps).
OVERLONG = {"config": "macs-goddard", "set": {"max_evals": 5000, "seed": 7}}


class Server:
    """``python -m ocpar serve`` on a free port of 127.0.0.1 with its state in
    ``state_dir``."""

    def __init__(self, state_dir: Path, *options: str, env: dict | None = None,
                 verify: ssl.SSLContext | bool = True) -> None:
        self.state_dir, self.options = state_dir, options
        self.env = dict(env or os.environ, OMP_NUM_THREADS="1")
        self.port = free_port()
        self.verify = verify
        self.url = f"{'https' if '--ssl-certfile' in options else 'http'}://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 120) -> Server:
        log = open(self.state_dir.parent / f"{self.state_dir.name}-server.log", "ab")  # noqa: SIM115
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ocpar", "serve", "--port", str(self.port), "--state-dir",
             str(self.state_dir), *self.options], stdout=log, stderr=log, env=self.env)
        log.close()
        deadline = time.monotonic() + timeout
        while True:
            try:
                if httpx.get(self.url + "/openapi.json", timeout=2,
                             verify=self.verify).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            assert self.proc.poll() is None, "the server exited: " + self.log()
            assert time.monotonic() < deadline, "the server did not answer: " + self.log()
            time.sleep(0.2)

    def log(self) -> str:
        return (self.state_dir.parent / f"{self.state_dir.name}-server.log").read_text()

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def client(self, token: str | None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=60, verify=self.verify)


def add_token(state_dir: Path, name: str, **limits) -> str:
    return issue(Store(state_dir), Token(name, **limits))


@pytest.fixture(scope="module")
def server(tmp_path_factory, user_package) -> Iterator[tuple[Server, dict[str, str]]]:
    """A server on the default backend (its embedded Dask cluster of 2 workers) running 4 jobs
    at once (jobs' memory estimates up to 0.3 GB), with tokens a-d (at most 2 running
    jobs each; d with small per-job limits) and w (3 s of wall time per job) issued before
    it starts; it allows the problem references of the test package ``mypkg`` (importable
    there) in modules problems and broken."""
    state = tmp_path_factory.mktemp("web") / "state"
    state.mkdir()
    proc = subprocess.run([sys.executable, "-m", "ocpar", "serve", "token", "add", "a",
                           "--max-jobs", "2", "--state-dir", str(state)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    tokens = {"a": proc.stdout.strip()}
    tokens |= {name: add_token(state, name, max_jobs=2) for name in "bc"}
    tokens["d"] = add_token(state, "d", max_jobs=2, max_agents=20, max_evaluations=1000)
    tokens["w"] = add_token(state, "w", wall_time=3.0)
    listed = subprocess.run([sys.executable, "-m", "ocpar", "serve", "token", "list",
                             "--state-dir", str(state)], capture_output=True, text=True)
    lines = listed.stdout.splitlines()
    # the defaults of the limits not given: 100,000 agents and evaluations, 3,600 s
    assert lines[0] == "a" + " " * 24 + "max-jobs 2, max-agents 100000, max-evaluations " \
        "100000, wall-time 3600", listed.stdout
    assert lines[-1].split(None, 1) == ["w", "max-jobs 2, max-agents 100000, max-evaluations "
                                        "100000, wall-time 3"], listed.stdout
    assert tokens["a"] not in listed.stdout and tokens["a"] not in (state / "server.sqlite3"
                                                                    ).read_bytes().decode(
        errors="replace")
    srv = Server(state, "--max-running", "4", "--max-job-memory", "0.3", "--allow-problem",
                 "mypkg.problems:*", "--allow-problem", "mypkg.broken:*",
                 "--wall-time-grace", "20", env=user_environment(user_package)).start()
    yield srv, tokens
    srv.stop()


def wait_final(client: httpx.Client, job_id: str, timeout: float = 240) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        record = client.get(f"/jobs/{job_id}").json()
        if record["state"] in FINAL:
            return record
        assert time.monotonic() < deadline, record
        time.sleep(0.3)


def wait_supersteps(client: httpx.Client, job_id: str, count: int) -> dict:
    deadline = time.monotonic() + 120
    while (record := client.get(f"/jobs/{job_id}").json())["supersteps"] < count:
        assert record["state"] not in FINAL, record
        assert time.monotonic() < deadline, record
        time.sleep(0.1)
    return record


def toml_value(value) -> str:
    return json.dumps(value) if not isinstance(value, bool) else str(value).lower()


def run_direct(request: dict, out: Path) -> dict:
    """``ocpar run`` of the request's configuration (serially, here): result.json."""
    config = request["config"]
    if isinstance(config, dict):
        path = out.with_suffix(".toml")
        path.write_text("".join(f"{key} = {toml_value(value)}\n"
                                for key, value in config.items()))
        config = str(path)
    sets = [f"{key}={toml_value(value)}" for key, value in request.get("set", {}).items()]
    assert ocpar_main(["run", config, "--set", *sets, f"output={out}", "quiet=true"]) == 0
    return json.loads((out / "result.json").read_text())


def assert_bitwise_equal(got, expected) -> None:
    """Two runs' array files hold the same variables with the same bits (the attributes,
    which carry run-time figures such as the backend and wall time, are not compared)."""
    assert sorted(got.variables) == sorted(expected.variables)
    for name in expected.variables:
        a, b = got[name].values, expected[name].values
        assert a.dtype == b.dtype and a.shape == b.shape, name
        if a.dtype.kind == "O":
            assert a.tolist() == b.tolist(), name
        else:
            assert a.tobytes() == b.tobytes(), name


def fetch_result(client: httpx.Client, job_id: str) -> dict:
    response = client.get(f"/jobs/{job_id}/files/result.json")
    assert response.status_code == 200, response.text
    return response.json()


def test_twenty_jobs_from_four_tokens_equal_their_direct_runs(server, tmp_path):
    """Each of 4 tokens submits the 5 configurations at once (20 concurrent requests): every
    job succeeds with the result of ``ocpar run`` of its configuration; no token had more
    than 2 jobs running at once, the server no more than 4; each token sees its 5 jobs."""
    srv, all_tokens = server
    tokens = {name: all_tokens[name] for name in "abcd"}
    submitted: dict[str, list[tuple[int, dict]]] = {name: [] for name in tokens}
    errors: list[str] = []

    def submit(name: str, index: int) -> None:
        with srv.client(tokens[name]) as client:
            response = client.post("/jobs", json=CONFIGS[index])
        if response.status_code != 201:
            errors.append(f"{name} {index}: {response.status_code} {response.text}")
        else:
            submitted[name].append((index, response.json()))

    threads = [threading.Thread(target=submit, args=(name, index))
               for name in tokens for index in range(len(CONFIGS))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert all(record["state"] in ("queued", "running") for jobs in submitted.values()
               for _, record in jobs)

    expected = [computed(run_direct(config, tmp_path / f"direct-{k}"))
                for k, config in enumerate(CONFIGS)]
    expected_arrays = [ocpar.load(tmp_path / f"direct-{k}").dataset
                       for k in range(len(CONFIGS))]
    finals = []
    for name, jobs in submitted.items():
        with srv.client(tokens[name]) as client:
            listed = client.get("/jobs").json()["jobs"]
            assert sorted(r["id"] for r in listed) == sorted(r["id"] for _, r in jobs)
            for index, record in jobs:
                final = wait_final(client, record["id"])
                assert final["state"] == "succeeded", final
                assert final["result_status"] == "converged" and final["reason"] is None
                assert "result.json" in final["files"]
                result = fetch_result(client, record["id"])
                # pursuit's supersteps are smaller than a round trip to the workers
                assert (result["backend"], result["workers"]) == (
                    ("serial", 1) if result["scheme"] == "pursuit" else ("dask", 2))
                assert computed(result) == expected[index], (name, index)
                assert final["supersteps"] >= result["supersteps"] > 0  # checkpointed ones
                arrays = client.get(f"/jobs/{record['id']}/files/{result['arrays']}")
                assert arrays.status_code == 200
                downloaded = tmp_path / f"{record['id']}.nc"
                downloaded.write_bytes(arrays.content)
                assert_bitwise_equal(ocpar.load(downloaded).dataset, expected_arrays[index])
                finals.append((name, final))
                if index in (0, 4):  # the events of a formation and a pursuit job
                    check_events(client, record["id"], result)
    intervals = [(name, _epoch(f["started"]), _epoch(f["finished"])) for name, f in finals]
    for _, start, _ in intervals:
        running = [name for name, s, e in intervals if s <= start < e]
        assert len(running) <= 4
        assert all(running.count(name) <= 2 for name in running)


def read_events(client: httpx.Client, job_id: str) -> list[tuple[str, dict]]:
    """The server-sent events of a job (read until the stream ends)."""
    text = client.get(f"/jobs/{job_id}/events", timeout=60).text
    events = []
    for block in filter(None, text.strip().split("\n\n")):
        name, data = block.split("\n")
        events.append((name.removeprefix("event: "), json.loads(data.removeprefix("data: "))))
    return events


def check_events(client: httpx.Client, job_id: str, result: dict) -> None:
    """A finished job's events: its progress lines in order, supersteps counting from 0,
    the last figure equal to the result (to the printed digits), one end event last."""
    events = read_events(client, job_id)
    assert [name for name, _ in events][-1] == "end" and events[-1][1]["state"] == "succeeded"
    progress = [data for name, data in events if name == "progress"]
    steps = [p["superstep"] for p in progress if p["superstep"] is not None]
    assert steps == list(range(len(steps))) and len(steps) >= result["supersteps"] - 1
    log = client.get(f"/jobs/{job_id}/log").json()["text"]
    assert [p["line"] for p in progress] == [line for line in log.splitlines() if line.strip()]
    if result["scheme"] == "formation":
        last = [p["figures"]["cost"] for p in progress if "cost" in p["figures"]][-1]
        assert last == pytest.approx(result["total_cost"], rel=1e-12)
    else:
        masses = [p["figures"]["last final mass"] for p in progress
                  if "last final mass" in p["figures"]]
        assert masses[-1] == pytest.approx(result["train_final_mass_kg"], abs=1e-6)


@pytest.mark.parametrize(("line", "superstep", "figures"), [
    ("superstep    3  cost 1.470244198995e+07  equidistance 7.4e-16 rad  wall     1.5 ms  "
     "overhead    0.3 ms", 3, {"cost": 1.470244198995e+07, "equidistance": 7.4e-16,
                               "wall": 1.5, "overhead": 0.3}),
    ("superstep     5  agents in flight   3  finished     1  last final mass 512.795059 kg  "
     "wall   11.1 ms", 5, {"agents in flight": 3, "finished": 1, "last final mass": 512.795059,
                           "wall": 11.1}),
    ("iteration    2  evaluations    218  archive  10  hypervolume 0.763327", None,
     {"iteration": 2, "evaluations": 218, "archive": 10, "hypervolume": 0.763327}),
    ("status converged (|sum of dJ/dphi_i| below tolerance)", None, {}),
])
def test_progress_lines_of_the_three_schemes_give_their_figures(line, superstep, figures):
    assert parse_progress(line) == (superstep, figures)


def _epoch(text: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def test_tokens_ownership_and_request_limits(server, tmp_path):
    """401 without or with a wrong token, 403 on another token's job, 404 for no such job,
    409 on cancelling or resuming a finished job, 413 over 64 KiB, the idempotency key, the
    allow-list of problem references and the per-token limits (422 naming the key)."""
    srv, tokens = server
    anonymous, a, b, d = (srv.client(None), srv.client(tokens["a"]), srv.client(tokens["b"]),
                          srv.client(tokens["d"]))
    assert anonymous.get("/jobs").status_code == 401
    assert anonymous.post("/jobs", json=CONFIGS[0]).status_code == 401
    assert srv.client("ocpar_not-a-token").get("/jobs").status_code == 401
    assert anonymous.get("/").status_code == 200  # the page needs no token

    first = a.post("/jobs", json=CONFIGS[0], headers={"Idempotency-Key": "k1"})
    assert first.status_code == 201
    job = first.json()["id"]
    again = a.post("/jobs", json=CONFIGS[0], headers={"Idempotency-Key": "k1"})
    assert again.status_code == 200 and again.json()["id"] == job
    other = b.post("/jobs", json=CONFIGS[0], headers={"Idempotency-Key": "k1"})
    assert other.status_code == 201 and other.json()["id"] != job  # keys are per token

    for method, path in (("GET", ""), ("GET", "/log"), ("GET", "/files"), ("GET", "/events"),
                         ("GET", "/files/result.json"), ("DELETE", ""), ("POST", "/resume")):
        assert b.request(method, f"/jobs/{job}{path}").status_code == 403, (method, path)
        assert b.request(method, f"/jobs/formation-20000101-000000-abcdef{path}"
                         ).status_code == 404
    assert a.get("/jobs/../../etc/passwd").status_code == 404
    assert a.get("/jobs/not-a-job").status_code == 404

    final = wait_final(a, job)
    assert final["state"] == "succeeded"
    assert a.delete(f"/jobs/{job}").status_code == 409
    assert a.post(f"/jobs/{job}/resume").status_code == 409
    assert a.get(f"/jobs/{job}/files/nothing.png").status_code == 404
    assert a.get(f"/jobs/{job}/files/..%2Fstate.json").status_code == 404
    log = a.get(f"/jobs/{job}/log").json()
    rest = a.get(f"/jobs/{job}/log", params={"offset": 10}).json()
    assert log["offset"] == 0 and log["next_offset"] == len(log["text"].encode())
    assert rest["text"] == log["text"][10:] and "superstep" in log["text"]
    assert {f["name"] for f in a.get(f"/jobs/{job}/files").json()["files"]} == \
        set(final["files"])

    big = {"config": {"scheme": "formation"}, "set": {"radius": 1.0}, "pad": "x" * 70_000}
    assert a.post("/jobs", json=big).status_code == 413
    assert a.post("/jobs", content=b"{" * 65_537,
                  headers={"Content-Type": "application/json"}).status_code == 413

    refused = {
        "agents": (d, {"config": "formation-60"}),                    # 60 > 20
        "max_agents": (d, {"config": "pursuit-case1"}),               # 100000 > 20
        "max_evals": (d, {"config": "macs-goddard"}),                 # 10000 > 1000
        "problem": (a, {"config": {"scheme": "formation", "problem": "os:system"}}),
        "output": (a, {"config": "formation-60", "set": {"output": "/tmp/x"}}),
    }
    for key, (client, body) in refused.items():
        response = client.post("/jobs", json=body)
        assert response.status_code == 422, (key, response.text)
        assert key in response.json()["detail"], response.text
    assert d.post("/jobs", json={"config": "formation-60", "set": {"agents": 20}}
                  ).status_code == 201


def test_a_job_that_kills_its_runner_fails_alone_and_jobs_run_on_warm(server):
    """A job whose process dies (os._exit, SIGSEGV) ends failed with the exit and its log's
    last line, and the server runs on; jobs one after another run in one warm process (no
    interpreter's start-up in their timings), never in a dead one."""
    srv, tokens = server
    client, store = srv.client(tokens["c"]), Store(srv.state_dir)
    crashed = []
    for how, reason in (("exit", "exit status 3: crash_in_job: exit"),
                        ("segfault", f"killed by signal {int(signal.SIGSEGV)}: crash_in_job: "
                                     "segfault")):
        response = client.post("/jobs", json={"config": {
            "scheme": "formation", "problem": "mypkg.problems:crash_in_job",
            "problem_args": {"how": how}}})
        assert response.status_code == 201, response.text
        final = wait_final(client, response.json()["id"])
        assert (final["state"], final["reason"]) == ("failed", reason), final
        crashed.append(store.job(final["id"])["pid"])
    pids = []
    for _ in range(3):
        final = wait_final(client, client.post("/jobs", json=CONFIGS[0]).json()["id"])
        assert final["state"] == "succeeded", final
        assert fetch_result(client, final["id"])["timings"]["startup_s"] < 0.5
        pids.append(store.job(final["id"])["pid"])
    assert len(set(pids)) < len(pids) and not set(pids) & set(crashed), (pids, crashed)


def test_a_jobs_plot_is_drawn_when_first_fetched_as_a_direct_run_draws_it(server, tmp_path):
    """The server says it is ready; a job draws no plot (no picture time in its timings):
    its plot is listed without a size until the first GET draws it, with the pixels of
    ``ocpar run``'s plot of the same configuration; the second GET serves the same bytes."""
    from PIL import Image

    srv, tokens = server
    deadline = time.monotonic() + 120
    while (health := httpx.get(srv.url + "/health")).status_code == 503:
        assert health.json() == {"ready": False} and time.monotonic() < deadline
        time.sleep(0.1)
    assert health.json() == {"ready": True}
    client = srv.client(tokens["c"])
    final = wait_final(client, client.post("/jobs", json=CONFIGS[2]).json()["id"])
    assert final["state"] == "succeeded", final
    assert "picture_s" not in fetch_result(client, final["id"])["timings"]
    listed = {f["name"]: f["size"] for f in client.get(f"/jobs/{final['id']}/files").json()[
        "files"]}
    assert listed["formation.png"] is None and listed["result.json"] > 0
    drawn = client.get(f"/jobs/{final['id']}/files/formation.png")
    assert drawn.status_code == 200, drawn.text
    assert client.get(f"/jobs/{final['id']}/files/formation.png").content == drawn.content
    listed = {f["name"]: f["size"] for f in client.get(f"/jobs/{final['id']}/files").json()[
        "files"]}
    assert listed["formation.png"] == len(drawn.content)
    run_direct(CONFIGS[2], tmp_path / "direct")
    (tmp_path / "served.png").write_bytes(drawn.content)
    with Image.open(tmp_path / "served.png") as served, \
            Image.open(tmp_path / "direct" / "formation.png") as direct:
        assert served.size == direct.size
        assert served.tobytes() == direct.tobytes()


def test_a_job_over_the_memory_limit_is_refused_naming_estimate_and_limit(server):
    """The module's server allows 0.3 GB per job: 50,000 agents (112 MiB + 3.9 KB each:
    0.312 GB) are refused before a job exists, 40,000 (0.273 GB) pass that check."""
    srv, tokens = server
    client = srv.client(tokens["c"])
    before = len(client.get("/jobs").json()["jobs"])
    response = client.post("/jobs", json={"config": "formation-60", "set": {"agents": 50_000}})
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == (
        "memory: a formation job of 50,000 agents needs about 0.312 GB at its peak, above "
        "this server's limit of 0.3 GB per job (ocpar serve --max-job-memory)")
    assert len(client.get("/jobs").json()["jobs"]) == before
    assert memory.check("formation", SimpleNamespace(agents=40_000), None, 300_000_000) is None


@pytest.mark.parametrize(("scheme", "units", "measured_mib"), [
    ("formation", 2, 110.9), ("formation", 10_000, 127.8), ("formation", 40_000, 237.7),
    ("pursuit", 301, 172.4), ("pursuit", 1_201, 204.4), ("pursuit", 2_401, 247.1),
    ("macs", 100, 190.9), ("macs", 8_000, 191.0)])
def test_memory_estimates_lie_within_20_percent_above_the_measured_peaks(
        scheme, units, measured_mib):
    """The peaks of serial runs (scripts/job_memory.py, ru_maxrss) against the model."""
    estimate = memory.estimate(scheme, units) / 2**20
    assert measured_mib <= estimate <= 1.2 * measured_mib, estimate


def test_revoking_a_token_refuses_it_and_stops_its_jobs(server, tmp_path):
    """``ocpar serve token revoke`` beside a running server: the token gets 401 at once; in
    a store, its queued job is cancelled and its running one asked to stop (the stop file);
    another token's jobs are untouched; an unknown name is one line and exit status 2."""
    srv, _ = server
    secret = add_token(srv.state_dir, "r")
    assert srv.client(secret).get("/jobs").status_code == 200
    assert ocpar_main(["serve", "token", "revoke", "r", "--state-dir", str(srv.state_dir)]) == 0
    assert srv.client(secret).get("/jobs").status_code == 401

    store = Store(tmp_path / "state")
    add_token(store.state_dir, "x")
    for job_id, owner, state in (("formation-20260101-000000-000001", "x", "queued"),
                                 ("formation-20260101-000000-000002", "x", "running"),
                                 ("formation-20260101-000000-000003", "y", "queued")):
        store.job_dir(job_id).mkdir()
        store.add_job({"id": job_id, "owner": owner, "scheme": "formation", "problem": "p",
                       "config": {}, "argv": [], "state": state, "submitted": time.time()})
    done = revoke(store, "x")
    assert done.cancelled == ["formation-20260101-000000-000001"]
    assert done.stopping == ["formation-20260101-000000-000002"]
    rows = {row["id"][-1]: row for row in store.jobs()}
    assert (rows["1"]["state"], rows["1"]["reason"]) == ("cancelled",
                                                         "its token 'x' was revoked")
    assert (rows["2"]["state"], rows["2"]["stop_reason"]) == ("running",
                                                              "its token 'x' was revoked")
    assert (store.job_dir(rows["2"]["id"]) / "cancel").exists()
    assert rows["3"]["state"] == "queued" and store.token("x") is None
    proc = subprocess.run([sys.executable, "-m", "ocpar", "serve", "token", "revoke", "x",
                           "--state-dir", str(store.state_dir)], capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip() == (
        "ocpar serve token revoke: error: no token named 'x' (ocpar serve token list shows "
        "them)")


def test_allow_list_of_problem_references(server):
    """A reference matching --allow-problem is loaded before a job id is returned (one that
    does not give a problem is a 422) and runs; any other is refused unloaded."""
    srv, tokens = server
    client = srv.client(tokens["c"])
    before = len(client.get("/jobs").json()["jobs"])
    ok = client.post("/jobs", json={"config": {"scheme": "formation", "problem":
                                               "mypkg.problems:make_formation"}})
    assert ok.status_code == 201, ok.text
    for reference, needle in (("mypkg.other:make", "not allowed"),
                              ("mypkg.problems:nothing", "has no attribute"),
                              ("mypkg.broken:make", "importing mypkg.broken raised"),
                              ("mypkg.problems:make_macs", "returned an object")):
        response = client.post("/jobs", json={"config": {"scheme": "formation",
                                                         "problem": reference}})
        assert response.status_code == 422 and needle in response.json()["detail"], \
            response.text
    final = wait_final(client, ok.json()["id"])
    assert final["state"] == "succeeded" and final["problem"] == "mypkg.problems:make_formation"
    assert len(client.get("/jobs").json()["jobs"]) == before + 1


# malformed configurations: each has one entry that cannot run ------------------------------

SCHEME_NAMES = ("formation", "pursuit", "macs")
JSON_SCALARS = st.one_of(st.booleans(), st.integers(-10**6, 10**6),
                         st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=8))


@st.composite
def malformed(draw) -> tuple[dict, str | None]:
    """A request body with one bad entry, and the key the error must name (None: any)."""
    scheme = draw(st.sampled_from(SCHEME_NAMES))
    options = scheme_options(scheme)
    kind = draw(st.sampled_from(["type", "unknown", "server", "null", "range", "scheme",
                                 "body"]))
    if kind == "scheme":
        return {"config": {"scheme": draw(st.text(max_size=10).filter(
            lambda s: s not in SCHEME_NAMES))}}, "scheme"
    if kind == "body":
        return draw(st.one_of(st.lists(JSON_SCALARS, max_size=3), JSON_SCALARS,
                              st.just({"config": "formation-60", "set": [1]}),
                              st.just({"config": 3}), st.just({"conf": "formation-60"}))), None
    where = draw(st.sampled_from(["config", "set"]))
    if kind == "type":
        key = draw(st.sampled_from(sorted(k for k, o in options.items()
                                          if o.kind in ("integer", "number", "flag"))))
        kind_of = options[key].kind
        value = draw(JSON_SCALARS.filter(
            lambda v: (isinstance(v, str) or isinstance(v, bool) != (kind_of == "flag")
                       or (kind_of == "integer" and isinstance(v, float)))))
    elif kind == "unknown":
        key = draw(st.from_regex(r"[a-z_]{1,12}", fullmatch=True).filter(
            lambda k: k not in options and k != "scheme"))
        value = draw(JSON_SCALARS)
    elif kind == "server":
        key, value = draw(st.sampled_from(sorted(SERVER_KEYS))), draw(JSON_SCALARS)
    elif kind == "null":
        key, value = draw(st.sampled_from(sorted(options))), None
    else:
        key = {"formation": "agents", "pursuit": "samples", "macs": "population"}[scheme]
        value = draw(st.sampled_from([0, -1, -10**9, 10**9]))
    entry = {key: value}
    body = ({"config": {"scheme": scheme, **entry}} if where == "config" else
            {"config": {"scheme": scheme}, "set": entry})
    return body, key


@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=malformed())
def test_malformed_configurations_get_422_naming_the_key(server, case):
    """Every malformed configuration is a 422 with one line naming its key, and no job."""
    srv, tokens = server
    body, key = case
    with srv.client(tokens["c"]) as client:
        before = len(client.get("/jobs").json()["jobs"])
        response = client.post("/jobs", json=body)
        assert response.status_code == 422, (body, response.text)
        detail = response.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail and 0 < len(detail) < 600
        if key is not None:
            assert key in detail or f"--{key.replace('_', '-')}" in detail, (body, detail)
        assert len(client.get("/jobs").json()["jobs"]) == before


# cancel, resume, restart, wall time ---------------------------------------------------------

@pytest.fixture(scope="module")
def long_expected(tmp_path_factory) -> dict:
    """The uninterrupted result of :data:`LONG`."""
    return computed(run_direct(LONG, tmp_path_factory.mktemp("long") / "direct"))


def test_cancel_lands_within_one_superstep_and_resume_finishes_it(server, long_expected):
    srv, tokens = server
    client = srv.client(tokens["b"])
    job = client.post("/jobs", json=LONG).json()["id"]
    wait_supersteps(client, job, 3)
    assert client.delete(f"/jobs/{job}").status_code == 204
    at_cancel = client.get(f"/jobs/{job}").json()["supersteps"]
    final = wait_final(client, job)
    assert final["state"] == "cancelled" and final["reason"] == "cancelled by request"
    assert at_cancel <= final["supersteps"] <= at_cancel + 1
    assert final["supersteps"] < long_expected["supersteps"]
    assert client.delete(f"/jobs/{job}").status_code == 409

    resumed = client.post(f"/jobs/{job}/resume")
    assert resumed.status_code == 202 and resumed.json()["state"] == "queued"
    final = wait_final(client, job)
    assert final["state"] == "succeeded", final
    assert computed(fetch_result(client, job)) == long_expected

    events = client.get(f"/jobs/{job}/events", timeout=30).text
    blocks = [block for block in events.strip().split("\n\n") if block]
    names = [block.split("\n")[0].removeprefix("event: ") for block in blocks]
    assert names[-1] == "end" and names.count("end") == 1 and "state" in names
    progress = [json.loads(block.split("\n")[1].removeprefix("data: ")) for block in blocks
                if block.startswith("event: progress")]
    iterations = [p for p in progress if "hypervolume" in p["figures"]]
    assert len(iterations) >= 3 and all(p["superstep"] is None for p in iterations)
    counts = [int(p["figures"]["iteration"]) for p in iterations]
    assert counts.count(1) == 2  # the log holds the cancelled run, then the resumed one
    resumed = counts[len(counts) - 1 - counts[::-1].index(1):]
    assert resumed == list(range(1, len(resumed) + 1)) and len(resumed) > counts.index(1, 1)


def test_a_killed_server_resumes_its_running_job_on_restart(tmp_path, long_expected):
    """SIGKILL the server during a run (its run frozen with SIGSTOP, a survivor that must
    not write on); the restarted server kills what is left of the run, resumes it from its
    checkpoint and it finishes with the uninterrupted result."""
    state = tmp_path / "state"
    state.mkdir()
    token = add_token(state, "k")
    srv = Server(state, "--backend", "serial").start()
    try:
        client = srv.client(token)
        job = client.post("/jobs", json=LONG).json()["id"]
        wait_supersteps(client, job, 4)
        pid = Store(state).job(job)["pid"]
        os.killpg(pid, signal.SIGSTOP)
        srv.stop(signal.SIGKILL)
        frozen = json.loads((state / "jobs" / job / "checkpoint" / "manifest.json"
                             ).read_text())["supersteps"]
        srv.start()
        client = srv.client(token)
        record = client.get(f"/jobs/{job}").json()
        assert record["state"] in ("queued", "running") and "restarted" in record["reason"]
        assert not Path(f"/proc/{pid}/cmdline").read_bytes() if Path(f"/proc/{pid}").exists() \
            else True  # the survivor was killed (gone, or a zombie not yet reaped)
        final = wait_final(client, job)
        assert final["state"] == "succeeded", final
        assert computed(fetch_result(client, job)) == long_expected
        assert final["reason"] == record["reason"] == (
            f"the server restarted; resumed from its checkpoint after {frozen} superstep(s)")
        assert 4 <= frozen < final["supersteps"]
    finally:
        srv.stop()


def test_a_job_over_its_wall_time_is_cancelled_and_marked(server):
    srv, tokens = server
    client = srv.client(tokens["w"])
    job = client.post("/jobs", json=OVERLONG).json()["id"]
    final = wait_final(client, job)
    assert final["state"] == "cancelled", final
    assert final["reason"] == "wall-time limit of 3 s exceeded"
    ran = _epoch(final["finished"]) - _epoch(final["started"])
    assert 3.0 <= ran < 20.0  # stopped at a superstep boundary, not killed after the grace


@pytest.mark.slow  # (HTTPS from the client's side: test_http_client.py)
def test_https_with_the_operators_certificate(tmp_path):
    """--ssl-certfile/--ssl-keyfile: the API over TLS (a client trusting the CA gets in with
    its token; plain HTTP gets no answer)."""
    from test_tls import make_certificates

    certs = make_certificates(tmp_path / "certs", ("server",))
    trust = ssl.create_default_context(cafile=str(certs / "ca.pem"))
    trust.check_hostname = False  # the test CA's certificate names no host
    state = tmp_path / "state"
    state.mkdir()
    token = add_token(state, "t")
    srv = Server(state, "--backend", "serial", "--ssl-certfile", str(certs / "server.pem"),
                 "--ssl-keyfile", str(certs / "server.key"), verify=trust).start()
    try:
        assert srv.client(token).get("/jobs").json() == {"jobs": []}
        assert srv.client(None).get("/jobs").status_code == 401
        with pytest.raises(httpx.HTTPError):
            httpx.get(srv.url.replace("https", "http") + "/jobs", timeout=5)
        with pytest.raises(httpx.HTTPError):  # nor with a client that does not trust it
            httpx.get(srv.url + "/jobs", timeout=5)
    finally:
        srv.stop()


def test_the_published_openapi_schema_is_the_servers():
    published = json.loads((REPO / "docs" / "openapi.json").read_text())
    assert published == openapi_schema()
    paths = published["paths"]
    assert {"/jobs", "/jobs/{job_id}", "/jobs/{job_id}/events", "/jobs/{job_id}/log",
            "/jobs/{job_id}/files", "/jobs/{job_id}/files/{name}",
            "/jobs/{job_id}/resume"} <= set(paths)
