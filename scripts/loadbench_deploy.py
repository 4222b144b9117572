"""The load benchmark's own deployment (``scripts/loadbench.py`` without ``--url``): a fresh PostgreSQL
database on the given server, a private Redis queue, a file blob store under a temporary folder, the API
(``fleetmap serve``) and ``--fusion-workers`` Celery workers, all on loopback, removed afterwards."""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _fleetmap(*args: str) -> list[str]:
    return [sys.executable, "-m", "service.cli", *args]


@contextlib.contextmanager
def local_deployment(
    args: argparse.Namespace, vehicles: list[str]
) -> Iterator[tuple[str, str, dict[str, str], int | None]]:
    """Start PostgreSQL-database + Redis + API + worker on loopback; yields (url, operator, tokens,
    API pid)."""
    import psycopg
    from sqlalchemy.engine import make_url

    run = uuid.uuid4().hex[:10]
    admin = make_url(args.pg_url)
    db_name = f"fleetmap_bench_{run}"
    dsn = admin.set(drivername="postgresql").render_as_string(hide_password=False)
    with psycopg.connect(dsn, autocommit=True, connect_timeout=5) as conn:
        conn.execute(f'CREATE DATABASE "{db_name}"')
    workdir = Path(tempfile.mkdtemp(prefix="fleetmap-bench-"))
    procs: list[subprocess.Popen[bytes]] = []
    env = _deployment_env(args, admin.set(database=db_name).render_as_string(hide_password=False), run, workdir)
    try:
        subprocess.run(_fleetmap("db", "upgrade"), cwd=REPO, env=env, check=True, capture_output=True)
        tokens = {}
        for name, role in [("bench-operator", "operator")] + [(v, "vehicle") for v in vehicles]:
            tokens[name] = _create_token(env, role, name)
        port = _free_port()
        _start_services(args, env, port, workdir, procs)
        url = f"http://127.0.0.1:{port}"
        _wait_ready(url, procs[0], workdir)
        print(f"deployment: {url} db={db_name} broker={args.redis_url} logs={workdir}", flush=True)
        yield url, tokens.pop("bench-operator"), tokens, procs[0].pid
    finally:
        _stop_all(procs)
        with psycopg.connect(dsn, autocommit=True, connect_timeout=5) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{db_name}" WITH (FORCE)')
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)


def _deployment_env(args: argparse.Namespace, database_url: str, run: str, workdir: Path) -> dict[str, str]:
    """The ``FLEETMAP_*`` settings of the deployment's processes (this run's database, queue and data)."""
    env = dict(os.environ)
    env.update(
        FLEETMAP_DATABASE_URL=database_url,
        FLEETMAP_BROKER_URL=args.redis_url,
        FLEETMAP_FUSION_QUEUE=f"fusion-bench-{run}",
        FLEETMAP_BLOB_URL=args.blob_url or f"file://{workdir / 'blobs'}",
        FLEETMAP_DATA_DIR=str(workdir),
        FLEETMAP_AUTH="on",
        FLEETMAP_LOG_LEVEL="WARNING",
    )
    if args.fuse_debounce is not None:
        env.update(
            FLEETMAP_FUSE_DEBOUNCE_S=str(args.fuse_debounce),
            FLEETMAP_SCHEDULER_INTERVAL_S=str(min(5.0, max(0.5, args.fuse_debounce / 2))),
        )
    if args.fusion_preset:
        env["FLEETMAP_FUSION_PRESET"] = args.fusion_preset
    return env


def _start_services(
    args: argparse.Namespace, env: dict[str, str], port: int, workdir: Path, procs: list[subprocess.Popen[bytes]]
) -> None:
    """The API on ``port`` (first in ``procs``) and ``args.fusion_workers`` Celery workers, each with its
    metrics port (appended to ``args.worker_metrics_ports``); logs under ``workdir``."""
    worker_env = dict(env, FLEETMAP_TORCH_THREADS=str(args.torch_threads))
    log = open(workdir / "api.log", "ab")  # noqa: SIM115 - the child owns it
    procs.append(
        subprocess.Popen(
            _fleetmap("serve", "--host", "127.0.0.1", "--port", str(port), "--workers", str(args.api_workers)),
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    )
    for k in range(args.fusion_workers):
        wlog = open(workdir / f"worker{k}.log", "ab")  # noqa: SIM115
        metrics_port = _free_port()
        args.worker_metrics_ports.append(metrics_port)
        procs.append(
            subprocess.Popen(
                _fleetmap("worker", "--concurrency", "1", "--metrics-port", str(metrics_port)),
                cwd=REPO,
                env=worker_env,
                stdout=wlog,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        )


def _wait_ready(url: str, api: subprocess.Popen[bytes], workdir: Path) -> None:
    """Until ``GET /readyz`` answers 200 (at most 60 s; fails early if the API exits)."""
    deadline = time.monotonic() + 60
    while True:
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return
        if time.monotonic() > deadline or api.poll() is not None:
            raise RuntimeError(f"API did not become ready; log: {workdir / 'api.log'}")
        time.sleep(0.3)


def _stop_all(procs: list[subprocess.Popen[bytes]]) -> None:
    """SIGTERM every process group, then SIGKILL those still running after 15 s."""
    for proc in procs:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
    for proc in procs:
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


def _create_token(env: dict[str, str], role: str, name: str) -> str:
    out = subprocess.run(
        _fleetmap("token", "create", "--role", role, "--name", name),
        cwd=REPO,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    secrets = [w for w in out.split() if w.startswith("fm_")]
    if not secrets:
        raise RuntimeError(f"no token in `fleetmap token create` output: {out!r}")
    return secrets[0]
