"""The server's state: a SQLite database (WAL) of tokens and jobs in the state directory, and
the jobs' directories beside it (``STATE_DIR/jobs/<id>``, laid out as
:mod:`ocpar.service.jobs` describes: ``checkpoint/``, ``output/``, ``log.txt``, ``cancel``).

Readers never take the write lock: every read runs on a read-only connection of its thread
(``mode=ro``, kept open), whose SELECT sees the last committed state (WAL: readers and the
one writer do not wait for each other). Every write opens its own connection for one short
``BEGIN IMMEDIATE`` transaction, so the HTTP handlers' threads, the supervisor's thread and
the ``ocpar serve token`` command can use one store at once.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: The job states of the HTTP service, and the final ones among them.
STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINAL = frozenset({"succeeded", "failed", "cancelled"})

SCHEMA = """
CREATE TABLE IF NOT EXISTS tokens (
    name TEXT PRIMARY KEY,
    hash TEXT NOT NULL UNIQUE,
    max_jobs INTEGER,           -- jobs running at once (the rest wait, queued)
    max_agents INTEGER,         -- formation agents / pursuit max_agents per job
    max_evaluations INTEGER,    -- MACS max_evals per job
    wall_time REAL,             -- seconds a job may run before it is cancelled
    created REAL NOT NULL,
    solver_options TEXT         -- JSON list of the solver options' patterns (NULL: the server's)
);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    owner TEXT NOT NULL,        -- the token's name
    scheme TEXT NOT NULL,
    problem TEXT NOT NULL,
    config TEXT NOT NULL,       -- the checked configuration (JSON: scheme and keys)
    argv TEXT NOT NULL,         -- the scheme's command line for it (JSON list)
    state TEXT NOT NULL,
    reason TEXT,
    submitted REAL NOT NULL,
    started REAL,
    finished REAL,
    idempotency_key TEXT,
    pid INTEGER,                -- the run's process (leader of its process group)
    resume INTEGER NOT NULL DEFAULT 0,   -- the next start resumes from the checkpoint
    stop_reason TEXT,           -- why the server asked the run to stop (wall time)
    exit_status INTEGER,
    result_status TEXT,
    headline TEXT,              -- result.json's title
    UNIQUE (owner, idempotency_key)
);
CREATE INDEX IF NOT EXISTS jobs_by_owner ON jobs (owner, submitted);
CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs (state, submitted);
"""


#: A new token's limits unless the operator gives others (``ocpar serve token add``; None:
#: unlimited): jobs running at once, formation agents (pursuit max_agents) per job, MACS
#: evaluations per job, seconds a job may run.
DEFAULT_LIMITS = {"max_jobs": 2, "max_agents": 100_000, "max_evaluations": 100_000,
                  "wall_time": 3600.0}

#: The solver options a job may set unless the operator says otherwise (``ocpar serve
#: --allow-solver-option``): every inner solver's, but those that name files or libraries on
#: the server (:data:`~ocpar.ocp.solver_options.HOST_FILE_OPTIONS`), which only a pattern
#: without wildcards allows.
DEFAULT_SOLVER_OPTIONS = ("ipopt.*", "sqpmethod.*", "qrqp.*", "newton.*")


@dataclass(frozen=True)
class Token:
    """A client's token (by name) and its limits (None: unlimited; the defaults:
    :data:`DEFAULT_LIMITS`); ``solver_options`` the fnmatch patterns of the solver options
    its jobs may set, within the server's (None: the server's)."""

    name: str
    max_jobs: int | None = DEFAULT_LIMITS["max_jobs"]
    max_agents: int | None = DEFAULT_LIMITS["max_agents"]
    max_evaluations: int | None = DEFAULT_LIMITS["max_evaluations"]
    wall_time: float | None = DEFAULT_LIMITS["wall_time"]
    solver_options: tuple[str, ...] | None = None


class Store:
    """The database ``STATE_DIR/server.sqlite3`` and the jobs' directories."""

    def __init__(self, state_dir: str | Path) -> None:
        self.state_dir = Path(state_dir).expanduser().resolve()
        self.jobs_dir = self.state_dir / "jobs"
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.state_dir / "server.sqlite3"
        db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(SCHEMA)
            columns = {row[1] for row in db.execute("PRAGMA table_info(tokens)")}
            if "solver_options" not in columns:   # a database of an earlier version
                db.execute("ALTER TABLE tokens ADD COLUMN solver_options TEXT")
        finally:
            db.close()
        self._readers = threading.local()

    def reader(self) -> sqlite3.Connection:
        """This thread's read-only connection (rows as mappings); each statement is a read
        transaction of its own."""
        db = getattr(self._readers, "db", None)
        if db is None:
            db = sqlite3.connect(f"{self.path.as_uri()}?mode=ro", uri=True, timeout=30,
                                 isolation_level=None)
            db.row_factory = sqlite3.Row
            self._readers.db = db
        return db

    @contextlib.contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        """A connection in one write transaction (committed on success), rows as
        mappings."""
        db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            db.execute("BEGIN IMMEDIATE")
            yield db
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        finally:
            db.close()

    def job_dir(self, job_id: str) -> Path:
        """The directory of job ``job_id``."""
        return self.jobs_dir / job_id

    # tokens ------------------------------------------------------------------------------

    def add_token(self, token: Token, digest: str) -> None:
        """Store ``token`` with the SHA-256 ``digest`` of its secret (ValueError if the name
        is taken)."""
        try:
            with self.connect() as db:
                db.execute("INSERT INTO tokens (name, hash, max_jobs, max_agents, "
                           "max_evaluations, wall_time, created, solver_options) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                           (token.name, digest, token.max_jobs, token.max_agents,
                            token.max_evaluations, token.wall_time, time.time(),
                            None if token.solver_options is None
                            else json.dumps(list(token.solver_options))))
        except sqlite3.IntegrityError:
            raise ValueError(f"a token named {token.name!r} exists already") from None

    def remove_token(self, name: str) -> bool:
        """Delete the token named ``name`` (its jobs stay); whether there was one."""
        with self.connect() as db:
            return db.execute("DELETE FROM tokens WHERE name = ?", (name,)).rowcount == 1

    def token_by_hash(self, digest: str) -> Token | None:
        """The token whose secret has SHA-256 ``digest``, if any."""
        row = self.reader().execute("SELECT * FROM tokens WHERE hash = ?",
                                    (digest,)).fetchone()
        return _token(row) if row else None

    def token(self, name: str) -> Token | None:
        """The token named ``name``, if any."""
        row = self.reader().execute("SELECT * FROM tokens WHERE name = ?", (name,)).fetchone()
        return _token(row) if row else None

    def tokens(self) -> list[Token]:
        """Every token, by name."""
        return [_token(row) for row in self.reader().execute(
            "SELECT * FROM tokens ORDER BY name")]

    # jobs --------------------------------------------------------------------------------

    def add_job(self, job: dict[str, Any]) -> dict[str, Any] | None:
        """Insert the job row ``job`` (state queued); returns None, or the existing job of
        the same owner and idempotency key (nothing inserted then)."""
        with self.connect() as db:
            if job.get("idempotency_key") is not None:
                row = db.execute("SELECT * FROM jobs WHERE owner = ? AND idempotency_key = ?",
                                 (job["owner"], job["idempotency_key"])).fetchone()
                if row:  # the write lock is held: no other insert in between
                    return dict(row)
            columns = ", ".join(job)
            db.execute(f"INSERT INTO jobs ({columns}) VALUES ({', '.join('?' * len(job))})",
                       [json.dumps(v) if isinstance(v, dict | list) else v
                        for v in job.values()])
        return None

    def job(self, job_id: str) -> dict[str, Any] | None:
        """The row of job ``job_id``, if any."""
        row = self.reader().execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return dict(row) if row else None

    def job_by_key(self, owner: str, key: str) -> dict[str, Any] | None:
        """The job ``owner`` submitted with idempotency key ``key``, if any."""
        row = self.reader().execute("SELECT * FROM jobs WHERE owner = ? AND idempotency_key = ?",
                                    (owner, key)).fetchone()
        return dict(row) if row else None

    def jobs(self, owner: str | None = None, state: str | None = None) -> list[dict[str, Any]]:
        """Rows of jobs (of ``owner``, in ``state``), newest first."""
        where, args = [], []
        if owner is not None:
            where.append("owner = ?")
            args.append(owner)
        if state is not None:
            where.append("state = ?")
            args.append(state)
        sql = "SELECT * FROM jobs" + (f" WHERE {' AND '.join(where)}" if where else "")
        return [dict(row) for row in self.reader().execute(
            sql + " ORDER BY submitted DESC, id DESC", args)]

    def update(self, job_id: str, only_if: str | tuple[str, ...] | None = None,
               **values: Any) -> bool:
        """Set ``values`` of job ``job_id`` (only if its state is in ``only_if``); whether
        it was set."""
        states = (only_if,) if isinstance(only_if, str) else only_if
        sql = f"UPDATE jobs SET {', '.join(f'{key} = ?' for key in values)} WHERE id = ?"
        args = [*values.values(), job_id]
        if states:
            sql += f" AND state IN ({', '.join('?' * len(states))})"
            args += list(states)
        with self.connect() as db:
            return db.execute(sql, args).rowcount == 1


def _token(row: sqlite3.Row) -> Token:
    patterns = row["solver_options"]
    return Token(row["name"], row["max_jobs"], row["max_agents"], row["max_evaluations"],
                 row["wall_time"], None if patterns is None else tuple(json.loads(patterns)))
