"""Helpers for the scheduler and worker tests: settings, an in-process app, uploads, a fake fusion.

Meshes are tiny (tests/scene.py's 16 m street); poses are map-frame ``{"t", "q"}``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from fastapi.testclient import TestClient

from fusion.meshio import write_submap_ply
from fusion.types import FusedMesh, FusionResult, Pose, SubmapInput, TileSpec
from service.api.app import create_app
from service.settings import Settings
from tests.production_support import submap_meta
from tests.scene import street


def make_settings(tmp_path: Path, **overrides: Any) -> Settings:
    """Embedded settings under ``tmp_path``: auth off, tiny fusion, the scheduler driven by the test."""
    values: dict[str, Any] = {
        "data_dir": tmp_path / "data",
        "auth": "off",
        "fuse_debounce_s": 30.0,
        "fuse_max_wait_s": 600.0,
        "fusion_preset": "tiny",
        "scheduler_interval_s": 3600.0,
        "lease_s": 60.0,
    }
    values.update(overrides)
    return Settings(**values)


@contextmanager
def api(settings: Settings, background: bool = False) -> Iterator[TestClient]:
    """The real app (migrated SQLite), through httpx; the scheduler/worker only when ``background``."""
    app = create_app(settings, migrate=True, background=background)
    with TestClient(app) as client:
        yield client


def session_factory(app: Any) -> Any:
    """The app's sessionmaker (``app.state.session_factory``)."""
    return app.state.session_factory


@contextmanager
def in_process(tmp_path: Path) -> Iterator[Any]:
    """The app with its settings and sessionmaker attached (``.settings``, ``.db``), no background work:
    tests tick the scheduler and run jobs themselves."""
    settings = make_settings(tmp_path)
    with api(settings) as client:
        client.settings = settings  # type: ignore[attr-defined]
        client.db = session_factory(client.app)  # type: ignore[attr-defined]
        yield client


_MESH: bytes | None = None


def mesh_bytes() -> bytes:
    global _MESH
    if _MESH is None:
        _MESH = write_submap_ply(street(16.0))
    return _MESH


def upload(
    client: Any, session: str, seq: int, t: list[float], *, agent: str = "veh-1", mesh: bytes | None = None
) -> dict[str, Any]:
    """POST one submap of ``session`` at map-frame translation ``t`` (identity rotation); returns the body."""
    meta = submap_meta(session, seq, t, agent, gps_sigma=2.0)
    files = {
        "meta": (None, json.dumps(meta), "application/json"),
        "mesh": ("submap.ply", mesh or mesh_bytes(), "application/octet-stream"),
    }
    response = client.post("/v1/submaps", files=files)
    assert response.status_code in (200, 201), response.text
    return response.json()


def fake_mesh(tile: TileSpec) -> FusedMesh:
    """Two labelled triangles in the tile (map frame)."""
    x0, y0 = tile.xy_min
    vertices = np.array([[x0 + 1, y0 + 1, 0], [x0 + 5, y0 + 1, 0], [x0 + 1, y0 + 5, 0], [x0 + 5, y0 + 5, 0]])
    return FusedMesh(
        vertices.astype(np.float32),
        np.array([[0, 1, 2], [1, 3, 2]], np.int32),
        np.ones(4, np.uint8),
        np.full(4, 0.9, np.float32),
        np.ones(2, np.uint8),
    )


class _FakeStage:
    """A stand-in for one fusion stage: records its calls, runs ``during`` inside (e.g. an upload that
    arrives meanwhile), raises ``error``; free poses move by ``shift`` metres along x."""

    def __init__(self, shift: float = 0.0, error: BaseException | None = None) -> None:
        self.shift = shift
        self.error = error
        self.calls: list[tuple[Any, list[SubmapInput]]] = []
        self.during: Callable[[], None] | None = None

    def _moved(self, where: Any, submaps: list[SubmapInput]) -> dict[str, Pose]:
        self.calls.append((where, submaps))
        if self.during is not None:
            self.during()
        if self.error is not None:
            raise self.error
        shift = np.array([self.shift, 0.0, 0.0])
        return {s.id: Pose(np.asarray(s.pose_init.t) + shift, s.pose_init.q) for s in submaps if s.free}


class FakeFusion(_FakeStage):
    """Stands in for the tile reconstruction (``worker.runner._fuse``): a two-triangle mesh, and a
    one-tensor field state whose value counts this fake's calls. ``warms``: each tile's last warm start."""

    def __init__(self, shift: float = 0.0, error: BaseException | None = None) -> None:
        super().__init__(shift, error)
        self.warms: dict[tuple[int, int], tuple[bytes | None, str]] = {}

    def __call__(self, inputs: Any, keeper: Any) -> FusionResult:
        import torch

        self.warm, self.warm_kind = inputs.warm, inputs.warm_kind
        self.warms[(inputs.tile.i, inputs.tile.j)] = (inputs.warm, inputs.warm_kind)
        poses = self._moved(inputs.tile, inputs.submaps)
        state = {"w": torch.full((1,), float(len(self.calls)))}
        return FusionResult(fake_mesh(inputs.tile), poses, {"losses": {"total": 0.1}}, inputs.config.to_dict(),
                            field_state=state)


class FakeAlign(_FakeStage):
    """Stands in for the region alignment (``worker.runner._align``); every free submap gets ``drift`` (a
    ``fusion.drift.Drift``), if given."""

    def __init__(self, shift: float = 0.0, error: BaseException | None = None, drift: Any = None) -> None:
        super().__init__(shift, error)
        self.drift = drift

    def __call__(self, inputs: Any, keeper: Any, frozen: dict[Any, bytes]) -> tuple[dict[str, Pose], dict[str, Any],
                                                                                   dict, dict]:
        self.frozen, self.config = frozen, inputs.config
        registration_only = inputs.config.align_iterations_per_tile == 0 and not frozen  # as align_region
        trained = {(t.i, t.j): f"field of {t.i},{t.j}".encode() for t in inputs.tiles
                   if (t.i, t.j) not in frozen and not registration_only}
        poses = self._moved(inputs.tiles, inputs.submaps)
        drifts = {sid: self.drift for sid in poses} if self.drift is not None else {}
        return poses, {"losses": {"total": 0.1}}, trained, drifts


def never_realign(monkeypatch: Any) -> None:
    """Sessions added to a map are always aligned against it (``realign_share`` > 1): for tests of the
    incremental path with fewer sessions than a joint re-alignment waits for."""
    from fusion.config import FusionConfig
    from service import schedule

    monkeypatch.setattr(schedule, "fusion_config",
                        lambda settings: FusionConfig.preset(settings.fusion_preset).with_(realign_share=2.0))


def wait_for(predicate: Callable[[], Any], timeout_s: float, what: str, interval_s: float = 0.2) -> Any:
    """Poll ``predicate`` until truthy (returns its value) or fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}; last value {last!r}")


def tile_fused(client: Any, i: int, j: int, version: int) -> Callable[[], dict[str, Any] | None]:
    """A ``wait_for`` predicate: tile (i, j) is ``fused`` at ``version`` or later (its region's alignment
    and then its reconstruction ran); a ``failed`` tile fails the wait."""

    def fused() -> dict[str, Any] | None:
        body: dict[str, Any] = client.get(f"/v1/tiles/{i}/{j}").json()
        assert body["state"] != "failed", body
        return body if body["state"] == "fused" and body["version"] >= version else None

    return fused
