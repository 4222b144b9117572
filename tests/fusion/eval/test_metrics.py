"""Metrics on toy cases: identical meshes, shifted meshes, semantic labels, Umeyama alignment."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.eval.metrics import (
    PointSet,
    gauge_alignment,
    geometric_prf,
    pose_rmse,
    sample_surface,
    semantic_f1,
    transform_points,
    umeyama,
)
from fusion.types import FusedMesh, Pose


def _plane(labels_split: bool = True, shift: float = 0.0) -> FusedMesh:
    xs = np.linspace(0, 10, 11)
    gx, gy = np.meshgrid(xs, xs)
    v = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, shift)]).astype(np.float32)
    faces = []
    for j in range(10):
        for i in range(10):
            a = j * 11 + i
            faces += [[a, a + 1, a + 12], [a, a + 12, a + 11]]
    f = np.array(faces, np.int32)
    centre_x = v[f].mean(axis=1)[:, 0]
    fl = np.where(centre_x < 5, 1, 2).astype(np.uint8) if labels_split else np.ones(len(f), np.uint8)
    return FusedMesh(v, f, np.zeros(len(v), np.uint8), np.ones(len(v), np.float32), fl)


def test_identical_meshes_score_one() -> None:
    m = _plane()
    p, r, f = geometric_prf(m, m)
    assert f == pytest.approx(1.0)
    sem, per_class = semantic_f1(m, m)
    assert sem == pytest.approx(1.0) and set(per_class) == {1, 2}


def test_shifted_by_one_metre_scores_zero() -> None:
    p, r, f = geometric_prf(_plane(shift=1.0), _plane())
    assert f < 0.01


def test_small_shift_within_threshold_counts() -> None:
    assert geometric_prf(_plane(shift=0.1), _plane())[2] == pytest.approx(1.0, abs=0.03)


def test_wrong_labels_lower_semantic_not_geometric() -> None:
    pred, gt = _plane(labels_split=False), _plane()
    assert geometric_prf(pred, gt)[2] == pytest.approx(1.0)
    sem, per_class = semantic_f1(pred, gt)
    assert per_class[2][2] == 0.0
    assert 0.3 < sem < 0.8


def test_region_and_observed_subset() -> None:
    gt = _plane()
    half = sample_surface(gt.vertices, gt.faces, gt.face_labels, seed=5)
    half = half.subset(half.points[:, 0] < 5)
    # prediction covers only the observed half: recall against the observed part is full
    pred = half
    p, r, f = geometric_prf(pred, gt, gt_observed=half)
    assert p == pytest.approx(1.0) and r == pytest.approx(1.0)
    p, r, f = geometric_prf(pred, gt)
    assert r == pytest.approx(0.5, abs=0.05)
    p, r, f = geometric_prf(pred, gt, region=((0.0, 0.0), (5.0, 10.0)))
    assert f == pytest.approx(1.0, abs=0.02)


def test_umeyama_recovers_rigid_transform() -> None:
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3)) * 10
    r_true = Rotation.from_euler("zyx", [40, 5, -3], degrees=True).as_matrix()
    t_true = np.array([3.0, -2.0, 0.5])
    r, t, s = umeyama(src, src @ r_true.T + t_true)
    assert np.allclose(r, r_true, atol=1e-9) and np.allclose(t, t_true, atol=1e-9) and s == 1.0


def test_pose_rmse_removes_global_rigid_transform() -> None:
    rng = np.random.default_rng(2)
    truth = [Pose(rng.normal(size=3) * 20, Rotation.random(random_state=k).as_quat()[[3, 0, 1, 2]]) for k in range(10)]
    g = Pose.from_matrix(np.block([[Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([[5.0], [1.0], [0.0]])],
                                   [np.zeros((1, 3)), np.ones((1, 1))]]))
    moved = [g.compose(p) for p in truth]
    t, r = pose_rmse(moved, truth)
    assert t == pytest.approx(0.0, abs=1e-9) and r == pytest.approx(0.0, abs=1e-5)
    t_raw, _ = pose_rmse(moved, truth, align=False)
    assert t_raw > 1.0
    # a known translation error on one pose shows up
    noisy = list(truth)
    noisy[0] = Pose(truth[0].t + np.array([1.0, 0, 0]), truth[0].q)
    t, _ = pose_rmse(noisy, truth, align=False)
    assert t == pytest.approx(np.sqrt(1 / 10))


def _rigid(yaw_deg: float, t: tuple[float, float, float]) -> Pose:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    m[:3, 3] = t
    return Pose.from_matrix(m)


def test_gauge_alignment_undoes_a_global_offset_and_fixes_collinear_trajectories() -> None:
    # submaps along a straight road (collinear positions): anchors spread over each submap fix the
    # rotation about the road that positions alone leave undetermined
    truth = [_rigid(0.0, (10.0 * k, 0.0, 0.0)) for k in range(5)]
    g = _rigid(2.0, (0.6, -0.4, 0.1))
    est = [g.compose(p) for p in truth]
    anchors = [np.array([[0.0, 0, 0], [5.0, 4.0, 0.0], [5.0, -4.0, 3.0], [9.0, 0.0, 0.5]])] * 5
    r, t = gauge_alignment(est, truth, anchors)
    pts = np.random.default_rng(0).normal(size=(50, 3)) * 20
    moved = transform_points(transform_points(as_set(pts), g.rotation(), g.t), r, t)
    assert np.allclose(moved.points, pts, atol=1e-6)
    # a fused map that is internally exact but offset by the gauge scores zero absolute, one aligned
    plane = _plane()
    offset = FusedMesh(plane.vertices + np.float32([0.0, 0.0, 0.5]), plane.faces, plane.vertex_labels,
                       plane.vertex_confidence, plane.face_labels)
    region = ((1.0, 1.0), (9.0, 9.0))
    assert geometric_prf(offset, plane, region=region)[2] < 0.1
    shifted = [Pose(p.t + np.array([0.0, 0.0, 0.5]), p.q) for p in truth]
    r, t = gauge_alignment(shifted, truth, anchors)
    pred = transform_points(sample_surface(offset.vertices, offset.faces, offset.face_labels, seed=1), r, t)
    assert geometric_prf(pred, plane, region=region)[2] == pytest.approx(1.0, abs=0.01)


def as_set(pts: np.ndarray) -> PointSet:
    return PointSet(pts, np.zeros(len(pts), np.int64))
