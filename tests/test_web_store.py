"""The job service's SQLite store: readers never take the write lock (WAL, read-only
connections), so a writer holding it for long delays no GET."""

from __future__ import annotations

import sqlite3
import threading
import time

import pytest

from ocpar.service.web.store import Store, Token


@pytest.fixture
def store(tmp_path) -> Store:
    store = Store(tmp_path / "state")
    store.add_token(Token("a"), "digest-a")
    store.add_job({"id": "formation-20261207-120000-abcdef", "owner": "a",
                   "scheme": "formation", "problem": "point-mass-plane", "config": {},
                   "argv": [], "state": "queued", "submitted": time.time()})
    return store


def test_the_database_is_in_wal_mode(store):
    with sqlite3.connect(store.path) as db:
        assert db.execute("PRAGMA journal_mode").fetchone() == ("wal",)


def test_reads_go_on_while_a_writer_holds_the_write_lock(store):
    """A writer holds the write lock (BEGIN IMMEDIATE, an uncommitted update) for 1 s: every
    read of the store answers within 0.1 s with the last committed state, and the update is
    seen once committed."""
    job = "formation-20261207-120000-abcdef"
    writer = sqlite3.connect(store.path, isolation_level=None)
    writer.execute("BEGIN IMMEDIATE")
    writer.execute("UPDATE jobs SET state = 'running' WHERE id = ?", (job,))
    answers: list[float] = []

    def read() -> None:
        t0 = time.perf_counter()
        assert store.job(job)["state"] == "queued"
        assert store.token_by_hash("digest-a").name == "a"
        assert [row["id"] for row in store.jobs(owner="a", state="queued")] == [job]
        assert [token.name for token in store.tokens()] == ["a"]
        answers.append(time.perf_counter() - t0)

    threads = [threading.Thread(target=read) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    time.sleep(max(0.0, 1.0 - max(answers, default=0)))
    writer.execute("COMMIT")
    writer.close()
    assert len(answers) == 4 and max(answers) < 0.1, answers
    assert store.job(job)["state"] == "running"


def test_a_readers_connection_cannot_write(store):
    with pytest.raises(sqlite3.OperationalError, match="readonly"):
        store.reader().execute("UPDATE jobs SET state = 'failed'")
