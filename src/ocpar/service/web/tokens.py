"""Bearer tokens: issued once by ``ocpar serve token add NAME``, stored as SHA-256 hashes,
revoked by ``ocpar serve token revoke NAME``."""

from __future__ import annotations

import hashlib
import secrets
import time
from dataclasses import dataclass

from ocpar.service.web.store import Store, Token

#: A token's prefix (so a leaked one is recognisable) before 32 random bytes, URL-safe.
PREFIX = "ocpar_"


def digest(secret: str) -> str:
    """The SHA-256 hex digest under which the token ``secret`` is stored."""
    return hashlib.sha256(secret.encode("utf-8", "surrogateescape")).hexdigest()


def issue(store: Store, token: Token) -> str:
    """Store ``token`` (its name and limits) and return its secret, which is kept nowhere."""
    if not token.name or not token.name.isprintable() or len(token.name) > 64:
        raise ValueError(f"token name {token.name!r}: expected 1 to 64 printable characters")
    for field in ("max_jobs", "max_agents", "max_evaluations", "wall_time"):
        value = getattr(token, field)
        if value is not None and value <= 0:
            raise ValueError(f"--{field.replace('_', '-')} must be positive, got {value}")
    secret = PREFIX + secrets.token_urlsafe(32)
    store.add_token(token, digest(secret))
    return secret


def authenticate(store: Store, secret: str) -> Token | None:
    """The token whose secret is ``secret``, if any."""
    return store.token_by_hash(digest(secret))


@dataclass(frozen=True)
class Revoked:
    """What :func:`revoke` did: the token's queued jobs cancelled, its running jobs asked to
    stop (at their next superstep boundary), by id."""

    cancelled: list[str]
    stopping: list[str]


def revoke(store: Store, name: str) -> Revoked:
    """Delete the token ``name`` (it authenticates no more; a ValueError if there is none),
    cancel its queued jobs and ask its running ones to stop; its finished jobs and their
    files stay. Works beside a running server (the database and the jobs' stop files)."""
    if not store.remove_token(name):
        raise ValueError(f"no token named {name!r} (ocpar serve token list shows them)")
    reason = f"its token {name!r} was revoked"
    cancelled, stopping = [], []
    for row in store.jobs(owner=name):
        if row["state"] == "queued" and store.update(
                row["id"], only_if="queued", state="cancelled", finished=time.time(),
                reason=reason):
            cancelled.append(row["id"])
        elif row["state"] == "running" and store.update(
                row["id"], only_if="running", stop_reason=reason):
            (store.job_dir(row["id"]) / "cancel").touch()
            stopping.append(row["id"])
    return Revoked(cancelled, stopping)
