"""TLS: a Dask cluster secured with certificates (a real ``dask scheduler --protocol tls`` with
two workers from ``workers/start-dask-worker.sh``, and the embedded cluster) runs the formation
example exactly as the serial backend does; a client without a certificate signed by the
cluster's CA is refused, and the command line says so in one line with exit status 2.

The certificates are made as workers/tls.md says, with the ``openssl`` command line (with the
``cryptography`` package where there is none; the embedded cluster's always come from it).
"""

from __future__ import annotations

import datetime
import gc
import json
import os
import shutil
import socket
import ssl
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, free_port, run_cli, stop_processes, tool, wait_for_port

from ocpar.bsp import open_backend
from ocpar.bsp.backend import BackendError
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation

AGENTS = 6
ROLES = ("scheduler", "worker", "client")
WORKER_SCRIPT = REPO / "workers" / "start-dask-worker.sh"

#: Extensions of the certificates the CA signs (the file workers/tls.md writes as leaf.ext).
LEAF_EXTENSIONS = """\
basicConstraints = CA:FALSE
keyUsage = critical, digitalSignature, keyEncipherment
extendedKeyUsage = serverAuth, clientAuth
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
"""


def openssl_certificates(directory: Path, names: tuple[str, ...]) -> None:
    """workers/tls.md's openssl commands: a CA (ca.pem, ca.key), then NAME.pem and NAME.key
    signed by it for each name."""
    def openssl(*args: str) -> None:
        proc = subprocess.run(["openssl", *args], cwd=directory, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr

    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "30",
            "-subj", "/CN=ocpar-dask-ca", "-keyout", "ca.key", "-out", "ca.pem")
    (directory / "leaf.ext").write_text(LEAF_EXTENSIONS)
    for name in names:
        openssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN=ocpar-{name}",
                "-keyout", f"{name}.key", "-out", f"{name}.csr")
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-days", "30", "-extfile", "leaf.ext", "-out", f"{name}.pem")


def cryptography_certificates(directory: Path, names: tuple[str, ...]) -> None:
    """The same files as :func:`openssl_certificates`, made with the ``cryptography``
    package (elliptic-curve keys)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    def write(stem: str, key, cert) -> None:
        (directory / f"{stem}.key").write_bytes(key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
        (directory / f"{stem}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))

    def builder(subject: str, issuer: x509.Name, key) -> x509.CertificateBuilder:
        now = datetime.datetime.now(datetime.UTC)
        return (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, subject)]))
                .issuer_name(issuer)
                .public_key(key.public_key())
                .serial_number(x509.random_serial_number())
                .not_valid_before(now - datetime.timedelta(minutes=5))
                .not_valid_after(now + datetime.timedelta(days=30)))

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ocpar-dask-ca")])
    ca_cert = (builder("ocpar-dask-ca", ca_name, ca_key)
               .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
               .add_extension(x509.KeyUsage(
                   digital_signature=False, content_commitment=False, key_encipherment=False,
                   data_encipherment=False, key_agreement=False, key_cert_sign=True,
                   crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
               .sign(ca_key, hashes.SHA256()))
    write("ca", ca_key, ca_cert)
    for name in names:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (builder(f"ocpar-{name}", ca_name, key)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]),
                               critical=False)
                .sign(ca_key, hashes.SHA256()))
        write(name, key, cert)


def make_certificates(directory: Path, names: tuple[str, ...] = ROLES,
                      maker: str | None = None) -> Path:
    """A CA and a certificate/key per name in ``directory`` (made there); ``maker``:
    ``openssl``, ``cryptography`` or None (openssl where it is installed)."""
    directory.mkdir(parents=True, exist_ok=True)
    maker = maker or ("openssl" if shutil.which("openssl") else "cryptography")
    (openssl_certificates if maker == "openssl" else cryptography_certificates)(directory, names)
    return directory


def client_security(certs: Path, ca: Path | None = None):
    """A client presenting ``certs``' client certificate and trusting ``ca`` (default:
    ``certs``' CA)."""
    from distributed import Security

    return Security(tls_ca_file=str(ca or certs / "ca.pem"),
                    tls_client_cert=str(certs / "client.pem"),
                    tls_client_key=str(certs / "client.key"), require_encryption=True)


