"""Real servers for the production tests: a throwaway PostgreSQL database, a private redis-server,
moto's S3 server, a cuttable loopback TCP proxy, and `fleetmap serve` / `fleetmap worker` processes.

Everything binds to 127.0.0.1 on free ports and is torn down by the fixtures that start it.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
DEFAULT_PG_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/0"
TEST_REDIS_URL = os.environ.get("FLEETMAP_TEST_REDIS_URL", DEFAULT_REDIS_URL)  # the Celery tests' broker


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def wait_until(predicate: Callable[[], Any], timeout_s: float, what: str, interval_s: float = 0.1) -> Any:
    """Poll ``predicate`` until it returns a truthy value or ``timeout_s`` passes (then fail)."""
    deadline = time.monotonic() + timeout_s
    last_exc: BaseException | None = None
    while time.monotonic() < deadline:
        try:
            value = predicate()
        except Exception as exc:  # polled again until the deadline
            last_exc = exc
        else:
            if value:
                return value
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s:.0f}s waiting for {what} (last error: {last_exc!r})")


# --- PostgreSQL -------------------------------------------------------------------------------------


def pg_admin_url() -> str:
    return os.environ.get("FLEETMAP_TEST_DATABASE_URL", DEFAULT_PG_URL)


def _psycopg_dsn(sqlalchemy_url: str) -> str:
    return sqlalchemy_url.replace("postgresql+psycopg://", "postgresql://", 1)


def pg_reachable() -> str | None:
    """None if the test PostgreSQL answers, else why not."""
    import psycopg

    try:
        with psycopg.connect(_psycopg_dsn(pg_admin_url()), connect_timeout=3) as conn:
            conn.execute("SELECT 1")
    except psycopg.Error as exc:
        return f"PostgreSQL at {pg_admin_url()} unreachable: {exc}"
    return None


@contextlib.contextmanager
def fresh_database() -> Iterator[str]:
    """A new, empty database ``fleetmap_test_<random>`` on the test server; dropped afterwards.
    Yields its SQLAlchemy URL."""
    import psycopg
    from sqlalchemy.engine import make_url

    admin = pg_admin_url()
    name = f"fleetmap_test_{uuid.uuid4().hex[:12]}"
    with psycopg.connect(_psycopg_dsn(admin), autocommit=True, connect_timeout=5) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    try:
        yield make_url(admin).set(database=name).render_as_string(hide_password=False)
    finally:
        with psycopg.connect(_psycopg_dsn(admin), autocommit=True, connect_timeout=5) as conn:
            conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


# --- Redis ------------------------------------------------------------------------------------------


class RedisServer:
    """A private redis-server on a free loopback port (no persistence: a restart loses the queue)."""

    def __init__(self, workdir: Path) -> None:
        self.port = free_port()
        self.workdir = workdir
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        binary = shutil.which("redis-server")
        if binary is None:
            pytest.skip("redis-server is not installed")
        self.proc = subprocess.Popen(
            [binary, "--bind", "127.0.0.1", "--port", str(self.port), "--save", "", "--appendonly", "no"],
            cwd=self.workdir,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        import redis

        client = redis.Redis(host="127.0.0.1", port=self.port, socket_timeout=1)
        wait_until(client.ping, 15, f"redis-server on port {self.port}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self.proc = None


@contextlib.contextmanager
def database_or_sqlite(tmp_path: Path) -> Iterator[str]:
    """A fresh PostgreSQL database (``fresh_database``), or a shared SQLite file under ``tmp_path`` when
    PostgreSQL is down. Yields its SQLAlchemy URL."""
    if pg_reachable() is not None:
        yield f"sqlite:///{tmp_path / 'shared.db'}"
        return
    with fresh_database() as url:
        yield url


def redis_or_skip(url: str) -> Any:
    """A client of the Redis at ``url``; skips the test when it does not answer."""
    import redis

    client = redis.Redis.from_url(url, socket_connect_timeout=2)
    try:
        client.ping()
    except redis.exceptions.ConnectionError as exc:
        pytest.skip(f"Redis at {url} unreachable: {exc}")
    return client


def stop_group(proc: subprocess.Popen[bytes], grace_s: float = 30) -> None:
    """SIGTERM ``proc``'s process group (started with ``start_new_session``), SIGKILL after ``grace_s``."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


