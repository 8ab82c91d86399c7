"""Many jobs of all three schemes at once on one shared Dask cluster, while the machine is kept
busy (issue 40: a superstep's second round of chunks got the first round's results back, and
formation jobs failed). Through the functions of ``scripts/concurrent_jobs.py``: a real ``ocpar
serve`` on its embedded cluster, and a real ``dask scheduler`` with two workers reached by
``ocpar submit --scheduler``; every job's result.json and array file against ``ocpar run`` of
its configuration."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import script_module

concurrent_jobs = script_module("concurrent_jobs")
MIX = concurrent_jobs.MIXES["small"]
#: CPU-burning processes beside the jobs (this machine has 2 cores).
LOAD = 2


@pytest.fixture(scope="module")
def direct(tmp_path_factory) -> dict[str, dict]:
    """``ocpar run`` of each configuration of the small mix, serially."""
    return concurrent_jobs.direct_runs(MIX, tmp_path_factory.mktemp("direct"))


@pytest.mark.slow  # (20 jobs at once on the embedded cluster: test_web_service.py)
@pytest.mark.timeout(900)
@pytest.mark.parametrize("path", ["serve", "submit"])
def test_fifty_jobs_of_three_schemes_at_once_equal_their_direct_runs(path, direct, tmp_path):
    """50 jobs (the five small configurations of all three schemes, ten times each) from 5
    clients at once, on ``ocpar serve``'s embedded cluster (4 running at once, 2 per token)
    or submitted with ``ocpar submit --scheduler`` (all running at once), with 2 processes
    burning CPU: every job succeeds and equals its direct run, bit for bit."""
    different = concurrent_jobs.differences(Path(direct[concurrent_jobs.label(MIX[0])]["dir"]),
                                            Path(direct[concurrent_jobs.label(MIX[2])]["dir"]))
    assert different  # the comparison sees a different result
    with concurrent_jobs.cpu_load(LOAD):
        result = concurrent_jobs.run_batches(path, MIX, direct, tmp_path / path, batches=1,
                                             jobs=50, tokens=5, max_running=4, max_jobs=2,
                                             timeout=600)
    totals = result["totals"]
    records = result["batches"][0]["job_records"]
    assert totals["jobs"] == len(records) == 50
    assert {r["config"].split()[0].split("-")[0] for r in records} >= {
        "formation", "macs", "pursuit", "{scheme=formation"}
    assert len({r["client"] for r in records}) == 5
    assert totals["failures"] == [], totals["failures"]
    assert totals["mismatches"] == [], totals["mismatches"]
    assert totals["succeeded"] == totals["equal"] == 50
