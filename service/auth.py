"""Bearer tokens: random secrets stored only as sha256 hashes, one role each.

Roles (API.md): ``vehicle`` uploads under its own agent_id (the token's name), ``operator`` can do
everything, ``reader`` reads labels, tiles, meshes, submaps and poses.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass

from sqlalchemy import or_, select
from sqlalchemy.orm import Session

from service.models import Role, Token, utcnow

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


def revoke_tokens(db: Session, name_or_id: str) -> int:
    """Revoke every active token whose name or id matches; returns how many were revoked."""
    rows = db.scalars(
        select(Token).where(or_(Token.name == name_or_id, Token.id == name_or_id), Token.revoked_at.is_(None))
    ).all()
    now = utcnow()
    for row in rows:
        row.revoked_at = now
    return len(rows)


def authenticate(db: Session, secret: str) -> Principal | None:
    """The principal of an active token, or None."""
    token = db.scalar(select(Token).where(Token.token_hash == hash_token(secret), Token.revoked_at.is_(None)))
    if token is None:
        return None
    return Principal(name=token.name, role=Role(token.role), token_id=token.id)