# --- a cuttable TCP proxy ---------------------------------------------------------------------------


class TcpProxy:
    """Forwards 127.0.0.1:<port> to a target; ``cut()`` drops every connection and refuses new ones
    (an outage as clients see it), ``restore()`` accepts again on the same port."""

    def __init__(self, target_host: str, target_port: int) -> None:
        self.target = (target_host, target_port)
        self.port = free_port()
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._listener: socket.socket | None = None
        self._stop = threading.Event()
        self._accepting = threading.Event()
        self._thread = threading.Thread(target=self._accept_loop, daemon=True)

    def start(self) -> TcpProxy:
        self._open_listener()
        self._thread.start()
        return self

    def _open_listener(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(128)
        listener.settimeout(0.2)
        self._listener = listener
        self._accepting.set()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            if not self._accepting.wait(0.2):
                continue
            listener = self._listener
            if listener is None:
                continue
            try:
                client, _ = listener.accept()
            except (TimeoutError, OSError):
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._conns += [client, upstream]
            threading.Thread(target=self._pump, args=(client, upstream), daemon=True).start()

    def _pump(self, a: socket.socket, b: socket.socket) -> None:
        try:
            while not self._stop.is_set():
                readable, _, _ = select.select([a, b], [], [], 0.5)
                for src in readable:
                    data = src.recv(65536)
                    if not data:
                        return
                    (b if src is a else a).sendall(data)
        except (OSError, ValueError):
            return
        finally:
            for sock in (a, b):
                with contextlib.suppress(OSError):
                    sock.close()

    def cut(self) -> None:
        """Close the listener and reset every open connection."""
        self._accepting.clear()
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        with self._lock:
            conns, self._conns = self._conns, []
        for sock in conns:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            with contextlib.suppress(OSError):
                sock.close()

    def restore(self) -> None:
        self._open_listener()

    def stop(self) -> None:
        self._stop.set()
        self.cut()
        self._thread.join(5)


# --- fleetmap processes -----------------------------------------------------------------------------


def fleetmap_cmd(*args: str) -> list[str]:
    """The ``fleetmap`` CLI as a command line (works without the console script being installed)."""
    return [sys.executable, "-m", "service.cli", *args]


def celery_worker_env(settings: Any, broker_url: str, drop: tuple[str, ...] = ("FLEETMAP_",), **extra: str) -> dict[str, str]:
    """The environment of a ``fleetmap worker`` process serving ``settings`` (its database, data folder and
    queue) through ``broker_url``, tiny preset, 60 s leases: this process's environment without the
    variables starting with ``drop``, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(drop)}
    env.update(
        FLEETMAP_BROKER_URL=broker_url,
        FLEETMAP_DATABASE_URL=settings.database_url,
        FLEETMAP_DATA_DIR=str(settings.data_dir),
        FLEETMAP_FUSION_QUEUE=settings.fusion_queue,
        FLEETMAP_FUSION_PRESET="tiny",
        FLEETMAP_LEASE_S="60",
        **extra,
    )
    return env


def spawn_celery_worker(env: dict[str, str], log_path: Path, *args: str) -> subprocess.Popen[bytes]:
    """``fleetmap worker --concurrency 1 --loglevel info *args`` in its own process group, logging to
    ``log_path``; stop it with ``stop_group``."""
    with open(log_path, "wb") as log:
        return subprocess.Popen(
            fleetmap_cmd("worker", "--concurrency", "1", "--loglevel", "info", *args),
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def run_cli(env: dict[str, str], *args: str, timeout_s: float = 120) -> str:
    """Run one ``fleetmap`` command to completion; returns stdout, fails the test on error."""
    done = subprocess.run(
        fleetmap_cmd(*args), cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s
    )
    if done.returncode != 0:
        raise AssertionError(f"fleetmap {' '.join(args)} failed ({done.returncode}): {done.stderr[-3000:]}")
    return done.stdout


class FleetmapProcess:
    """A long-running ``fleetmap`` subprocess (serve or worker) in its own process group."""

    def __init__(self, name: str, args: list[str], env: dict[str, str], logdir: Path) -> None:
        self.name = name
        self.args = args
        self.env = env
        self.log_path = logdir / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> FleetmapProcess:
        log = open(self.log_path, "ab")  # handed to the child, closed below
        self.proc = subprocess.Popen(
            fleetmap_cmd(*self.args),
            cwd=REPO,
            env=self.env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        return self

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal_group(self, sig: int) -> None:
        """Send ``sig`` to the process and all its children (uvicorn/celery pool workers)."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, sig)

    def kill(self) -> None:
        """SIGKILL the whole process group (a crash: no cleanup, no acks)."""
        self.signal_group(signal.SIGKILL)
        if self.proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(10)

    def stop(self, grace_s: float = 10) -> None:
        """SIGTERM, then SIGKILL after ``grace_s``."""
        if not self.alive:
            self.kill()  # reap children left behind by a dead parent
            return
        self.signal_group(signal.SIGTERM)
        assert self.proc is not None
        try:
            self.proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            pass
        self.kill()

    def log_tail(self, chars: int = 4000) -> str:
        with contextlib.suppress(OSError):
            return self.log_path.read_text(errors="replace")[-chars:]
        return ""


def start_api(
    env: dict[str, str], logdir: Path, *, workers: int = 1, name: str = "api", port: int | None = None
) -> tuple[FleetmapProcess, str]:
    """Start ``fleetmap serve`` (on ``port`` or a free one) and wait for /healthz; returns (process, URL)."""
    port = port or free_port()
    args = ["serve", "--host", "127.0.0.1", "--port", str(port), "--workers", str(workers)]
    proc = FleetmapProcess(name, args, env, logdir).start()
    base = f"http://127.0.0.1:{port}"

    def healthy() -> bool:
        if not proc.alive:
            raise RuntimeError(f"{name} exited")
        return httpx.get(f"{base}/healthz", timeout=2).status_code == 200

    try:
        wait_until(healthy, 90, f"{name} /healthz", interval_s=0.2)
    except AssertionError:
        proc.stop()
        raise AssertionError(f"{name} did not become healthy:\n{proc.log_tail()}") from None
    return proc, base


def start_worker(
    env: dict[str, str], logdir: Path, name: str = "worker", **overrides: str
) -> FleetmapProcess:
    """Start one ``fleetmap worker`` (concurrency 1) on the deployment's queue; ``overrides`` are
    extra environment variables for this worker only (e.g. ``FLEETMAP_FUSION_PRESET``)."""
    worker_env = {**env, **overrides}
    return FleetmapProcess(
        name, ["worker", "--concurrency", "1", "--loglevel", "info"], worker_env, logdir
    ).start()


# --- a whole deployment -----------------------------------------------------------------------------


class Deployment:
    """One production-style deployment for a test: its own PostgreSQL database, Celery queue and blob
    folder, ``fleetmap serve`` / ``fleetmap worker`` processes, and an operator token."""

    def __init__(self, database_url: str, broker_url: str, workdir: Path, **settings: str) -> None:
        self.database_url = database_url
        self.broker_url = broker_url
        self.workdir = workdir
        self.queue = f"fleetmap-prod-test-{uuid.uuid4().hex[:10]}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETMAP_")}
        self.env.update(
            FLEETMAP_DATABASE_URL=database_url,
            FLEETMAP_BROKER_URL=broker_url,
            FLEETMAP_FUSION_QUEUE=self.queue,
            FLEETMAP_DATA_DIR=str(workdir / "data"),
            FLEETMAP_BLOB_URL=f"file://{workdir / 'blobs'}",
            FLEETMAP_AUTH="on",
            FLEETMAP_FUSION_PRESET="tiny",
            FLEETMAP_FUSE_DEBOUNCE_S="1",
            FLEETMAP_SCHEDULER_INTERVAL_S="0.5",
            FLEETMAP_LOG_LEVEL="INFO",
        )
        self.env.update({f"FLEETMAP_{k.upper()}": str(v) for k, v in settings.items()})
        self.processes: list[FleetmapProcess] = []
        self._engine: Any = None
        self.token = ""

    def migrate_and_token(self) -> None:
        """Upgrade the schema and create an operator token (in-process, directly on the database)."""
        from service.api.auth import create_token
        from service.store.migrate import upgrade

        upgrade(self.engine)
        with self.session() as db:
            _, self.token = create_token(db, "operator", "prod-test-operator")
            db.commit()

    @property
    def engine(self) -> Any:
        if self._engine is None:
            from sqlalchemy import create_engine

            self._engine = create_engine(self.database_url, pool_pre_ping=True)
        return self._engine

    def session(self) -> Any:
        from sqlalchemy.orm import Session

        return Session(self.engine, expire_on_commit=False)

    @property
    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def api(
        self, *, port: int | None = None, name: str = "api", **overrides: str
    ) -> tuple[FleetmapProcess, str]:
        proc, base = start_api({**self.env, **overrides}, self.workdir, name=name, port=port)
        self.processes.append(proc)
        return proc, base

    def worker(self, name: str = "worker", **overrides: str) -> FleetmapProcess:
        proc = start_worker(self.env, self.workdir, name, **overrides)
        self.processes.append(proc)
        return proc

    def logs(self) -> str:
        return "\n".join(f"--- {p.name} ---\n{p.log_tail(3000)}" for p in self.processes)

    def close(self) -> None:
        for proc in self.processes:
            proc.stop(grace_s=5)
        if self._engine is not None:
            self._engine.dispose()
        with contextlib.suppress(Exception):
            import redis

            redis.Redis.from_url(self.broker_url, socket_timeout=2).delete(
                self.queue, f"_kombu.binding.{self.queue}"
            )