def tls_options(certs: Path, ca: Path | None = None) -> list[str]:
    return ["--tls-ca-file", str(ca or certs / "ca.pem"), "--tls-cert", str(certs / "client.pem"),
            "--tls-key", str(certs / "client.key")]


def refusal(address: str, expected: type[BaseException] | tuple = OSError, **options) -> str:
    """Connect a distributed ``Client`` to ``address``, which must fail with ``expected``
    within 5 s; the error message."""
    from distributed import Client

    with pytest.raises(expected) as caught:
        Client(address, timeout="5s", **options).close()
    message = str(caught.value)
    # the half-started Client is garbage: collect it now, or its __del__ may run inside the
    # next Client's start and deadlock on distributed's LoopRunner lock
    del caught
    gc.collect()
    return message


def assert_one_line_error(proc: subprocess.CompletedProcess, needle: str,
                          prog: str = "ocpar.formation") -> str:
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"{prog}: error:") and needle in lines[0], lines[0]
    assert "Traceback" not in proc.stderr + proc.stdout
    return lines[0]


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """The cluster's CA and a certificate for its scheduler, its workers and a client."""
    return make_certificates(tmp_path_factory.mktemp("tls"))


@pytest.fixture(scope="module")
def stranger(tmp_path_factory) -> Path:
    """Another CA, and a client certificate it signed: not one the cluster trusts."""
    return make_certificates(tmp_path_factory.mktemp("stranger"), ("client",), "cryptography")


@pytest.fixture(scope="module")
def reference():
    return solve_formation(paper_example(agents=AGENTS))


def assert_same_run(result: dict, reference) -> None:
    assert result["status"] == "converged"
    assert result["total_cost"] == pytest.approx(reference.total_cost, rel=1e-10)
    np.testing.assert_allclose(result["phi"], reference.phi, rtol=1e-10, atol=1e-12)
    assert result["supersteps"] == reference.supersteps


@pytest.fixture(scope="module")
def tls_cluster(certs, tmp_path_factory):
    """``dask scheduler --protocol tls`` on 127.0.0.1 with the scheduler's certificate (keeping
    its jobs in a temporary directory), and two workers started by
    workers/start-dask-worker.sh with the workers' certificate (through OCPAR_TLS_*); yields
    the tls:// address."""
    from distributed import Client

    logs = tmp_path_factory.mktemp("tls-logs")
    port = free_port()
    address = f"tls://127.0.0.1:{port}"
    dask = tool("dask")
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PATH=f"{Path(dask).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    procs = []

    def start(cmd: list[str], log: str, cwd: Path | None = None, **extra: str) -> None:
        with open(logs / log, "wb") as out:
            procs.append(subprocess.Popen(cmd, env=dict(env, **extra), stdout=out, cwd=cwd,
                                          stderr=subprocess.STDOUT))

    def log_tail() -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-2000:]}" for p in logs.iterdir())

    try:
        # certificate paths relative to the scheduler's directory, as an admin may give them
        start([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
               "--protocol", "tls", "--no-dashboard", "--tls-ca-file", "ca.pem",
               "--tls-cert", "scheduler.pem", "--tls-key", "scheduler.key"], "scheduler.log",
              cwd=certs, OCPAR_JOBS_DIR=str(tmp_path_factory.mktemp("tls-jobs")))
        wait_for_port(port, procs[0], 30,
                      lambda: f"TLS dask scheduler did not start\n{log_tail()}")
        start([str(WORKER_SCRIPT), address, "2"], "workers.log",
              OCPAR_TLS_CA_FILE=str(certs / "ca.pem"), OCPAR_TLS_CERT=str(certs / "worker.pem"),
              OCPAR_TLS_KEY=str(certs / "worker.key"))
        try:
            with Client(address, timeout="20s", security=client_security(certs)) as client:
                client.wait_for_workers(2, timeout=40)
                workers = list(client.scheduler_info(n_workers=-1)["workers"])
        except (OSError, TimeoutError) as exc:
            pytest.fail(f"TLS dask cluster did not come up: {exc}\n{log_tail()}")
        assert len(workers) == 2 and all(w.startswith("tls://") for w in workers), workers
        yield address
    finally:
        stop_processes(procs)


