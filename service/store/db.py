"""Database engine and sessions: the same code on SQLite (embedded) and PostgreSQL (psycopg 3).

SQLite gets WAL, foreign keys and a busy timeout on every connection so that the API, the
scheduler and the embedded worker can share one file.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

from sqlalchemy import Engine, Table, create_engine, event, exc, text
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.settings import Settings

log = logging.getLogger(__name__)

SQLITE_BUSY_TIMEOUT_MS = 30_000


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def postgres_engine_options(settings: Settings | None = None, url_options: str = "") -> dict[str, Any]:
    """Production pool and connection options for PostgreSQL (psycopg 3).

    Liveness: a connection that sat idle in the pool for ``db_ping_idle_s`` is pinged on checkout
    (see :func:`_install_idle_ping`) and replaced if dead; a busy pool skips that round trip. A
    connection that dies in use raises a disconnect error, which invalidates the whole pool (every
    older connection is replaced on its next checkout). Connect/pool timeouts turn an outage into
    fast errors (503) instead of hung requests; TCP keepalives and ``tcp_user_timeout`` detect a
    silently dead peer; ``statement_timeout`` bounds every statement server-side. ``url_options``
    (the URL's own ``options=`` query, e.g. a search_path) is kept.
    """
    s = settings or Settings()
    timeout = f"-c statement_timeout={s.db_statement_timeout_ms}" if s.db_statement_timeout_ms else ""
    options = " ".join(part for part in (url_options, timeout) if part)
    connect_args: dict[str, Any] = {
        "connect_timeout": s.db_connect_timeout_s,
        "keepalives": 1,
        "keepalives_idle": 30,
        "keepalives_interval": 10,
        "keepalives_count": 3,
        "tcp_user_timeout": s.db_connect_timeout_s * 1000 + 10_000,
        "application_name": "fleetmap",
    }
    if options:
        connect_args["options"] = options
    return {
        "pool_pre_ping": s.db_ping_idle_s <= 0,
        "pool_size": s.db_pool_size,
        "max_overflow": s.db_max_overflow,
        "pool_timeout": s.db_pool_timeout_s,
        "pool_recycle": s.db_pool_recycle_s,
        "connect_args": connect_args,
    }


_CHECKIN_AT = "fleetmap_checkin_at"


def _install_idle_ping(engine: Engine, idle_s: float) -> None:
    """Pre-ping only connections that were idle in the pool for ``idle_s`` seconds or more.

    A ping per checkout was a round trip on every request; under load connections come back within
    milliseconds and a dead one is noticed by its first statement anyway. Raising
    ``DisconnectionError`` from the checkout event makes the pool discard the connection and check
    out (or open) another.
    """

    @event.listens_for(engine, "checkin")
    def _checkin(_dbapi_connection: Any, record: Any) -> None:
        record.info[_CHECKIN_AT] = time.monotonic()

    @event.listens_for(engine, "checkout")
    def _checkout(dbapi_connection: Any, record: Any, _proxy: Any) -> None:
        since = record.info.get(_CHECKIN_AT)
        if since is None or time.monotonic() - since < idle_s:
            return  # just opened, or recently in use
        try:
            engine.dialect.do_ping(dbapi_connection)
        except Exception as err:
            record.info.pop(_CHECKIN_AT, None)
            raise exc.DisconnectionError(f"pooled connection failed its ping: {err}") from err


def make_engine(url: str, settings: Settings | None = None) -> Engine:
    """An engine for ``url``; creates the parent folder of a SQLite file. PostgreSQL gets the pool
    and timeout options of :func:`postgres_engine_options` (from ``settings``, else defaults)."""
    parsed = make_url(url)
    kwargs: dict[str, Any] = {"pool_pre_ping": True}
    if parsed.get_backend_name() == "postgresql":
        url_options = parsed.query.get("options", "")
        kwargs = postgres_engine_options(
            settings, url_options if isinstance(url_options, str) else " ".join(url_options)
        )
    if parsed.get_backend_name() == "sqlite":
        if parsed.database and parsed.database != ":memory:":
            Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
        kwargs["connect_args"] = {"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}
    engine = create_engine(url, **kwargs)
    if parsed.get_backend_name() == "sqlite":
        event.listen(engine, "connect", _sqlite_pragmas)
    elif not kwargs.get("pool_pre_ping"):
        _install_idle_ping(engine, (settings or Settings()).db_ping_idle_s)
    return engine


def engine_from_settings(settings: Settings) -> Engine:
    """The engine for the configured database."""
    return make_engine(settings.resolved_database_url, settings)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    """Sessions that keep loaded attributes after commit (responses are built after commit)."""
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that commits on success and rolls back on error (for scripts and workers)."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def ping(engine: Engine) -> None:
    """Raise if the database cannot answer ``SELECT 1``."""
    with engine.connect() as conn:
        conn.execute(text("SELECT 1"))


def is_postgres(db: Session) -> bool:
    """Whether ``db`` talks to PostgreSQL (else SQLite, the embedded default)."""
    return db.get_bind().dialect.name == "postgresql"


def table_of(model: type[Any]) -> Table:
    """The Core ``Table`` of a declarative model (SQLAlchemy types ``__table__`` as a ``FromClause``)."""
    return cast(Table, model.__table__)


def insert_ignore(db: Session, model: type[Any], rows: list[dict[str, Any]]) -> None:
    """INSERT … ON CONFLICT DO NOTHING on either backend.

    Core executemany with bound rows: the statement compiles once and is cached (a ``.values(rows)``
    statement recompiled on every upload and was a hot spot of the ingest path).
    """
    module = postgresql if is_postgres(db) else sqlite
    db.connection().execute(module.insert(table_of(model)).on_conflict_do_nothing(), rows)
