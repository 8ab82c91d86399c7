"""Bearer tokens: issued once by ``ocpar serve token add NAME``, stored as SHA-256 hashes."""

from __future__ import annotations

import hashlib
import secrets

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