def test_tls_cluster_runs_the_formation_like_serial(tls_cluster, certs, reference, tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), "--backend", "dask",
                   "--scheduler", tls_cluster, "--workers", "2", *tls_options(certs),
                   "--output", str(tmp_path), "--quiet", timeout=120)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "dask" and data["workers"] == 2
    assert_same_run(data, reference)


def test_tls_cluster_refuses_clients_without_its_certificates(tls_cluster, certs, stranger):
    port = int(tls_cluster.rsplit(":", 1)[1])
    # distributed's client has no certificate to offer: it will not even try
    refusal(tls_cluster, (OSError, TypeError))
    # plain TCP to the TLS port
    refusal(f"tcp://127.0.0.1:{port}")
    # a certificate from another CA: the scheduler rejects it in the handshake (the client
    # sees the alert "unknown ca", or under TLS 1.3 sometimes only the connection closing)
    message = refusal(tls_cluster, security=client_security(stranger, ca=certs / "ca.pem"))
    assert "ssl" in message.lower()
    # ... and the client, trusting only that other CA, rejects the scheduler
    assert "certificate" in refusal(tls_cluster, security=client_security(stranger)).lower()
    # a TLS client that trusts the scheduler but shows no certificate: the scheduler hangs up
    context = ssl.create_default_context(cafile=str(certs / "ca.pem"))
    context.check_hostname = False
    with (pytest.raises((ssl.SSLError, ConnectionError)),  # not a TimeoutError: refused
          socket.create_connection(("127.0.0.1", port), timeout=5) as raw,
          context.wrap_socket(raw) as tls):
        if not tls.recv(1):  # TLS 1.3 sends the refusal after the handshake
            raise ConnectionResetError("closed by the scheduler")
    # ocpar's own client, through the Python API
    with pytest.raises(BackendError, match="no client certificate"):
        open_backend("dask", scheduler=tls_cluster)
    # ... while the cluster's client certificate is let in
    with open_backend("dask", scheduler=tls_cluster, security=client_security(certs)) as ok:
        assert ok.workers == 2


def test_command_line_without_certificates_is_refused_in_one_line(tls_cluster, certs,
                                                                  stranger):
    # each refused at once, not after Dask's 30 s connect timeout
    started = time.monotonic()
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), "--scheduler", tls_cluster,
                   timeout=60)
    line = assert_one_line_error(proc, f"cannot reach Dask scheduler {tls_cluster}")
    assert "--tls-cert" in line
    assert time.monotonic() - started < 30
    started = time.monotonic()
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), "--scheduler", tls_cluster,
                   *tls_options(stranger, ca=certs / "ca.pem"), timeout=60)
    line = assert_one_line_error(proc, f"cannot reach Dask scheduler {tls_cluster}")
    assert "ssl" in line.lower()
    assert time.monotonic() - started < 30


@pytest.mark.slow
def test_a_job_submitted_to_the_tls_cluster_matches_serial(tls_cluster, certs, reference,
                                                          tmp_path):
    """``ocpar submit`` with the client's certificate; the job's coordinator, on the scheduler's
    host, connects with the scheduler's own certificate files (given relative to the
    scheduler's directory); a later process fetches the result. Without a certificate the
    service commands are refused in one line."""
    def ocpar(*args: str) -> subprocess.CompletedProcess:
        return run_cli("-m", "ocpar", *args, "--scheduler", tls_cluster, timeout=120)

    assert_one_line_error(ocpar("jobs"), "no client certificate", prog="ocpar jobs")
    proc = ocpar("submit", "formation-60", "--set", f"agents={AGENTS}", *tls_options(certs))
    assert proc.returncode == 0, proc.stderr
    job = proc.stdout.strip()
    deadline = time.monotonic() + 120
    while (state := json.loads(ocpar("status", job, "--json", *tls_options(certs)).stdout)
           )["state"] not in ("finished", "failed", "cancelled"):
        assert time.monotonic() < deadline, state
        time.sleep(0.5)
    assert state["state"] == "finished", state
    proc = ocpar("result", job, "--output", str(tmp_path), *tls_options(certs))
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "dask" and data["workers"] == 2
    assert_same_run(data, reference)


