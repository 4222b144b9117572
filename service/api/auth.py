"""Bearer tokens: random secrets stored only as sha256 hashes, one role each.

Roles (API.md): ``vehicle`` uploads under its own agent_id (the token's name), ``operator`` can do
everything, ``reader`` reads labels, tiles, meshes, submaps and poses.

Valid tokens are cached per API process for ``FLEETMAP_AUTH_CACHE_S`` seconds (default 5; 0: off) so
that a request does not pay a database round trip for its token. A revocation therefore takes effect
within that many seconds in every process (``fleetmap token revoke`` runs in another process), and at
once in the process that revoked (:func:`revoke_tokens` clears the caches it can reach). Unknown or
revoked tokens are never cached: a new token works at once.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
import weakref
from dataclasses import dataclass

from sqlalchemy import bindparam, or_, select
from sqlalchemy.orm import Session

from service.store.models import Role, Token, utcnow

TOKEN_PREFIX = "fm_"


@dataclass(frozen=True)
class Principal:
    """Who is calling: the token's name (a vehicle's agent_id) and role."""

    name: str
    role: Role
    token_id: str | None = None

    def may_upload_as(self, agent_id: str) -> bool:
        """Vehicles upload only under their own agent_id; operators under any."""
        return self.role == Role.operator or (self.role == Role.vehicle and self.name == agent_id)


ANONYMOUS_OPERATOR = Principal(name="anonymous", role=Role.operator)


def hash_token(secret: str) -> str:
    """The stored form of a token (sha256 hex of its secret)."""
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


def create_token(db: Session, role: Role | str, name: str) -> tuple[Token, str]:
    """Create a token; returns the row and the secret, which is shown once and never stored."""
    role = Role(role)
    if not name.strip():
        raise ValueError("a token needs a non-empty name")
    secret = TOKEN_PREFIX + secrets.token_urlsafe(32)
    token = Token(name=name, role=role.value, token_hash=hash_token(secret))
    db.add(token)
    db.flush()
    return token, secret


def list_tokens(db: Session) -> list[Token]:
    return list(db.scalars(select(Token).order_by(Token.created_at, Token.name)))


class TokenCache:
    """token hash → principal for ``ttl_s`` seconds (bounded; only valid tokens are stored)."""

    MAX_ENTRIES = 10_000

    def __init__(self, ttl_s: float) -> None:
        self.ttl_s = ttl_s
        self._entries: dict[str, tuple[float, Principal]] = {}
        self._lock = threading.Lock()
        _CACHES.add(self)

    def get(self, token_hash: str) -> Principal | None:
        entry = self._entries.get(token_hash)
        if entry is None:
            return None
        if entry[0] <= time.monotonic():
            with self._lock:
                self._entries.pop(token_hash, None)
            return None
        return entry[1]

    def put(self, token_hash: str, principal: Principal) -> None:
        if self.ttl_s <= 0:
            return
        with self._lock:
            if len(self._entries) >= self.MAX_ENTRIES:
                self._entries.clear()
            self._entries[token_hash] = (time.monotonic() + self.ttl_s, principal)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


_CACHES: weakref.WeakSet[TokenCache] = weakref.WeakSet()


def clear_token_caches() -> None:
    """Forget every cached token of this process (after a revocation)."""
    for cache in list(_CACHES):
        cache.clear()


def revoke_tokens(db: Session, name_or_id: str) -> int:
    """Revoke every active token whose name or id matches; returns how many were revoked.

    This process's token caches are cleared; other API processes honour the revocation within
    ``FLEETMAP_AUTH_CACHE_S`` seconds."""
    rows = db.scalars(
        select(Token).where(or_(Token.name == name_or_id, Token.id == name_or_id), Token.revoked_at.is_(None))
    ).all()
    now = utcnow()
    for row in rows:
        row.revoked_at = now
    clear_token_caches()
    return len(rows)


_LOOKUP = select(Token.id, Token.name, Token.role).where(
    Token.token_hash == bindparam("h"), Token.revoked_at.is_(None)
)


def authenticate(db: Session, secret: str, cache: TokenCache | None = None) -> Principal | None:
    """The principal of an active token, or None (``cache``: consulted first, filled on success)."""
    token_hash = hash_token(secret)
    if cache is not None and (hit := cache.get(token_hash)) is not None:
        return hit
    row = db.execute(_LOOKUP, {"h": token_hash}).first()
    if row is None:
        return None
    principal = Principal(name=row.name, role=Role(row.role), token_id=row.id)
    if cache is not None:
        cache.put(token_hash, principal)
    return principal
