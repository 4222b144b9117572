"""The one gauge-aligned scoring (``fusion.eval.scoring``) on toy meshes: it agrees with the metrics used
directly, and the gauge fit undoes a global rigid offset of the poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusion.eval import metrics, scoring
from fusion.types import FusedMesh, Pose


def _plane(shift: float = 0.0) -> FusedMesh:
    xs = np.linspace(0, 10, 11)
    gx, gy = np.meshgrid(xs, xs)
    v = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, shift)]).astype(np.float32)
    faces = np.array([[j * 11 + i, j * 11 + i + 1, j * 11 + i + 12] for j in range(10) for i in range(10)]
                     + [[j * 11 + i, j * 11 + i + 12, j * 11 + i + 11] for j in range(10) for i in range(10)], np.int32)
    labels = np.where(v[faces].mean(axis=1)[:, 0] < 5, 1, 2).astype(np.uint8)
    vl = np.ones(len(v), np.uint8)
    return FusedMesh(v, faces, vl, np.ones(len(v), np.float32), labels)


def _truth(mesh: FusedMesh, region: metrics.Region) -> scoring.TruthPoints:
    gt = metrics.crop(metrics.sample_surface(mesh.vertices, mesh.faces, mesh.face_labels, seed=2), region)
    empty = metrics.PointSet(np.zeros((0, 3)), np.zeros(0, np.int64))
    return scoring.TruthPoints(region, gt, gt, empty)


def test_score_mesh_without_gauge_matches_the_metrics() -> None:
    region = ((0.0, 0.0), (6.0, 6.0))
    truth, pred = _truth(_plane(), region), _plane(shift=0.05)
    figs = scoring.score_mesh(truth, pred)
    pts = metrics.sample_surface(pred.vertices, pred.faces, pred.face_labels, seed=1)
    p, r, f = metrics.geometric_prf(pts, truth.gt_all, metrics.DEFAULT_D, region, truth.gt_observed)
    sem, _ = metrics.semantic_f1(pts, truth.gt_all, metrics.DEFAULT_D, region, truth.gt_observed)
    assert (figs["geo_p"], figs["geo_r"], figs["geo_f"], figs["sem_f"]) == (p, r, f, sem)
    assert figs["transient_survival"] is None and figs["faces"] == len(pred.faces)
    assert scoring.score_mesh(truth, pred, scoring.IDENTITY) == figs


def _pose(r: np.ndarray, t: np.ndarray) -> Pose:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return Pose.from_matrix(m)


def test_gauge_fit_undoes_a_global_rigid_offset() -> None:
    rng = np.random.default_rng(0)
    true = [_pose(Rotation.from_euler("z", rng.uniform(-3, 3)).as_matrix(), np.array([10.0 * k, 0.0, 0.0]))
            for k in range(4)]
    g_r, g_t = Rotation.from_euler("z", 2.0, degrees=True).as_matrix(), np.array([0.3, -0.2, 0.1])
    est = [_pose(g_r.T @ p.rotation(), g_r.T @ (p.t - g_t)) for p in true]  # truth = g ∘ est
    verts = [rng.uniform(-5, 5, (200, 3)) for _ in true]
    r, t = scoring.gauge_fit(est, true, verts)
    np.testing.assert_allclose(r, g_r, atol=1e-9)
    np.testing.assert_allclose(t, g_t, atol=1e-9)
    size = scoring.gauge_size((r, t), ((0.0, 0.0), (0.0, 0.0)))
    assert size["gauge_m"] == pytest.approx(float(np.linalg.norm(g_t)))
    assert size["gauge_deg"] == pytest.approx(2.0)


def test_anchors_spread_over_the_vertices() -> None:
    v = np.arange(300, dtype=np.float64).reshape(100, 3)
    a = scoring.anchors(v)
    assert len(a) == 64 and (a[0] == v[0]).all() and (a[-1] == v[-1]).all()
    assert len(scoring.anchors(v[:10])) == 10


def test_aligned_and_absolute_without_gauge_are_the_same_figures() -> None:
    region = ((0.0, 0.0), (6.0, 6.0))
    figs = scoring.score_aligned_and_absolute(_truth(_plane(), region), _plane(shift=0.05), None)
    assert figs["abs_geo_f"] == figs["geo_f"] and figs["gauge_m"] == 0.0 and figs["gauge_deg"] == 0.0
    assert set(scoring.ABS_KEYS) <= {k.removeprefix("abs_") for k in figs if k.startswith("abs_")}


def test_contested_transients_are_those_another_session_saw_through() -> None:
    """A car of session 0 stands where session 1 later saw bare road (contested); another stands where only
    session 0 looked (its own road below does not count). Scored: a mesh keeping the first car survives
    only on the contested share."""
    from types import SimpleNamespace

    def box(x: float) -> tuple[np.ndarray, np.ndarray]:  # a 2 m car-sized slab, 0.5-1.5 m above the road
        v = np.array([[x, 0, 0.5], [x + 2, 0, 0.5], [x + 2, 2, 0.5], [x, 2, 0.5],
                      [x, 0, 1.5], [x + 2, 0, 1.5], [x + 2, 2, 1.5], [x, 2, 1.5]], float)
        f = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])
        return v, f

    (va, fa), (vb, fb) = box(0.0), box(30.0)
    road = np.array([[x, y, 0.0] for x in np.arange(-2, 5, 0.25) for y in np.arange(-2, 5, 0.25)])
    own_road = road + [30.0, 0.0, 0.0]
    truth = SimpleNamespace(
        transient_vertices=np.concatenate([va, vb]), transient_faces=np.concatenate([fa, fb + 8]),
        transient_session=np.zeros(8, np.int64),
        poses={"a0": Pose.identity(), "b0": Pose.identity(), "b1": Pose.identity()},
        sessions={"a0": 0, "b0": 0, "b1": 1})
    pts = metrics.sample_surface(truth.transient_vertices, truth.transient_faces, density=20, seed=0).points
    mask = scoring.contested_transients(truth, pts, {"a0": own_road, "b0": own_road, "b1": road})
    np.testing.assert_array_equal(mask, pts[:, 0] < 15)  # the first car only, all of it
    assert mask.any() and not mask.all()
    assert not scoring.contested_transients(truth, pts, {"a0": own_road, "b0": road}).any()  # its own session only

    region = ((-5.0, -5.0), (40.0, 5.0))
    tr = metrics.PointSet(pts, np.ones(len(pts), np.int64))
    first = FusedMesh(va.astype(np.float32), fa.astype(np.int32), np.ones(8, np.uint8), np.ones(8, np.float32),
                      np.ones(len(fa), np.uint8))
    figs = scoring.score_mesh(scoring.TruthPoints(region, tr, tr, tr, tr.subset(mask)), first)
    assert figs["contested_survival"] == pytest.approx(1.0)
    assert figs["transient_survival"] == pytest.approx(mask.mean(), abs=0.05)
    assert scoring.score_mesh(scoring.TruthPoints(region, tr, tr, tr), first)["contested_survival"] is None


def test_pose_figures_split_the_error_by_session_and_measure_the_surface_offset() -> None:
    """Session b (2 submaps) shifted 0.4 m along x against session a (6): b's RMSE is the larger; exact poses score 0."""
    from types import SimpleNamespace

    rng = np.random.default_rng(1)
    subs, true, est = [], {}, {}
    for k in range(8):
        sid = "a" if k < 6 else "b"
        name = f"{sid}{k}"
        mesh = SimpleNamespace(vertices=rng.uniform(-10, 10, (100, 3)))
        subs.append(SimpleNamespace(input=SimpleNamespace(id=name, session_id=sid, mesh=mesh)))
        true[name] = _pose(Rotation.from_euler("z", 0.3 * k).as_matrix(), np.array([20.0 * (k % 4), 15.0 * (k // 4), 0]))
        est[name] = Pose(true[name].t + (np.array([0.4, 0, 0]) if sid == "b" else 0.0), true[name].q)
    exact = scoring.pose_figures(subs, true, true)
    assert exact["pose_trans_m"] == pytest.approx(0, abs=1e-9) and exact["pose_surface_m"] == pytest.approx(0, abs=1e-9)
    figs = scoring.pose_figures(subs, est, true)
    assert figs["poses"] == 8 and set(figs["pose_session_m"]) == {"a", "b"}
    assert figs["pose_session_m"]["b"] > figs["pose_session_m"]["a"]
    assert 0.1 < figs["pose_surface_m"] < 0.4


def test_the_relative_offset_ignores_a_warp_all_sessions_share_and_sees_one_session_off() -> None:
    """Two sessions driving the same 200 m road: bent together (the map's common warp, up to 0.5 m at the
    ends) they still meet exactly (relative 0, pose RMSE not); session b shifted 0.3 m across the road, the
    relative offset is the shift."""
    from types import SimpleNamespace

    rng = np.random.default_rng(2)
    subs, true = [], {}
    for sid in ("a", "b"):
        for k in range(8):
            name = f"{sid}{k}"
            mesh = SimpleNamespace(vertices=rng.uniform(-5, 5, (50, 3)))
            subs.append(SimpleNamespace(input=SimpleNamespace(id=name, session_id=sid, mesh=mesh)))
            true[name] = _pose(np.eye(3), np.array([25.0 * k + (1.0 if sid == "b" else 0.0), 0.0, 0.0]))

    def bent(name: str, extra: float = 0.0) -> Pose:
        x = true[name].t[0]
        return Pose(true[name].t + np.array([0.0, 0.5 * ((x - 90) / 90) ** 2 + extra, 0.0]), true[name].q)

    warped = {n: bent(n) for n in true}
    figs = scoring.pose_figures(subs, warped, true)
    assert figs["pose_trans_m"] > 0.1
    assert figs["pose_relative_m"] == pytest.approx(0.0, abs=0.015)  # the warp differs over 1 m by ≤ 0.011 m
    shifted = {n: bent(n, 0.3 if n.startswith("b") else 0.0) for n in true}
    assert scoring.pose_figures(subs, shifted, true)["pose_relative_m"] == pytest.approx(0.3, abs=0.02)
    alone = [s for s in subs if s.input.session_id == "a"]
    assert scoring.pose_figures(alone, warped, true)["pose_relative_m"] is None  # no second session to meet
