"""Classical baseline ((G)ICP pose graph + Poisson) on a tiny synthetic scene."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from fusion.eval.baseline.poisson import OrientedSamples, label_and_clip, majority_labels
from fusion.types import Pose, SemanticMesh, SubmapInput, TileSpec

ROAD, BUILDING = 1, 5


def _scene() -> SemanticMesh:
    """A 24 m × 24 m ground (road) with four 3 m buildings of different sizes, map frame, metres."""
    g = np.linspace(-12.0, 12.0, 25)
    xx, yy = np.meshgrid(g, g, indexing="ij")
    verts = [np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1)]
    idx = np.arange(xx.size).reshape(xx.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = [np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])]
    labels = [np.full(len(faces[0]), ROAD)]
    offset = len(verts[0])
    for centre, size in (
        ((-6, -5), (3, 4, 3)),
        ((5, -6), (4, 2, 4)),
        ((-5, 6), (2, 5, 2.5)),
        ((6, 5), (3, 3, 5)),
    ):
        box = trimesh.creation.box(extents=size)
        box.apply_translation([centre[0], centre[1], size[2] / 2])
        verts.append(np.asarray(box.vertices))
        faces.append(np.asarray(box.faces) + offset)
        labels.append(np.full(len(box.faces), BUILDING))
        offset += len(box.vertices)
    return SemanticMesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64), np.concatenate(labels))


def _submaps(shift: np.ndarray) -> tuple[list[SubmapInput], dict[str, Pose]]:
    """Four submaps of the scene in their own local frames; the last one's GPS pose is shifted."""
    scene = _scene()
    subs, truth = [], {}
    for k, t in enumerate(([1.0, 2.0, 0.0], [-2.0, 1.0, 0.0], [0.5, -1.5, 0.0], [3.0, 3.0, 0.0])):
        true_pose = Pose(np.asarray(t), np.array([1.0, 0.0, 0.0, 0.0]))
        local = SemanticMesh(true_pose.inverse().apply(scene.vertices), scene.faces, scene.face_labels)
        init = Pose(true_pose.t + (shift if k == 3 else 0.0), true_pose.q)
        subs.append(SubmapInput(f"s{k}", f"session{k}", 0, local, init, Pose.identity()))
        truth[f"s{k}"] = true_pose
    return subs, truth


def test_majority_labels_breaks_ties_to_smaller_id() -> None:
    assert majority_labels(np.array([[3, 3, 1, 1, 2], [4, 4, 4, 0, 0]])).tolist() == [1, 4]


def test_label_and_clip_keeps_faces_with_centroid_in_tile() -> None:
    vertices = np.array([[1.0, 1, 0], [2, 1, 0], [1, 2, 0], [-1, 1, 0], [-2, 1, 0], [-1, 2, 0]])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    samples = OrientedSamples(vertices.copy(), np.tile([0.0, 0, 1], (6, 1)), np.array([5, 5, 5, 1, 1, 1]))
    mesh = label_and_clip(vertices, faces, samples, TileSpec(0, 0, 10.0), k=3)
    assert len(mesh.faces) == 1 and mesh.vertices.shape == (3, 3)
    assert mesh.face_labels.tolist() == [5] and np.all(mesh.vertex_confidence == 1.0)


