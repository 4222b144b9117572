"""The one-tile bench reads the poses from the alignment (the reconstruction holds every pose)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from fusion.eval import bench
from fusion.types import FusedMesh, FusionResult, Pose


def test_fused_row_takes_the_aligned_poses(monkeypatch: pytest.MonkeyPatch) -> None:
    aligned = Pose(np.array([1.0, 2.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))

    def fake_fuse_tiles(submaps: Any, keys: Any, config: Any, tile_size: float, refined: dict, **_: Any) -> dict:
        refined["s1"] = aligned  # what the region alignment writes
        return {bench.TILE: FusionResult(FusedMesh.empty(), {}, {"points_per_s": 1.0}, {})}

    monkeypatch.setattr(bench, "fuse_tiles", fake_fuse_tiles)
    ctx = SimpleNamespace(submaps=[], config=None, tile_size=64.0)
    figures, result, poses = bench._fuse(ctx)  # type: ignore[arg-type]
    assert poses == {"s1": aligned} and result.poses == {}
    assert figures["points_per_s"] == 1.0
