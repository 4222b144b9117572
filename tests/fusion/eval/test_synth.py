"""Synthetic fleet: labels, upload files the service would accept, truth apart, noise statistics."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fusion.eval.synth.fleet import FleetParams, perturb
from fusion.eval.synth.simulate import load_ground_truth, simulate
from fusion.eval.synth.world import World, WorldParams
from fusion.labels import NUM_CLASSES
from fusion.meshio import read_submap_ply
from fusion.types import Pose

TINY_WORLD = {"core_max": (32.0, 32.0), "margin": 14.0, "ground_res": 0.5}
TINY_FLEET = {"submap_length": 15.0, "sensor_range": 14.0, "submap_res": 0.6}


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("sim")
    records = simulate(out, seed=3, sessions=3, world_params=WorldParams(**TINY_WORLD),
                       fleet_params=FleetParams(**TINY_FLEET))
    return out, records


def test_world_uses_every_label_and_varies_with_seed() -> None:
    worlds = [World(WorldParams(seed=s, **TINY_WORLD)) for s in (0, 1)]
    for w in worlds:
        v, f, ground = w.gt_ground()
        labels = set(np.unique(ground)) | {int(x) for p in w.parts for x in np.unique(p.labels)}
        assert labels == set(range(1, NUM_CLASSES))
    # roads differ (curves, junction angle) between seeds
    a, b = worlds[0].roads[0], worlds[1].roads[0]
    assert not np.allclose(a[: min(len(a), len(b))], b[: min(len(a), len(b))])


def test_uploads_are_valid_and_ground_truth_apart(sim) -> None:
    out, records = sim
    plys = sorted(out.glob("*.ply"))
    assert len(plys) == len(records) >= 4
    sessions = set()
    for ply in plys:
        mesh = read_submap_ply(ply.read_bytes())
        meta = json.loads(ply.with_suffix(".json").read_text())
        assert set(meta) == {"agent_id", "session_id", "seq", "captured_at", "gps", "gps_sigma", "odometry",
                             "odometry_sigma"}
        Pose.from_json(meta["gps"]["pose"])
        Pose.from_json(meta["odometry"])
        assert "pose_true" not in json.dumps(meta)
        assert len(mesh.faces) > 1000
        # local frame: near its own origin, not the map frame
        assert np.abs(mesh.vertices).max() < 80.0
        sessions.add(meta["session_id"])
    assert len(sessions) == 3
    gt = load_ground_truth(out)
    assert set(gt.poses) == {p.stem for p in plys}
    assert 0.1 < gt.observed.mean() < 1.0
    assert set(np.unique(gt.labels)) | set(np.unique(gt.transient_labels)) == set(range(1, NUM_CLASSES))
    # transient objects exist, each seen by exactly one session
    assert len(gt.transient_faces) > 0 and gt.transient_observed.any()
    # each submap's session index, the tag its session's transients carry
    assert set(gt.sessions) == set(gt.poses) and set(gt.sessions.values()) == {0, 1, 2}
    assert set(np.unique(gt.transient_session)) <= {0, 1, 2}


def test_submap_mesh_matches_truth_when_posed(sim) -> None:
    """Posed by its true pose, a submap lies on the ground-truth surface (up to vertex noise)."""
    from scipy.spatial import cKDTree

    from fusion.eval.metrics import sample_surface

    out, records = sim
    gt = load_ground_truth(out)
    tree = cKDTree(sample_surface(gt.vertices, gt.faces, density=50).points)
    r = records[1]
    pts = r.pose_true.apply(r.mesh.vertices)
    d, _ = tree.query(pts[::20])
    assert np.median(d) < 0.15
    d_gps, _ = tree.query(r.pose_gps.apply(r.mesh.vertices)[::20])
    assert np.median(d_gps) > np.median(d)


def test_label_noise_rate(sim) -> None:
    _, records = sim
    r = records[0]
    # a flipped face on the ground carries an object/other label where the truth is ground
    labels = r.mesh.face_labels
    assert labels.min() >= 1 and labels.max() < NUM_CLASSES
    share_road = np.mean(labels == 1)
    assert 0.05 < share_road < 0.8


def test_gps_noise_statistics() -> None:
    rng = np.random.default_rng(0)
    truth = Pose(np.array([10.0, -5.0, 2.0]), np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)]))
    noisy = [perturb(truth, 1.5, 1.5, 0.3, rng) for _ in range(2000)]
    dt = np.array([p.t - truth.t for p in noisy])
    assert np.allclose(dt.std(axis=0)[:2], 1.5, rtol=0.1)
    assert dt.std(axis=0)[2] < 0.7
    assert np.allclose(dt.mean(axis=0), 0.0, atol=0.15)
    yaw = np.degrees([2 * np.arctan2(p.q[3], p.q[0]) for p in noisy]) - np.degrees(0.6)
    assert abs(np.std(yaw) - 1.5) < 0.2


def test_odometry_drift_is_small_and_accumulates(sim) -> None:
    _, records = sim
    by_session: dict[str, list] = {}
    for r in records:
        by_session.setdefault(r.session_id, []).append(r)
    for recs in by_session.values():
        recs.sort(key=lambda r: r.seq)
        first = recs[0]
        assert np.allclose(first.odometry.t, 0.0)
        for r in recs[1:]:
            true_rel = first.pose_true.inverse().compose(r.pose_true)
            err = np.linalg.norm(true_rel.t - r.odometry.t)
            dist = np.linalg.norm(true_rel.t)
            assert err < 0.05 * dist + 0.05  # a few per cent of the distance at most
