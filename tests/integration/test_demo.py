"""``fleetmap demo`` (the README's run command) end to end with the tiny fusion preset."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.integration
@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "demo",
            "--sessions",
            "1",
            "--preset",
            "tiny",
            "--out",
            str(out),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=900,
    )
    log = (out / "serve.log").read_text() if (out / "serve.log").exists() else ""
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:] + log[-3000:]
    assert "geo F" in done.stdout and "refined" in done.stdout
    assert list((out / "meshes").glob("tile_*.ply")) and list((out / "meshes").glob("tile_*.glb"))
    assert (out / "poses.json").exists()
    # A second run into the same folder replaces the previous demo; a foreign folder is refused.
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    refused = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--out", str(foreign)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert refused.returncode != 0 and (foreign / "keep.txt").exists()
