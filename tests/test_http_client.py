"""The command line on an HTTP job server: a real ``ocpar serve`` on 127.0.0.1 (serial backend,
one job at a time), driven by ``ocpar submit|status|wait|result|cancel|jobs --server URL
--token T`` (ocpar.__main__.main in this process) and checked against the server's own job
directories on disk."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import REPO, free_port, stop_processes, wait_for_port

from ocpar.__main__ import EXIT_TIMEOUT, main
from ocpar.results import EXIT_STATUS
from ocpar.service.http_client import FINAL_STATES, ServerRefused, parse_events


def ocpar(*args: str) -> SimpleNamespace:
    """``ocpar ARGS`` in this process: its exit status, stdout and stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(list(args))
        except SystemExit as exc:
            code = exc.code
    return SimpleNamespace(code=code, out=out.getvalue(), err=err.getvalue())


def one_line_error(proc: SimpleNamespace, command: str, *needles: str) -> str:
    """The single stderr line of a refused command (exit status 2, nothing on stdout)."""
    lines = proc.err.strip().splitlines()
    assert proc.code == 2 and proc.out == "" and len(lines) == 1, proc
    assert lines[0].startswith(f"ocpar {command}: error: "), lines
    for needle in needles:
        assert needle in lines[0], lines
    return lines[0]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``ocpar serve --backend serial --max-running 1`` with the tokens of alice, bob and
    carol."""
    state = tmp_path_factory.mktemp("server")
    env = dict(os.environ, OMP_NUM_THREADS="1")
    tokens = {}
    for name in ("alice", "bob", "carol"):
        issued = ocpar("serve", "token", "add", name, "--state-dir", str(state))
        assert issued.code == 0, issued
        tokens[name] = issued.out.strip()
    port = free_port()
    log = open(state / "serve.log", "wb")  # noqa: SIM115 (closed below)
    proc = subprocess.Popen([sys.executable, "-m", "ocpar", "serve", "--port", str(port),
                             "--state-dir", str(state), "--backend", "serial",
                             "--max-running", "1"], env=env, cwd=REPO, stdout=log,
                            stderr=subprocess.STDOUT)
    try:
        wait_for_port(port, proc, 60, lambda: (state / "serve.log").read_text())
        url = f"http://127.0.0.1:{port}"
        yield SimpleNamespace(url=url, state=state, tokens=tokens,
                              as_alice=["--server", url, "--token", tokens["alice"]])
    finally:
        stop_processes([proc])
        log.close()


@pytest.fixture(scope="module")
def jobs(server, tmp_path_factory):
    """Three jobs of alice, one at a time: the 60-agent formation by name (it converges), the
    same from a TOML file with one outer iteration (not converged: the job fails) and a MACS
    run that waits in the queue behind them and carol's longer MACS run (the ``blocker``)
    until test_wait_gives_up_after_its_timeout cancels both (a warm server runs the two
    formations within a second)."""
    config = tmp_path_factory.mktemp("config") / "short.toml"
    config.write_text('scheme = "formation"\nproblem = "point-mass-plane"\nagents = 60\n'
                      'max_outer_iterations = 1\noutput = "ignored: the service sets it"\n')
    ids = {}
    as_carol = ["--server", server.url, "--token", server.tokens["carol"]]
    for name, args, who in (
            ("converged", ["formation-60"], server.as_alice),
            ("short", [str(config)], server.as_alice),
            ("blocker", ["macs-goddard", "--set", "max_evals=5000"], as_carol),
            ("cancelled", ["macs-goddard", "--set", "max_evals=3000"], server.as_alice)):
        proc = ocpar("submit", *args, *who)
        assert proc.code == 0 and proc.err == "", proc
        ids[name] = proc.out.strip()
    assert len(set(ids.values())) == 4
    return ids


def test_wait_gives_up_after_its_timeout(server, jobs):
    """The MACS job waits behind the two formation runs: ``wait --timeout`` gives up; a
    queued job's cancel is at once, and ``wait`` then exits with a cancelled run's status."""
    job = jobs["cancelled"]
    proc = ocpar("wait", job, "--timeout", "0.5", *server.as_alice)
    assert proc.code == EXIT_TIMEOUT and proc.out == "", proc
    assert proc.err.strip() == f"ocpar wait: job {job} has not ended after 0.5 s"
    proc = ocpar("cancel", job, *server.as_alice)
    assert proc.code == 0 and "cancel requested" in proc.out, proc
    proc = ocpar("wait", job, "--timeout", "60", *server.as_alice)
    assert proc.code == EXIT_STATUS["cancelled"] == 4, proc
    assert " cancelled " in proc.out
    record = json.loads(ocpar("status", job, "--json", *server.as_alice).out)
    assert record["started"] is None and record["supersteps"] == 0  # it never ran
    proc = ocpar("cancel", jobs["blocker"], "--server", server.url, "--token",
                 server.tokens["carol"])
    assert proc.code == 0, proc


def test_submit_wait_result_gives_the_files_the_server_holds(server, jobs, tmp_path):
    proc = ocpar("wait", jobs["converged"], *server.as_alice)
    assert proc.code == 0, proc
    assert proc.out.startswith(jobs["converged"]) and " succeeded " in proc.out
    out = tmp_path / "fetched"
    proc = ocpar("result", jobs["converged"], "--output", str(out), *server.as_alice)
    assert proc.code == 0 and proc.out.startswith("wrote "), proc
    held = server.state / "jobs" / jobs["converged"] / "output"
    names = sorted(p.name for p in held.iterdir())
    assert "result.json" in names and any(name.endswith(".png") for name in names)
    assert sorted(p.name for p in out.iterdir()) == names
    for name in names:
        assert (out / name).read_bytes() == (held / name).read_bytes(), name
    summary = json.loads((out / "result.json").read_text())
    assert summary["status"] == "converged"
    assert summary["total_cost"] == pytest.approx(1.470244198995e+07, rel=1e-12)
    record = json.loads(ocpar("status", jobs["converged"], "--json", *server.as_alice).out)
    assert record["state"] == "succeeded" and record["result_status"] == "converged"
    assert record["supersteps"] == summary["supersteps"]


def test_status_follow_prints_the_progress_lines_of_the_jobs_log(server, jobs):
    """Followed from while it waits or runs to its end: the job's log, line by line, with a
    line at each change of state."""
    job = jobs["short"]
    proc = ocpar("status", job, "--follow", *server.as_alice)
    assert proc.code == 0 and proc.err == "", proc
    lines = proc.out.splitlines()
    states = [line for line in lines if line.startswith(job)]
    progress = [line for line in lines if not line.startswith(job)]
    log = (server.state / "jobs" / job / "log.txt").read_text()
    assert progress == [line for line in log.splitlines() if line.strip()]
    assert any(line.startswith("superstep    1  cost ") for line in progress)
    assert " failed " in states[-1] and len(set(states)) == len(states)


def test_wait_exits_with_the_runs_exit_status(server, jobs):
    proc = ocpar("wait", jobs["short"], *server.as_alice)
    assert proc.code == EXIT_STATUS["not_converged"] == 1, proc
    assert " failed " in proc.out and "not converged: iteration limit reached" in proc.out


def test_jobs_lists_the_callers_jobs_from_the_environment(server, jobs, monkeypatch):
    monkeypatch.setenv("OCPAR_SERVER", server.url)
    monkeypatch.setenv("OCPAR_TOKEN", server.tokens["alice"])
    proc = ocpar("jobs")
    assert proc.code == 0, proc
    header, *rows = proc.out.splitlines()
    assert header.startswith("# id, scheme, problem, state")
    for name in ("converged", "short", "cancelled"):  # alice's (the blocker is carol's)
        assert sum(row.startswith(jobs[name]) for row in rows) == 1
    monkeypatch.setenv("OCPAR_TOKEN", server.tokens["bob"])
    assert ocpar("jobs").out.splitlines()[1:] == []  # bob's own: none


def test_the_same_idempotency_key_gives_the_same_job(server):
    key = ["--idempotency-key", "retry-7"]
    first = ocpar("submit", "formation-60", *key, *server.as_alice)
    again = ocpar("submit", "formation-60", *key, *server.as_alice)
    assert first.code == again.code == 0 and first.out == again.out
    cancel = ocpar("cancel", first.out.strip(), *server.as_alice)  # a warm server may be done
    assert cancel.code == 0 or "is already succeeded (HTTP 409)" in cancel.err


@pytest.mark.parametrize(("args", "needles"), [
    (["--set", "agents=1"], ["agents"]),
    (["--set", "agnets=12"], ["agnets"]),
    (["--set", "output=/tmp/x"], ["output"]),
])
def test_a_malformed_configuration_is_one_line_and_exit_2(server, args, needles):
    proc = ocpar("submit", "formation-60", *args, *server.as_alice)
    one_line_error(proc, "submit", *needles, "(HTTP 422)")


def test_tokens_and_addresses_are_checked(server, jobs, monkeypatch):
    job = jobs["converged"]
    monkeypatch.delenv("OCPAR_SERVER", raising=False)
    one_line_error(ocpar("submit", "formation-60"), "submit",
                   "give --server URL (or set OCPAR_SERVER)", "or --scheduler ADDR")
    one_line_error(ocpar("wait", job), "wait", "give --server URL (or set OCPAR_SERVER)")
    one_line_error(ocpar("jobs", "--server", server.url, "--token", "not-a-token"), "jobs",
                   "(HTTP 401)")
    one_line_error(ocpar("status", job, "--server", server.url, "--token",
                         server.tokens["bob"]), "status", "(HTTP 403)")
    one_line_error(ocpar("status", "no-such-job", *server.as_alice), "status", "(HTTP 404)")
    for path in ("../openapi.json", "x/../../openapi.json"):  # one path segment each
        one_line_error(ocpar("status", path, *server.as_alice), "status", "(HTTP 404)")
    one_line_error(ocpar("status", "..", *server.as_alice), "status",
                   "not a job id or file name: '..'")
    one_line_error(ocpar("jobs", "--server", f"{server.url}/static/x", "--token", "t"), "jobs")
    one_line_error(ocpar("cancel", job, *server.as_alice), "cancel", "(HTTP 409)")
    closed = f"http://127.0.0.1:{free_port()}"
    one_line_error(ocpar("jobs", "--server", closed, "--token", "t"), "jobs",
                   f"cannot reach the ocpar server at {closed}")
    one_line_error(ocpar("jobs", "--server", server.url, "--scheduler", "tcp://h:1"), "jobs",
                   "not allowed with argument")
    one_line_error(ocpar("jobs", "--scheduler", "tcp://h:1", "--token", "t"), "jobs",
                   "--token is for an ocpar server (--server), not --scheduler")
    one_line_error(ocpar("status", job, "--follow", "--scheduler", "tcp://h:1"), "status",
                   "--follow needs an ocpar server")


def test_server_sent_events_are_parsed_as_sent():
    lines = [": comment", "event: progress", 'data: {"line": "a",', 'data: "n": 1}', "",
             "data: {}", "", "event: end", 'data: {"state": "succeeded"}']
    assert list(parse_events(iter(lines))) == [
        ("progress", {"line": "a", "n": 1}), ("message", {}), ("end", {"state": "succeeded"})]
    assert str(ServerRefused(404, "no job x")) == "no job x (HTTP 404)"


def self_signed_certificate(directory: Path) -> tuple[Path, Path]:
    """A self-signed certificate for 127.0.0.1 and its key (cert.pem, key.pem in
    ``directory``)."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ocpar-test-server")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName(
                [x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = directory / "cert.pem", directory / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def test_an_https_server_is_trusted_through_its_ca_file(tmp_path):
    """``ocpar serve --ssl-certfile/--ssl-keyfile``: the commands reach it with
    ``--tls-ca-file``, and refuse it in one line without (an unknown certificate)."""
    cert, key = self_signed_certificate(tmp_path)
    token = ocpar("serve", "token", "add", "carol", "--state-dir", str(tmp_path)).out.strip()
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "ocpar", "serve", "--port", str(port),
                             "--state-dir", str(tmp_path), "--backend", "serial",
                             "--ssl-certfile", str(cert), "--ssl-keyfile", str(key)],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for_port(port, proc, 60, "ocpar serve --ssl-certfile did not start")
        url = f"https://127.0.0.1:{port}"
        listed = ocpar("jobs", "--server", url, "--token", token, "--tls-ca-file", str(cert))
        assert listed.code == 0 and listed.out.startswith("# id, scheme"), listed
        one_line_error(ocpar("jobs", "--server", url, "--token", token), "jobs",
                       f"cannot reach the ocpar server at {url}", "CERTIFICATE_VERIFY_FAILED")
    finally:
        stop_processes([proc])


def test_a_server_that_is_not_ocpar_is_one_line(tmp_path):
    """A web server that answers ``GET /jobs`` with something else than JSON."""
    import functools
    import http.server
    import threading

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:  # not on this test's stderr
            pass

    (tmp_path / "jobs").write_text("<html>a page</html>")
    handler = functools.partial(Quiet, directory=str(tmp_path))
    with http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler) as httpd:
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        url = f"http://127.0.0.1:{httpd.server_address[1]}"
        one_line_error(ocpar("jobs", "--server", url, "--token", "t"), "jobs",
                       f"{url}/jobs answered 200 without JSON: is it an ocpar server?")
        httpd.shutdown()


