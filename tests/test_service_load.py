"""``ocpar serve`` under load (issue 47): 50 clients polling job status, 5 following
``/events`` and 20 jobs unfinished at all times, through ``scripts/service_latency.py``'s
:func:`under_load` against a real server on its embedded cluster: no 5xx, status GETs within
100 ms at the 99th percentile, every job that ended succeeded. The figures hold on a quiet
2-core machine; a machine that other work keeps busy starves the server and the clients."""

from __future__ import annotations

import pytest
from conftest import script_module

latency = script_module("service_latency")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_fifty_pollers_five_followers_twenty_jobs_no_5xx_and_gets_within_100_ms(tmp_path):
    state = tmp_path / "state"
    token = latency.issue_tokens(state, 1, None)["t0"]
    with latency.ocpar_serve(state) as url:
        latency.wait_ready(url)
        figures = latency.under_load(url, token, seconds=15)
    assert figures["server_errors"] == 0, figures
    assert set(figures["responses"]) <= {"200", "201"}, figures
    assert figures["status_gets"] > 0.5 * 15 * latency.POLLERS / latency.POLL_S, figures
    assert figures["get_p99_ms"] <= 100, figures
    ended = figures["jobs_ended"]
    assert ended.get("succeeded", 0) > 0 and set(ended) == {"succeeded"}, figures
