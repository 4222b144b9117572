"""``fleetmap demo`` (the README's run command) end to end with the tiny fusion preset and one session:
every tile it reports ends fused, it draws ``map.png`` and, with ``--serve``, keeps the service up for the
viewer until it is told to stop."""

from __future__ import annotations

import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from fusion.labels import LABEL_BY_NAME

REPO = Path(__file__).resolve().parents[2]
ROW = re.compile(r"^\s*\((-?\d+),(-?\d+)\)\s+(\w+)\s")
VIEWER = re.compile(r"^viewer: (http://127\.0\.0\.1:\d+)/ \(serving")


def _lines(stream: object) -> queue.Queue[str]:
    """The lines of ``stream`` as they come, from a reader thread."""
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        for line in stream:  # type: ignore[attr-defined]
            lines.put(line)

    threading.Thread(target=read, daemon=True).start()
    return lines


def _until_viewer(proc: subprocess.Popen[str], lines: queue.Queue[str], timeout_s: float) -> tuple[str, list[str]]:
    """Read the demo's output until it prints the viewer URL; returns the URL and the lines so far."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            assert proc.poll() is None, "".join(seen)[-3000:]
            continue
        seen.append(line)
        if match := VIEWER.match(line):
            return match.group(1), seen
    raise AssertionError("no viewer URL within the timeout:\n" + "".join(seen)[-3000:])


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_demo_fuses_every_tile_draws_the_map_and_serves(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "demo", "--sessions", "1", "--preset", "tiny", "--out", str(out),
         "--serve"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        url, seen = _until_viewer(proc, _lines(proc.stdout), 1100)
        stdout = "".join(seen)
        log = (out / "serve.log").read_text() if (out / "serve.log").exists() else ""
        rows = [ROW.match(line) for line in seen]
        states = {(int(m.group(1)), int(m.group(2))): m.group(3) for m in rows if m}
        assert states and set(states.values()) == {"fused"}, stdout[-3000:] + log[-3000:]
        assert "geo F" in stdout and "refined" in stdout
        assert list((out / "meshes").glob("tile_*.ply")) and list((out / "meshes").glob("tile_*.glb"))
        assert (out / "poses.json").exists()
        # map.png: a PNG whose pixels hold the road's label colour
        png = (out / "map.png").read_bytes()
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        pixels = np.asarray(Image.open(out / "map.png").convert("RGB")).reshape(-1, 3)
        assert np.any(np.all(pixels == LABEL_BY_NAME["road"].color, axis=1))
        # --serve: the service keeps answering after the report, until the demo is told to stop
        time.sleep(2.0)
        assert proc.poll() is None
        assert httpx.get(f"{url}/healthz", timeout=5).status_code == 200
        assert httpx.get(f"{url}/v1/tiles", timeout=5).json()["items"]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(90) == 0
        with pytest.raises(httpx.HTTPError):
            httpx.get(f"{url}/healthz", timeout=2)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


@pytest.mark.integration
def test_demo_refuses_a_foreign_folder_and_bad_options(tmp_path: Path) -> None:
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    run = [sys.executable, "-m", "service.cli", "demo"]
    refused = subprocess.run([*run, "--out", str(foreign)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0 and (foreign / "keep.txt").exists()
    assert "not empty" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    for bad in (["--sessions", "0"], ["--preset", "huge"], ["--port", "70000"], ["--workers", "2"],
                ["--world", "moon"], ["--camera", "depth=0.3"], ["--sensor", "exact", "--camera", "range_m=30"]):
        done = subprocess.run([*run, *bad, "--out", str(tmp_path / "x")], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 2 and done.stderr.strip().splitlines()[-1].startswith("fleetmap demo: error:"), bad
        assert not (tmp_path / "x").exists()


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.timeout(900)
def test_demo_fuses_through_celery_workers_on_postgresql(tmp_path: Path) -> None:
    """``--broker``: the service as production runs it (PostgreSQL, Redis, two ``fleetmap worker``
    processes): the alignment and every tile's reconstruction run in the workers, each tile is fused once,
    and the report scores the whole map as the bench does."""
    from tests.production_support import TEST_REDIS_URL, fresh_database, pg_reachable, redis_or_skip

    redis_or_skip(TEST_REDIS_URL)
    if reason := pg_reachable():
        pytest.skip(reason)
    out = tmp_path / "demo"
    with fresh_database() as url:
        done = subprocess.run(
            [sys.executable, "-m", "service.cli", "demo", "--sessions", "1", "--preset", "tiny", "--out", str(out),
             "--broker", TEST_REDIS_URL, "--workers", "2", "--database-url", url],
            cwd=REPO, capture_output=True, text=True, timeout=840,
        )
    logs = "".join(p.read_text() for p in sorted(out.glob("*.log")))
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:] + logs[-3000:]
    lines = done.stdout.splitlines()
    states = {(int(m.group(1)), int(m.group(2))): (m.group(3), line.split()[2])
              for line in lines if (m := ROW.match(line))}
    assert states and {s for s, _ in states.values()} == {"fused"}, done.stdout[-3000:]
    assert {v for _, v in states.values()} == {"1"}  # one burst of uploads: each tile fused once
    assert any(line.startswith("whole map (40 × 40 m core") and "fusions per tile at most 1" in line
               for line in lines), done.stdout[-3000:]
    assert any(line.strip().startswith("per class F: road") for line in lines)
    ran = "".join((out / f"worker-{n}.log").read_text() for n in (1, 2))
    succeeded = re.findall(r"Task (fleetmap\.\w+)\[[^\]]+\] succeeded", ran)
    assert sorted(succeeded) == ["fleetmap.align_region"] + ["fleetmap.fuse_tile"] * len(states), ran[-3000:]