def start_server(state: Path, port: int, *options: str) -> subprocess.Popen:
    """``ocpar serve`` on 127.0.0.1:``port`` with its state in ``state`` (serial backend),
    once it accepts connections."""
    proc = subprocess.Popen([sys.executable, "-m", "ocpar", "serve", "--port", str(port),
                             "--state-dir", str(state), "--backend", "serial", *options],
                            cwd=REPO, env=dict(os.environ, OMP_NUM_THREADS="1"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for_port(port, proc, 60, "ocpar serve did not start")
    return proc


@pytest.mark.slow  # (the server's own restart is in test_web_service.py's default run)
def test_wait_outlives_a_restart_of_the_server(tmp_path):
    """The server is killed while a client waits for a job, and started again: the wait
    reconnects and returns the job's final record."""
    import threading

    from ocpar.service.http_client import Server

    token = ocpar("serve", "token", "add", "dave", "--state-dir", str(tmp_path)).out.strip()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    proc = start_server(tmp_path, port)
    try:
        with Server(url, token) as server:
            job = server.submit("formation-60")["id"]
            outcome: dict = {}

            def wait() -> None:
                try:
                    outcome["record"] = server.wait(job, timeout_s=120)
                except Exception as exc:  # reported by the assertion below
                    outcome["error"] = exc

            waiting = threading.Thread(target=wait)
            waiting.start()
            time.sleep(0.5)
            assert waiting.is_alive()
            proc.kill()
            proc.wait()
            time.sleep(1.5)  # the waiting client finds no server
            proc = start_server(tmp_path, port)
            waiting.join(150)
            assert "record" in outcome, outcome
            assert outcome["record"]["state"] in FINAL_STATES
            assert outcome["record"] == server.status(job)
    finally:
        stop_processes([proc])
