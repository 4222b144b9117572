"""End to end, embedded deployment: a real ``fleetmap serve`` process (SQLite, no broker) whose
embedded worker child fuses the tile with the tiny fusion config; everything through HTTP."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import httpx
import pytest

from fusion.meshio import read_fused_ply
from service.client.demo import stop_server
from tests.worker_support import mesh_bytes, upload, wait_for

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def server(tmp_path: Path) -> Any:
    port = free_port()
    env = {
        **{k: v for k, v in os.environ.items() if not k.startswith("FLEETMAP_")},
        "FLEETMAP_DATA_DIR": str(tmp_path / "data"),
        "FLEETMAP_AUTH": "off",
        "FLEETMAP_FUSE_DEBOUNCE_S": "1",
        "FLEETMAP_SCHEDULER_INTERVAL_S": "0.5",
        "FLEETMAP_FUSION_PRESET": "tiny",
        "FLEETMAP_LEASE_S": "60",
    }
    log_path = tmp_path / "serve.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port)],
            cwd=REPO,
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    base = f"http://127.0.0.1:{port}"

    def healthy() -> bool:
        assert proc.poll() is None, log_path.read_text()[-3000:]
        try:
            return httpx.get(f"{base}/healthz", timeout=2).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_for(healthy, 60, "fleetmap serve /healthz")
        with httpx.Client(base_url=base, timeout=30) as client:
            client.proc = proc  # type: ignore[attr-defined]
            client.log_path = log_path  # type: ignore[attr-defined]
            yield client
    finally:
        stop_server(proc)  # as `fleetmap demo` stops it: SIGTERM, SIGKILL to the group if stuck


def children_of(pid: int) -> list[int]:
    """Child process ids of ``pid`` (Linux /proc)."""
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


@pytest.mark.integration
@pytest.mark.slow
def test_fleetmap_serve_fuses_uploads_with_its_embedded_worker(server: httpx.Client) -> None:
    mesh = mesh_bytes()
    created = [upload(server, "veh-1/e2e", seq, [10.0 + 2 * seq, 10.0, 0.0], mesh=mesh) for seq in range(2)]
    assert all(c["tiles"] == [[0, 0]] for c in created)
    proc = server.proc  # type: ignore[attr-defined]
    worker_pids = children_of(proc.pid)
    assert worker_pids, "the embedded worker child process is not running"

    def fused() -> dict[str, Any] | None:
        body = server.get("/v1/tiles/0/0").json()
        assert body["state"] != "failed", body
        return body if body["state"] == "fused" else None

    try:
        tile = wait_for(fused, 240, "tile (0, 0) to be fused", interval_s=0.5)
    except AssertionError:
        raise AssertionError(server.log_path.read_text()[-4000:]) from None  # type: ignore[attr-defined]
    assert tile["version"] == 1 and tile["progress"] == 1.0
    job = server.get(f"/v1/jobs/{tile['job_id']}").json()
    assert job["state"] == "succeeded" and job["metrics"]["submaps"] == 2

    ply = server.get("/v1/tiles/0/0/mesh")
    assert ply.status_code == 200
    fused_mesh = read_fused_ply(ply.content)
    assert len(fused_mesh.faces) > 0
    assert server.get("/v1/tiles/0/0/mesh", params={"format": "glb"}).content[:4] == b"glTF"
    poses = server.get("/v1/sessions/veh-1%2Fe2e/poses").json()
    assert [p["pose_refined"] is not None for p in poses] == [True, True]

    # Shutdown stops the embedded worker with the API.
    proc.send_signal(signal.SIGTERM)
    proc.wait(60)
    for pid in worker_pids:
        wait_for(
            lambda pid=pid: not Path(f"/proc/{pid}").exists() or _zombie(pid), 30, f"worker {pid} to exit"
        )


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    except OSError:
        return True
