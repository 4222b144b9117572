"""FastAPI dependencies, declared once as ``Annotated`` types (settings, DB session, blobs, caller).

The cheap ones are ``async def``: FastAPI runs a plain ``def`` dependency in the threadpool, and a
hop per dependency was a measurable part of every request. The caller's token is looked up in the
process's token cache first (see :mod:`service.api.auth`) and only on a miss in the database (one hop).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Coroutine, Iterator
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session

from service.api.auth import ANONYMOUS_OPERATOR, Principal, TokenCache, authenticate, hash_token
from service.api.problems import ProblemError
from service.settings import Settings
from service.store.blobs import BlobStore
from service.store.models import Role

log = logging.getLogger(__name__)


async def get_settings_dep(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


def get_db(request: Request) -> Iterator[Session]:
    """One session per request; routes commit explicitly, anything uncommitted is rolled back."""
    session: Session = request.app.state.session_factory()
    try:
        yield session
    finally:
        try:
            session.close()
        except DBAPIError as exc:
            # The database went away after the response was built (its final ROLLBACK failed).
            # The pool has dropped that connection; raising here would abort an already-sent
            # response and the client's keep-alive connection with it.
            log.warning("closing a database session failed (%s); the connection was discarded", exc.orig)


async def get_blobs(request: Request) -> BlobStore:
    return request.app.state.blobs  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(get_settings_dep)]
SessionDep = Annotated[Session, Depends(get_db)]
BlobsDep = Annotated[BlobStore, Depends(get_blobs)]

_bearer = HTTPBearer(
    auto_error=False, description="`Authorization: Bearer <token>` (created with `fleetmap token create`)"
)
_CHALLENGE = {"WWW-Authenticate": "Bearer"}


def _token_cache(request: Request, settings: Settings) -> TokenCache:
    cache: TokenCache | None = getattr(request.app.state, "token_cache", None)
    if cache is None:
        cache = request.app.state.token_cache = TokenCache(settings.auth_cache_s)
    return cache


def _lookup_token(request: Request, secret: str, cache: TokenCache) -> Principal | None:
    with request.app.state.session_factory() as db:
        return authenticate(db, secret, cache)


async def get_principal(
    request: Request,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Principal:
    """The caller; 401 without a valid token (any operator when ``FLEETMAP_AUTH=off``)."""
    if not settings.auth_enabled:
        return ANONYMOUS_OPERATOR
    if credentials is None or credentials.scheme.lower() != "bearer" or not credentials.credentials:
        raise ProblemError(401, "a bearer token is required", code="unauthenticated", headers=_CHALLENGE)
    cache = _token_cache(request, settings)
    principal = cache.get(hash_token(credentials.credentials))
    if principal is None:
        principal = await run_in_threadpool(_lookup_token, request, credentials.credentials, cache)
    if principal is None:
        raise ProblemError(
            401,
            "the bearer token is invalid or revoked",
            code="invalid_token",
            headers={"WWW-Authenticate": 'Bearer error="invalid_token"'},
        )
    return principal


def require_roles(*roles: Role) -> Callable[[Principal], Coroutine[Any, Any, Principal]]:
    """A dependency admitting only ``roles`` (403 otherwise)."""

    async def check(principal: Annotated[Principal, Depends(get_principal)]) -> Principal:
        if principal.role not in roles:
            allowed = ", ".join(r.value for r in roles)
            raise ProblemError(
                403, f"role {principal.role.value!r} may not do this (needs {allowed})", code="forbidden"
            )
        return principal

    return check


AnyRole = Annotated[Principal, Depends(require_roles(Role.vehicle, Role.operator, Role.reader))]
Uploader = Annotated[Principal, Depends(require_roles(Role.vehicle, Role.operator))]
Reader = Annotated[Principal, Depends(require_roles(Role.reader, Role.operator))]
Operator = Annotated[Principal, Depends(require_roles(Role.operator))]
