"""How fast ``ocpar serve`` answers: its start time, and POST → ``succeeded`` of a 12-agent
formation job (``formation-60`` with agents=12) one at a time and 20 at once, on its default
backend (the embedded Dask cluster of 2 workers), quiet and with CPU burners; writes JSON.

::

    python scripts/service_latency.py --output latency.json [--load 0 2] [--repeat 10]

Start time: from launching ``python -m ocpar serve`` to its first answer (``/openapi.json``),
and to its saying it is ready (``GET /health`` 200: the cluster up, the warm runners warmed
up; a server without ``/health`` is taken as ready at its first answer). A job's latency:
from sending its POST to the first ``GET /jobs/ID`` (polled every 20 ms;
every 100 ms for the jobs at once) that says ``succeeded``. The first job of a server (the
workers build their inner solvers) is a warm-up, reported apart. Resume: a MACS job
cancelled at its third superstep, from ``POST /jobs/ID/resume`` to ``running`` (and to its
next superstep), beside its submission's POST to ``running``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from concurrent_jobs import (
    cpu_load,
    issue_tokens,
    machine,
    ocpar_serve,
)

JOB = {"config": "formation-60", "set": {"agents": 12}}
#: Seconds between the polls of each of the jobs at once (20 clients polling every 20 ms
#: would send 1,000 requests a second to a server on the same 2 cores).
AT_ONCE_POLL_S = 0.1


def percentile(values: list[float], q: float) -> float:
    """The ``q`` quantile (0..1) of ``values``, by linear interpolation."""
    ordered = sorted(values)
    position = q * (len(ordered) - 1)
    low = int(position)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (position - low)


def one_job(client, started: float | None = None, poll_s: float = 0.02) -> tuple[float, str]:
    """POST :data:`JOB` and poll it every ``poll_s`` seconds to its end: (seconds, final
    state)."""
    t0 = time.perf_counter() if started is None else started
    response = client.post("/jobs", json=JOB)
    response.raise_for_status()
    job = response.json()["id"]
    while True:
        state = client.get(f"/jobs/{job}").json()["state"]
        if state in ("succeeded", "failed", "cancelled"):
            return time.perf_counter() - t0, state
        time.sleep(poll_s)


#: A job long enough to cancel and resume (MACS, ~19 supersteps).
LONG = {"config": "macs-goddard", "set": {"max_evals": 1000, "seed": 7}}


def until(client, job: str, done, timeout: float = 300) -> dict:
    """Poll ``job`` every 20 ms until ``done(record)``; the record."""
    deadline = time.perf_counter() + timeout
    while not done(record := client.get(f"/jobs/{job}").json()):
        if time.perf_counter() > deadline:
            raise TimeoutError(f"job {job}: {record}")
        time.sleep(0.02)
    return record


def cancel_and_resume(client) -> dict:
    """Seconds from POST to ``running`` of :data:`LONG`, and from its resume (after a cancel
    at its third superstep) to ``running`` again and to its next superstep."""
    t0 = time.perf_counter()
    job = client.post("/jobs", json=LONG).json()["id"]
    until(client, job, lambda r: r["state"] != "queued")
    submit_s = time.perf_counter() - t0
    until(client, job, lambda r: r["supersteps"] >= 3)
    client.delete(f"/jobs/{job}")
    at = until(client, job, lambda r: r["state"] == "cancelled")["supersteps"]
    t0 = time.perf_counter()
    client.post(f"/jobs/{job}/resume").raise_for_status()
    until(client, job, lambda r: r["state"] != "queued")
    resume_s = time.perf_counter() - t0
    until(client, job, lambda r: r["supersteps"] > at or r["state"] != "running")
    step_s = time.perf_counter() - t0
    final = until(client, job, lambda r: r["state"] in ("succeeded", "failed", "cancelled"))
    return {"submit_to_running_s": round(submit_s, 3), "resume_to_running_s": round(resume_s, 3),
            "resume_to_next_superstep_s": round(step_s, 3), "state": final["state"]}


def wait_ready(url: str, timeout: float = 300) -> None:
    """Wait until the server at ``url`` says it is ready (``/health``; none: at once)."""
    import httpx

    deadline = time.perf_counter() + timeout
    while (code := httpx.get(url + "/health", timeout=10).status_code) == 503:
        if time.perf_counter() > deadline:
            raise TimeoutError(f"{url} not ready after {timeout:g} s")
        time.sleep(0.1)
    if code not in (200, 404):
        raise RuntimeError(f"{url}/health: HTTP {code}")


def measure(workdir: Path, load: int, repeat: int, concurrent: int) -> dict:
    import httpx

    state = workdir / f"load{load}" / "state"
    token = issue_tokens(state, 1, None)["t0"]
    with cpu_load(load):
        t0 = time.perf_counter()
        with ocpar_serve(state) as url:
            start_s = time.perf_counter() - t0
            wait_ready(url)
            ready_s = time.perf_counter() - t0
            headers = {"Authorization": f"Bearer {token}"}
            with httpx.Client(base_url=url, headers=headers, timeout=120) as client:
                first, _ = one_job(client)
                single = [one_job(client) for _ in range(repeat)]
                resume = cancel_and_resume(client)
            results: list[tuple[float, str]] = []
            go = threading.Barrier(concurrent)

            def submit() -> None:
                with httpx.Client(base_url=url, headers=headers, timeout=120) as client:
                    go.wait()
                    results.append(one_job(client, poll_s=AT_ONCE_POLL_S))

            threads = [threading.Thread(target=submit) for _ in range(concurrent)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
    one = [s for s, _ in single]
    many = [s for s, _ in results]
    return {"cpu_burners": load, "server_start_s": round(start_s, 3),
            "server_ready_s": round(ready_s, 3),
            "first_job_s": round(first, 3),
            "one_at_a_time": {"jobs": repeat, "succeeded": sum(s == "succeeded"
                                                              for _, s in single),
                              "p50_s": round(statistics.median(one), 3),
                              "p95_s": round(percentile(one, 0.95), 3)},
            "at_once": {"jobs": concurrent, "succeeded": sum(s == "succeeded"
                                                            for _, s in results),
                        "p50_s": round(statistics.median(many), 3),
                        "p95_s": round(percentile(many, 0.95), 3),
                        "max_s": round(max(many), 3)},
            "cancel_and_resume": resume}


def main(argv: list[str] | None = None) -> int:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", required=True, help="the JSON report")
    parser.add_argument("--load", type=int, nargs="+", default=[0, 2],
                        help="CPU burners of each measurement (default 0 2)")
    parser.add_argument("--repeat", type=int, default=10, help="jobs one at a time")
    parser.add_argument("--concurrent", type=int, default=20, help="jobs at once")
    args = parser.parse_args(argv)
    report = {"job": JOB, "machine": machine(), "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        for load in args.load:
            figures = measure(Path(tmp), load, args.repeat, args.concurrent)
            print(json.dumps(figures), flush=True)
            report["runs"].append(figures)
    Path(args.output).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
