"""How fast ``ocpar serve`` answers: its start time, and POST → ``succeeded`` of a 12-agent
formation job (``formation-60`` with agents=12) one at a time and 20 at once, on its default
backend (the embedded Dask cluster of 2 workers), quiet and with CPU burners; writes JSON.

::

    python scripts/service_latency.py --output latency.json [--load 0 2] [--repeat 10]
    python scripts/service_latency.py --output load.json --under-load [--seconds 20]

Start time: from launching ``python -m ocpar serve`` to its first answer (``/openapi.json``),
and to its saying it is ready (``GET /health`` 200: the cluster up, the warm runners warmed
up; a server without ``/health`` is taken as ready at its first answer). A job's latency:
from sending its POST to the first ``GET /jobs/ID`` (polled every 20 ms;
every 100 ms for the jobs at once) that says ``succeeded``. The first job of a server (the
workers build their inner solvers) is a warm-up, reported apart. Resume: a MACS job
cancelled at its third superstep, from ``POST /jobs/ID/resume`` to ``running`` (and to its
next superstep), beside its submission's POST to ``running``.

Under load (``--under-load``, :func:`under_load`): for ``--seconds``, 50 clients poll the
status of the unfinished jobs (one GET each every 0.25 s), 5 follow their ``/events`` (a new
stream as each ends) and a submitter keeps 20 jobs unfinished (submitted anew as they end:
queued or running on the server's 2 runners); every response's status is counted, every
status GET timed (p50, p99, max), and the jobs ended are counted by final state.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import os
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


#: What :func:`under_load` runs by default: status pollers, event followers, unfinished
#: jobs, seconds between one poller's GETs.
POLLERS, FOLLOWERS, UNFINISHED, POLL_S = 50, 5, 20, 0.25
FINAL = ("succeeded", "failed", "cancelled")


async def _under_load(url: str, headers: dict, seconds: float, pollers: int, followers: int,
                      unfinished: int, poll_s: float) -> dict:
    import httpx

    statuses: collections.Counter = collections.Counter()
    ended: collections.Counter = collections.Counter()
    gets: list[float] = []
    live: list[str] = []
    stop = time.perf_counter() + seconds
    limits = httpx.Limits(max_connections=pollers + followers + 4)
    async with httpx.AsyncClient(base_url=url, headers=headers, timeout=120,
                                 limits=limits) as client:
        async def submitter() -> None:
            while time.perf_counter() < stop:
                while len(live) < unfinished:
                    response = await client.post("/jobs", json=JOB)
                    statuses[response.status_code] += 1
                    if response.status_code != 201:
                        break
                    live.append(response.json()["id"])
                await asyncio.sleep(0.05)

        async def poller(k: int) -> None:
            await asyncio.sleep(poll_s * k / pollers)  # spread over the interval
            while time.perf_counter() < stop:
                if live:
                    job = live[k % len(live)]
                    t0 = time.perf_counter()
                    response = await client.get(f"/jobs/{job}")
                    gets.append(time.perf_counter() - t0)
                    statuses[response.status_code] += 1
                    state = response.json().get("state") if response.status_code == 200 \
                        else None
                    if state in FINAL and job in live:
                        live.remove(job)
                        ended[state] += 1
                await asyncio.sleep(poll_s)

        async def follower(k: int) -> None:
            while time.perf_counter() < stop:
                if not live:
                    await asyncio.sleep(0.05)
                    continue
                async with client.stream("GET", f"/jobs/{live[k % len(live)]}/events"
                                         ) as response:
                    statuses[response.status_code] += 1
                    async for _ in response.aiter_lines():
                        if time.perf_counter() > stop:
                            break

        await asyncio.gather(submitter(), *(poller(k) for k in range(pollers)),
                             *(follower(k) for k in range(followers)))
    return {"seconds": seconds, "pollers": pollers, "followers": followers,
            "unfinished_jobs": unfinished, "poll_every_s": poll_s,
            "status_gets": len(gets), "gets_per_s": round(len(gets) / seconds, 1),
            "get_p50_ms": round(1e3 * percentile(gets, 0.5), 2),
            "get_p99_ms": round(1e3 * percentile(gets, 0.99), 2),
            "get_max_ms": round(1e3 * max(gets), 2),
            "responses": {str(code): count for code, count in sorted(statuses.items())},
            "server_errors": sum(count for code, count in statuses.items() if code >= 500),
            "jobs_ended": dict(ended)}


def under_load(url: str, token: str, seconds: float = 20.0, pollers: int = POLLERS,
               followers: int = FOLLOWERS, unfinished: int = UNFINISHED,
               poll_s: float = POLL_S) -> dict:
    """The server at ``url`` under load for ``seconds`` (see the module's docstring), with
    ``token``'s jobs: GET latencies (ms), responses by status, jobs ended by state."""
    return asyncio.run(_under_load(url, {"Authorization": f"Bearer {token}"}, seconds,
                                   pollers, followers, unfinished, poll_s))


def measure_under_load(workdir: Path, seconds: float) -> dict:
    """A fresh server, ready, then :func:`under_load`; with the load average before."""
    state = workdir / "under-load" / "state"
    token = issue_tokens(state, 1, None)["t0"]
    with ocpar_serve(state) as url:
        wait_ready(url)
        loadavg = os.getloadavg()
        return {"loadavg_before": [round(x, 2) for x in loadavg],
                **under_load(url, token, seconds)}


def main(argv: list[str] | None = None) -> int:
    import tempfile

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", required=True, help="the JSON report")
    parser.add_argument("--load", type=int, nargs="+", default=[0, 2],
                        help="CPU burners of each measurement (default 0 2)")
    parser.add_argument("--repeat", type=int, default=10, help="jobs one at a time")
    parser.add_argument("--concurrent", type=int, default=20, help="jobs at once")
    parser.add_argument("--under-load", action="store_true",
                        help=f"measure GETs under load instead: {POLLERS} status pollers, "
                             f"{FOLLOWERS} event followers, {UNFINISHED} unfinished jobs")
    parser.add_argument("--seconds", type=float, default=20.0,
                        help="with --under-load: its duration (default 20)")
    args = parser.parse_args(argv)
    report = {"job": JOB, "machine": machine(), "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        if args.under_load:
            figures = measure_under_load(Path(tmp), args.seconds)
            print(json.dumps(figures), flush=True)
            report["under_load"] = figures
            args.load = []
        for load in args.load:
            figures = measure(Path(tmp), load, args.repeat, args.concurrent)
            print(json.dumps(figures), flush=True)
            report["runs"].append(figures)
    Path(args.output).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