@pytest.mark.parametrize("method", ["icp", "gicp"])
def test_baseline_recovers_shift_and_labels_mesh(method: str) -> None:
    pytest.importorskip("open3d")
    from fusion.eval.baseline.registration import BaselineConfig, run_baseline

    shift = np.array([0.5, 0.0, 0.0])
    subs, truth = _submaps(shift)
    tile = TileSpec(-1, -1, 24.0)  # x, y ∈ [-24, 0): the quarter with one building
    # the paper's 500 source points per submap (the default), registered against a dense target
    cfg = BaselineConfig(method=method, poisson_points=30_000, poisson_depth=7)
    mesh, poses, timing = run_baseline(subs, tile, config=cfg)

    def rel(p: dict[str, Pose], a: str, b: str) -> np.ndarray:
        return p[a].inverse().compose(p[b]).t

    before = np.linalg.norm(rel({s.id: s.pose_init for s in subs}, "s0", "s3") - rel(truth, "s0", "s3"))
    after = np.linalg.norm(rel(poses, "s0", "s3") - rel(truth, "s0", "s3"))
    assert before == pytest.approx(0.5)
    assert after < 0.15, f"relative error {after:.3f} m"
    assert set(poses) == {"s0", "s1", "s2", "s3"} and timing["loop_edges"] > 0
    assert timing["loop_edges_kept"] > 0 and timing["mean_fitness"] > 0.5  # loop closures shape the graph

    assert len(mesh.faces) > 100
    v = mesh.vertices
    assert v[:, 0].max() <= 0.5 and v[:, 1].max() <= 0.5  # clipped to the tile (+ one face)
    assert {ROAD, BUILDING} <= set(np.unique(mesh.face_labels).tolist())
    roof = v[:, 2] > 2.5
    assert roof.any() and np.mean(mesh.vertex_labels[roof] == BUILDING) > 0.9


def test_gps_variant_keeps_initial_poses() -> None:
    pytest.importorskip("open3d")
    from fusion.eval.baseline.registration import BaselineConfig, run_baseline

    subs, _ = _submaps(np.array([0.5, 0.0, 0.0]))
    cfg = BaselineConfig(method="gps", poisson_points=20_000, poisson_depth=6)
    mesh, poses, _ = run_baseline(subs, TileSpec(0, 0, 24.0), config=cfg)
    assert np.allclose(poses["s3"].t, subs[3].pose_init.t) and len(mesh.faces) > 0


def test_fixed_submaps_stay_put() -> None:
    pytest.importorskip("open3d")
    from fusion.eval.baseline.registration import BaselineConfig, run_baseline

    subs, _ = _submaps(np.array([0.5, 0.0, 0.0]))
    subs[0].free = False
    cfg = BaselineConfig(poisson_points=20_000, poisson_depth=6)
    _, poses, _ = run_baseline(subs, TileSpec(0, 0, 24.0), config=cfg)
    assert "s0" not in poses


def test_region_baseline_aligns_once_and_meshes_every_tile(monkeypatch: pytest.MonkeyPatch) -> None:
    """The multi-tile bench's baseline: one pose graph over the region's submaps, one Poisson mesh per
    tile clipped to that tile."""
    pytest.importorskip("open3d")
    from fusion.eval.baseline import registration

    calls: list[int] = []
    real_align = registration.align
    monkeypatch.setattr(registration, "align", lambda subs, cfg: calls.append(len(subs)) or real_align(subs, cfg))
    subs, truth = _submaps(np.array([0.5, 0.0, 0.0]))
    tiles = [TileSpec(i, j, 12.0) for i in (-1, 0) for j in (-1, 0)]
    cfg = registration.BaselineConfig(method="gicp", poisson_points=30_000, poisson_depth=7)
    meshes, poses, timing = registration.run_baseline_region(subs, tiles, config=cfg)
    assert calls == [4]  # one alignment of all four submaps, not one per tile
    assert set(meshes) == {(t.i, t.j) for t in tiles} and set(timing["tile_s"]) == {"-1_-1", "-1_0", "0_-1", "0_0"}
    for t in tiles:
        v = meshes[(t.i, t.j)].vertices
        assert len(meshes[(t.i, t.j)].faces) > 50
        centre = v.mean(axis=0)[:2]
        assert t.xy_min[0] <= centre[0] < t.xy_max[0] and t.xy_min[1] <= centre[1] < t.xy_max[1]
    rel = poses["s0"].inverse().compose(poses["s3"]).t - truth["s0"].inverse().compose(truth["s3"]).t
    assert np.linalg.norm(rel) < 0.15
