"""The journal's durability: every superstep reaches the operating system as it completes, the
disk (``fsync``) at most every ``interval_s`` and when the backend's block exits; a log cut
short or altered (a power loss) resumes from its intact prefix to the uninterrupted result."""

from __future__ import annotations

import hashlib
import json
import os
import struct

import numpy as np
import pytest
from conftest import run_cli

from ocpar.bsp.journal import (
    INTERVAL_ENV,
    LOG,
    MANIFEST,
    CheckpointError,
    Journal,
    recorded_supersteps,
)
from ocpar.bsp.serial import SerialBackend
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation

AGENTS = 6


@pytest.fixture(scope="module")
def uninterrupted():
    return solve_formation(paper_example(AGENTS), SerialBackend())


def recorded(directory) -> int:
    return json.loads((directory / MANIFEST).read_text())["supersteps"]


def journaled_run(directory, interval_s: float | None = None):
    with SerialBackend() as backend:
        backend.journal = Journal(directory, {"run": "j"}, resume=False, interval_s=interval_s)
        result = solve_formation(paper_example(AGENTS), backend)
    return result, backend


def resumed_run(directory):
    with SerialBackend() as backend:
        backend.journal = Journal(directory, {"run": "j"}, resume=True)
        kept = backend.journal.recorded_supersteps
        return solve_formation(paper_example(AGENTS), backend), kept


def same(a, b) -> bool:
    return (a.total_cost == b.total_cost and np.array_equal(a.phi, b.phi)
            and np.array_equal(a.agent_costs, b.agent_costs)
            and np.array_equal(a.trajectories, b.trajectories) and a.supersteps == b.supersteps)


@pytest.mark.parametrize("interval_s, during_run", [(0.0, 2), (3600.0, 0)],
                         ids=["every-superstep", "once-an-hour"])
def test_fsyncs_come_every_interval_and_at_the_end(tmp_path, monkeypatch, interval_s,
                                                   during_run):
    """0: the log and the manifest synced after each superstep (2 fsyncs); an hour: none
    during the run, 2 when the backend's block exits; the log holds every superstep either
    way (a killed process keeps them), the manifest counts them all after the block."""
    calls = []
    fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: calls.append(fd) or fsync(fd))
    with SerialBackend() as backend:
        backend.journal = Journal(tmp_path, {"run": "j"}, resume=False, interval_s=interval_s)
        opened = len(calls)
        solve_formation(paper_example(AGENTS), backend)
        n = len(backend.traces)
        assert len(calls) - opened == during_run * n
        # unflushed, as a killed process leaves it: a resumed run finds every superstep
        assert Journal(tmp_path, {"run": "j"}, resume=True).recorded_supersteps == n > 2
    assert len(calls) - opened == during_run * n + 2
    assert recorded(tmp_path) == n


@pytest.mark.parametrize("damage", ["cut", "altered"])
def test_a_damaged_log_resumes_from_its_intact_prefix(tmp_path, uninterrupted, damage):
    """The log's last entry cut short (a power loss before its sync) or one byte of it
    changed: the resumed journal keeps the supersteps before it, the run recomputes the rest,
    and the result is the uninterrupted one, bit for bit."""
    result, backend = journaled_run(tmp_path)
    assert same(result, uninterrupted)
    n = len(backend.traces)
    log = tmp_path / LOG
    data = bytearray(log.read_bytes())
    if damage == "cut":
        del data[-100:]
    else:
        data[-100] ^= 0xFF
    log.write_bytes(bytes(data))
    again, kept = resumed_run(tmp_path)
    assert kept == n - 1
    assert same(again, uninterrupted)
    assert recorded(tmp_path) == n
    _, kept = resumed_run(tmp_path)  # the rewritten log is whole again
    assert kept == n


def test_a_bad_interval_is_refused_with_one_line(tmp_path, monkeypatch):
    with pytest.raises(CheckpointError, match="expected >= 0"):
        Journal(tmp_path / "a", {"run": "j"}, resume=False, interval_s=-1.0)
    monkeypatch.setenv(INTERVAL_ENV, "soon")
    proc = run_cli("-m", "ocpar.formation", "--agents", "6", "--quiet", "--checkpoint",
                   str(tmp_path / "b"))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and INTERVAL_ENV in lines[0], proc.stderr


def test_readers_count_the_whole_entries_of_the_log(tmp_path):
    assert recorded_supersteps(tmp_path) == 0
    entries = [b"a" * 5, b"", b"b" * 300]
    with open(tmp_path / LOG, "wb") as log:
        for data in entries:
            log.write(struct.pack("<Q32s", len(data), hashlib.sha256(data).digest()) + data)
        log.write(struct.pack("<Q32s", 50, bytes(32)) + b"c" * 10)   # cut short by a kill
    assert recorded_supersteps(tmp_path) == 3