@contextlib.contextmanager
def deployment(tmp_path: Path, broker_url: str | None = None, **settings: str) -> Iterator[Deployment]:
    """A migrated :class:`Deployment` on a fresh PostgreSQL database (skips if PostgreSQL is down)."""
    reason = pg_reachable()
    if reason is not None:
        pytest.skip(reason)
    with fresh_database() as url:
        dep = Deployment(
            url,
            broker_url or os.environ.get("FLEETMAP_TEST_REDIS_URL", DEFAULT_REDIS_URL),
            tmp_path,
            **settings,
        )
        try:
            dep.migrate_and_token()
            yield dep
        finally:
            dep.close()


# --- submaps ----------------------------------------------------------------------------------------

IDENTITY_Q = [1.0, 0.0, 0.0, 0.0]


def submap_meta(
    session: str, seq: int, t: list[float], agent: str | None = None, gps_sigma: float = 1.0
) -> dict[str, Any]:
    """Upload meta of submap ``seq`` of ``session`` at map-frame translation ``t`` (identity rotation),
    GPS sigma ``gps_sigma`` (m and deg); the agent defaults to the session's first path segment."""
    return {
        "agent_id": agent or session.split("/")[0],
        "session_id": session,
        "seq": seq,
        "captured_at": "2026-11-24T08:00:00Z",
        "gps": {"pose": {"t": t, "q": IDENTITY_Q}},
        "gps_sigma": {"trans_m": gps_sigma, "rot_deg": gps_sigma},
        "odometry": {"t": [float(seq), 0.0, 0.0], "q": IDENTITY_Q},
    }


def small_mesh(seed: int = 0) -> bytes:
    """A small labelled street scene (16 m, local frame), made unique by ``seed`` (a sub-mm z shift)."""
    from fusion.meshio import write_submap_ply
    from tests.scene import street

    mesh = street(16.0)
    mesh.vertices = mesh.vertices + [0.0, 0.0, 1e-4 * seed]
    return write_submap_ply(mesh)


def post_submap(
    client: httpx.Client, headers: dict[str, str], meta: dict[str, Any], mesh: bytes
) -> httpx.Response:
    files = {"meta": (None, json.dumps(meta), "application/json"), "mesh": ("submap.ply", mesh)}
    return client.post("/v1/submaps", files=files, headers=headers)
