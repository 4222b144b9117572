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


def test_concatenated_poses_submaps_and_crops_to_the_region() -> None:
    from fusion.eval.bench_context import concatenated
    from fusion.offline import LoadedSubmap
    from fusion.types import SemanticMesh, SubmapInput

    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [20.0, 0.0, 0.0], [21.0, 0.0, 0.0],
                  [20.0, 1.0, 0.0]])
    mesh = SemanticMesh(v, np.array([[0, 1, 2], [3, 4, 5]]), np.array([1, 5]))
    subs = [LoadedSubmap(SubmapInput(name, "s", 0, mesh, Pose.identity(), Pose.identity()), Pose.identity(), [(0, 0)],
                         (0, 0))
            for name in ("a", "b")]
    poses = {"a": Pose.identity(), "b": Pose(np.array([5.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0, 0.0]))}
    out = concatenated(subs, poses, ((0.0, -5.0), (10.0, 5.0)))  # keeps each submap's first face only
    assert out.face_labels.tolist() == [1, 1]
    posed = out.vertices[out.faces].reshape(-1, 3)
    assert np.allclose(posed[:3], v[:3]) and np.allclose(posed[3:], v[:3] + [5.0, 0.0, 1.0])
    assert len(concatenated(subs, poses, None).faces) == 4


def test_concat_rows_score_the_uploads_without_fusion(tmp_path) -> None:
    """At the true poses the exact sensor's uploads nearly coincide with the truth; at GPS poses far less."""
    from fusion.config import FusionConfig
    from fusion.eval.synth.fleet import FleetParams
    from fusion.eval.synth.simulate import simulate
    from fusion.eval.synth.world import WorldParams

    simulate(tmp_path, seed=3, sessions=2, world_params=WorldParams(core_max=(32.0, 32.0), margin=14.0, ground_res=0.5),
             fleet_params=FleetParams(submap_length=15.0, sensor_range=14.0, submap_res=0.6), sensor="exact")
    ctx = bench.prepare(tmp_path, FusionConfig.preset("tiny"), tile_size=32.0)
    true, gps = bench.ROWS["concat"](ctx), bench.ROWS["concat_gps"](ctx)
    assert true["geo_f"] > 0.9 and true["gauge_m"] == 0.0
    assert gps["geo_f"] < true["geo_f"] - 0.2 and gps["sem_f"] < true["sem_f"]