def test_embedded_cluster_uses_tls_and_matches_serial(certs, reference, tmp_path_factory):
    """``--backend dask`` with certificates and no scheduler: a LocalCluster that speaks TLS
    only, its scheduler and workers using the client's certificate (here from cryptography)."""
    own = make_certificates(tmp_path_factory.mktemp("embedded"), ("client",), "cryptography")
    with open_backend("dask", workers=2, security=client_security(own)) as backend:
        address = backend.client.scheduler.address
        assert address.startswith("tls://")
        assert all(w.startswith("tls://") for w in backend.addresses)
        result = solve_formation(paper_example(agents=AGENTS), backend)
        refusal(address, (OSError, TypeError))
        # a certificate from another CA
        message = refusal(address, security=client_security(certs, ca=own / "ca.pem"))
        assert "ssl" in message.lower()
    assert_same_run({"status": result.status, "total_cost": result.total_cost,
                     "phi": result.phi, "supersteps": result.supersteps}, reference)
    assert result.workers == 2 and result.backend == "dask"


@pytest.mark.slow  # (the embedded TLS cluster itself: test_embedded_cluster_uses_tls_...)
def test_embedded_tls_cluster_from_the_command_line(certs, reference, tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), "--backend", "dask",
                   "--workers", "2", *tls_options(certs), "--output", str(tmp_path), "--quiet",
                   timeout=120)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "dask" and data["workers"] == 2
    assert_same_run(data, reference)


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"--tls-key": None, "--tls-ca-file": None}, "go together: --tls-ca-file is missing"),
        ({"--tls-key": None}, "go together: --tls-key is missing"),
        ({"--tls-ca-file": "MISSING"}, "--tls-ca-file"),
        ({"--tls-cert": "MISSING"}, "No such file"),
        ({"--tls-key": "DIRECTORY"}, "--tls-key"),
        ({"--backend": "serial"}, "only apply to --backend dask"),
        ({"--scheduler": "tcp://127.0.0.1:9"}, "tls://HOST:PORT"),
        ({"--tls-key": "OTHER KEY"}, "cannot load the TLS"),
        ({"--scheduler": "127.0.0.1:8786"}, "tls://HOST:PORT"),
    ],
)
def test_bad_tls_options_get_one_line_and_status_2(certs, tmp_path, change, needle):
    options = {"--backend": "dask", "--tls-ca-file": str(certs / "ca.pem"),
               "--tls-cert": str(certs / "client.pem"), "--tls-key": str(certs / "client.key")}
    special = {"MISSING": str(tmp_path / "missing.pem"), "DIRECTORY": str(tmp_path),
               "OTHER KEY": str(certs / "worker.key")}
    options.update({k: special.get(v, v) for k, v in change.items()})
    args = [part for k, v in options.items() if v is not None for part in (k, v)]
    proc = run_cli("-m", "ocpar.formation", "--agents", str(AGENTS), *args, timeout=60)
    assert_one_line_error(proc, needle)
    assert "worker(s)" not in proc.stdout  # refused before a backend started


@pytest.mark.parametrize(
    ("env", "address", "needle"),
    [
        ({"OCPAR_TLS_CERT": "CERT"}, "tls://127.0.0.1:9", "OCPAR_TLS_CA_FILE is not set"),
        ({"OCPAR_TLS_CA_FILE": "CA", "OCPAR_TLS_CERT": "CERT", "OCPAR_TLS_KEY": "MISSING"},
         "tls://127.0.0.1:9", "is not a readable file"),
        ({"OCPAR_TLS_CA_FILE": "CA", "OCPAR_TLS_CERT": "CERT", "OCPAR_TLS_KEY": "KEY"},
         "tcp://127.0.0.1:9", "tls:// scheduler address"),
    ],
)
def test_worker_script_checks_its_tls_settings(certs, tmp_path, env, address, needle):
    files = {"CA": certs / "ca.pem", "CERT": certs / "worker.pem", "KEY": certs / "worker.key",
             "MISSING": tmp_path / "missing.key"}
    environ = {k: v for k, v in os.environ.items() if not k.startswith("OCPAR_TLS_")}
    environ.update({k: str(files[v]) for k, v in env.items()})
    proc = subprocess.run([str(WORKER_SCRIPT), address, "1"], env=environ, capture_output=True,
                          text=True, timeout=30)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "error:" in lines[0] and needle in lines[0], proc.stderr
