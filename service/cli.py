"""The ``fleetmap`` command line: serve, db, token, blobs, worker, demo, map-image, and the fusion tools.

Errors print one line on stderr and exit with status 2. Subcommands that need torch or Celery
(worker, demo, simulate/fuse/bench) are imported only when run.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any

from fusion.eval import cli as fusion_cli
from service.settings import Settings, get_settings

EXIT_ERROR = 2
# Subcommands whose own modules parse the rest of the command line: name → "module:function".
PASSTHROUGH = {
    "worker": ("worker.main:main", "run a Celery fusion worker (production)"),
    "demo": ("service.client.demo:main", "run the embedded demo: simulate a fleet, upload, fuse, serve"),
    "map-image": ("service.client.mapimage:main", "draw a top-down semantic PNG of a service's fused map"),
}


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def _engine(settings: Settings) -> Any:
    from service.store.db import engine_from_settings

    return engine_from_settings(settings)


def cmd_serve(args: argparse.Namespace) -> int:
    """Run the API (uvicorn). Embedded mode upgrades the database and starts the embedded worker."""
    import uvicorn

    from service.api.app import create_app

    settings = get_settings()
    if args.workers > 1:
        # Each uvicorn worker process builds its own app (engine, pools) from the environment.
        if settings.embedded:
            raise CliError(
                "--workers > 1 needs a broker (FLEETMAP_BROKER_URL): the embedded worker is per process"
            )
        uvicorn.run(
            "service.api.app:create_app",
            factory=True,
            host=args.host,
            port=args.port,
            workers=args.workers,
            log_config=None,
            access_log=False,  # RequestContextMiddleware logs every request (with its request id)
            proxy_headers=True,
        )
        return 0
    app = create_app(settings)
    uvicorn.run(app, host=args.host, port=args.port, log_config=None, access_log=False, proxy_headers=True)
    return 0


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    from service.store.migrate import upgrade

    engine = _engine(get_settings())
    try:
        upgrade(engine, args.revision)
    finally:
        engine.dispose()
    print(f"database upgraded to {args.revision}")
    return 0


def _with_db(action: Callable[[Any], int]) -> int:
    """Run ``action(session)`` in one transaction (upgrading an embedded database first)."""
    from service.store.db import make_sessionmaker, session_scope
    from service.store.migrate import upgrade

    settings = get_settings()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = _engine(settings)
    try:
        if settings.embedded:
            upgrade(engine)
        with session_scope(make_sessionmaker(engine)) as db:
            return action(db)
    finally:
        engine.dispose()


def cmd_token_create(args: argparse.Namespace) -> int:
    from service.api.auth import create_token

    def action(db: Any) -> int:
        token, secret = create_token(db, args.role, args.name)
        print(secret)
        print(
            f"created {token.role} token {token.name!r} (id {token.id}); it is shown only once",
            file=sys.stderr,
        )
        return 0

    return _with_db(action)


def cmd_token_list(_args: argparse.Namespace) -> int:
    from service.api.auth import list_tokens

    def action(db: Any) -> int:
        print(f"{'id':36}  {'role':8}  {'name':24}  {'created':25}  revoked")
        for t in list_tokens(db):
            revoked = t.revoked_at.isoformat(timespec="seconds") if t.revoked_at else "-"
            print(
                f"{t.id:36}  {t.role:8}  {t.name:24}  {t.created_at.isoformat(timespec='seconds'):25}  {revoked}"
            )
        return 0

    return _with_db(action)


def cmd_token_revoke(args: argparse.Namespace) -> int:
    from service.api.auth import revoke_tokens

    def action(db: Any) -> int:
        count = revoke_tokens(db, args.token)
        if count == 0:
            raise CliError(f"no active token named or with id {args.token!r}")
        print(f"revoked {count} token(s)")
        return 0

    return _with_db(action)


def cmd_blobs_gc(args: argparse.Namespace) -> int:
    from datetime import timedelta

    from service.store.blobs import blob_store_from_url
    from service.store.gc import collect, referenced

    if not args.min_age_hours >= 0:
        raise CliError(f"--min-age-hours must be >= 0, not {args.min_age_hours}")
    blobs = blob_store_from_url(get_settings().resolved_blob_url)

    def action(db: Any) -> int:
        keep = referenced(db)
        db.rollback()  # no transaction held open over the listing
        report = collect(blobs, keep, min_age=timedelta(hours=args.min_age_hours), dry_run=args.dry_run)
        for sha in report.removed if args.verbose else []:
            print(sha)
        print(report.summary())
        return 0

    return _with_db(action)


def _passthrough(target: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        module_name, func_name = target.split(":")
        func = getattr(importlib.import_module(module_name), func_name)
        result = func(list(args.rest))
        return int(result or 0)

    return run


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fleetmap", description="Crowd-sourced semantic mapping backend")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = sub.add_parser("serve", help="run the HTTP API (embedded: with the fusion worker)")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--workers", type=int, default=1, help="API processes (production: with a broker)")
    serve.set_defaults(func=cmd_serve)

    db = sub.add_parser("db", help="database maintenance")
    db_sub = db.add_subparsers(dest="db_command", required=True, metavar="ACTION")
    up = db_sub.add_parser("upgrade", help="apply migrations (Alembic)")
    up.add_argument("--revision", default="head")
    up.set_defaults(func=cmd_db_upgrade)

    token = sub.add_parser("token", help="API tokens (stored only as hashes)")
    token_sub = token.add_subparsers(dest="token_command", required=True, metavar="ACTION")
    create = token_sub.add_parser("create", help="create a token and print it once")
    create.add_argument("--role", required=True, choices=["vehicle", "operator", "reader"])
    create.add_argument("--name", required=True, help="for vehicles: the agent_id it may upload as")
    create.set_defaults(func=cmd_token_create)
    token_sub.add_parser("list", help="list tokens (never their secrets)").set_defaults(func=cmd_token_list)
    revoke = token_sub.add_parser("revoke", help="revoke tokens by name or id")
    revoke.add_argument("token", metavar="NAME|ID")
    revoke.set_defaults(func=cmd_token_revoke)

    blobs = sub.add_parser("blobs", help="blob store maintenance")
    blobs_sub = blobs.add_subparsers(dest="blobs_command", required=True, metavar="ACTION")
    gc = blobs_sub.add_parser("gc", help="remove blobs no row names (superseded fields, unfinished writes)")
    gc.add_argument("--min-age-hours", type=float, default=24.0,
                    help="only blobs last written longer ago than this (default 24: a job or upload between "
                         "its blob and its row is never touched)")
    gc.add_argument("--dry-run", action="store_true", help="report what would be removed, remove nothing")
    gc.add_argument("--verbose", action="store_true", help="print the sha256 of each blob removed")
    gc.set_defaults(func=cmd_blobs_gc)

    for name, (target, help_text) in PASSTHROUGH.items():
        p = sub.add_parser(name, help=help_text, add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER)
        p.set_defaults(func=_passthrough(target))

    fusion_cli.register(sub)  # adds simulate / fuse / bench; each sets ``func`` and imports lazily
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``fleetmap`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if argv and argv[0] in PASSTHROUGH:  # let the target parse everything, including --help
        args = argparse.Namespace(rest=argv[1:], func=_passthrough(PASSTHROUGH[argv[0]][0]))
    else:
        args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except SystemExit:
        raise
    except Exception as exc:  # one line for people; the traceback only at debug level
        logging.getLogger(__name__).debug("command failed", exc_info=exc)
        print(f"fleetmap: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_ERROR


def _one_line(exc: Exception) -> str:
    """``exc`` for people, on one line; settings errors name their environment variable."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError) and exc.title == "Settings":
        return "; ".join(("FLEETMAP_" + "_".join(map(str, e["loc"])).upper() + ": " if e["loc"] else "")
                         + e["msg"].removeprefix("Value error, ") for e in exc.errors())
    text = str(exc).strip()
    return text.splitlines()[0] if text else exc.__class__.__name__


if __name__ == "__main__":
    sys.exit(main())
