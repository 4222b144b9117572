"""Coarse session registration (fusion.coarse): a wide pose basin before the field alignment."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import trimesh

from fusion.coarse import coarse_register, label_groups
from fusion.types import Pose, SemanticMesh, Sigma, SubmapInput
from tests.scene import ground, rot_z, street, tiny_config

CFG = tiny_config()


def _relative(result, a: int = 0, b: int = 1) -> tuple[np.ndarray, float]:
    """Pose of submap b relative to a (both are the same place in truth): translation, yaw (deg)."""
    rel = np.linalg.inv(result.poses[a]) @ result.poses[b]
    return rel[:3, 3], float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0])))


def _pair(mesh_a: SemanticMesh, mesh_b: SemanticMesh, wrong: Pose, sigma: Sigma, free_a: bool = True
          ) -> list[SubmapInput]:
    return [SubmapInput("a", "sa", 0, mesh_a, Pose.identity(), Pose.identity(), sigma, free=free_a),
            SubmapInput("b", "sb", 0, mesh_b, wrong, Pose.identity(), sigma)]


def _start(subs: list[SubmapInput]) -> list[np.ndarray]:
    return [s.pose_init.matrix() for s in subs]


def _block(extra_box: bool = False) -> SemanticMesh:
    """Four copies of the test street, each turned differently: a 32 m block where yaw shows."""
    parts = []
    for k, (dx, dy) in enumerate([(0.0, 0.0), (16.0, 0.0), (0.0, 16.0), (16.0, 16.0)]):
        m = street(extra_box=extra_box and k == 3)
        c = np.array([8.0, 8.0, 0.0])
        rot = Pose(np.zeros(3), rot_z(90.0 * k)).matrix()[:3, :3]
        parts.append(SemanticMesh((m.vertices - c) @ rot.T + c + [dx, dy, 0.0], m.faces, m.face_labels))
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return SemanticMesh(np.concatenate([p.vertices for p in parts]),
                        np.concatenate([p.faces + o for p, o in zip(parts, offsets, strict=True)]),
                        np.concatenate([p.face_labels for p in parts]))


def test_a_session_metres_and_degrees_off_is_moved_onto_the_other() -> None:
    # 3.6 m / 3°: beyond the field's coarsest level, inside 3 GPS σ of 2 m / 2°
    wrong = Pose(np.array([3.0, -2.0, 0.4]), rot_z(3.0))
    subs = _pair(_block(), _block(extra_box=True), wrong, Sigma(2.0, 2.0))
    res = coarse_register(subs, _start(subs), CFG)
    t, yaw = _relative(res)
    # inside the field alignment's basin (its coarsest level: ~2 m cells); it does the rest
    assert np.linalg.norm(t) < 0.5 and abs(yaw) < 1.0, (t, yaw)
    assert any(m.get("kept") or m.get("first_kept") for m in res.metrics.values())
    assert min(m["shift_m"] for m in res.metrics.values()) > 1.0  # gauge: each session took about half


def test_a_session_of_n_submaps_is_searched_over_its_chains_placement_error() -> None:
    # one GPS fix of σ 2 m: ±3 σ = 6 m; a chain on four independent fixes sits ~σ/2 off: ±3 m
    def session(sid: str, n: int, wrong: Pose) -> list[SubmapInput]:
        return [SubmapInput(f"{sid}{k}", sid, k, _block(), wrong, Pose.identity(), Sigma(2.0, 2.0))
                for k in range(n)]

    wrong = Pose(np.array([-2.5, 2.0, 0.0]), rot_z(0.0))
    ranges = {}
    for n in (1, 4):
        subs = [replace(s, free=False) for s in session("a", 1, Pose.identity())] + session("b", n, wrong)
        res = coarse_register(subs, _start(subs), CFG)
        ranges[n] = res.metrics["b"]["first_range_m"]  # the wide stage (then a ±2 m fine one)
        t, yaw = _relative(res, 0, 1)
        assert np.linalg.norm(t) < 0.5 and abs(yaw) < 1.0, (n, t, yaw)  # found either way
    assert ranges == {1: 6.0, 4: 3.0}


def test_the_mean_correction_is_taken_out_when_nothing_is_fixed() -> None:
    wrong = Pose(np.array([2.0, 1.5, 0.0]), rot_z(0.0))
    subs = _pair(street(), street(), wrong, Sigma(2.0, 2.0))
    res = coarse_register(subs, _start(subs), CFG)
    ta, tb = res.poses[0][:3, 3], res.poses[1][:3, 3] - wrong.t
    np.testing.assert_allclose(ta + tb, 0.0, atol=0.05)  # equal and opposite: the GPS mean stays
    assert np.linalg.norm(ta) > 1.0


def test_fixed_submaps_stay_and_the_new_session_moves_onto_them() -> None:
    wrong = Pose(np.array([-2.5, 2.0, 0.0]), rot_z(-2.0))
    subs = _pair(_block(), _block(extra_box=True), wrong, Sigma(2.0, 2.0), free_a=False)
    res = coarse_register(subs, _start(subs), CFG)
    np.testing.assert_array_equal(res.poses[0], subs[0].pose_init.matrix())
    t, yaw = _relative(res)
    assert np.linalg.norm(t) < 0.5 and abs(yaw) < 1.0, (t, yaw)
    assert set(res.metrics) == {"sb"}


def _corridor(length: float, x0: float = 0.0) -> SemanticMesh:
    """A road along x from ``x0`` with a wall along it: nothing in it fixes a shift along x."""
    road = ground(length, 1.0)
    road.apply_scale([1.0, 10.0 / length, 1.0])  # length × 10 m
    road.apply_translation((x0, 0.0, 0.0))
    wall = trimesh.creation.box(extents=(length, 0.4, 3.0)).subdivide().subdivide().subdivide()
    wall.apply_translation((x0 + length / 2, 11.0, 1.5))
    verts = np.concatenate([road.vertices, wall.vertices])
    faces = np.concatenate([road.faces, wall.faces + len(road.vertices)])
    labels = np.concatenate([np.full(len(road.faces), 1), np.full(len(wall.faces), 5)])
    return SemanticMesh(verts, faces.astype(np.int64), labels)


def test_along_a_featureless_corridor_the_start_keeps_what_the_data_leave_open() -> None:
    wrong = Pose(np.array([2.0, 1.5, 0.0]), rot_z(0.0))
    # the fixed session's corridor runs 20 m past both ends of the new one's: no end to match either
    subs = _pair(_corridor(80.0), _corridor(40.0, x0=20.0), wrong, Sigma(2.0, 2.0), free_a=False)
    res = coarse_register(subs, _start(subs), CFG)
    t, _ = _relative(res)
    assert abs(t[1]) < 0.3, t  # across the corridor: the wall decides
    assert abs(t[0] - 2.0) < 0.5, t  # along it: nothing does, the start stays


def test_sessions_that_share_no_surface_keep_their_poses() -> None:
    far = Pose(np.array([300.0, 0.0, 0.0]), rot_z(0.0))
    subs = _pair(street(), street(), far, Sigma(2.0, 2.0))
    res = coarse_register(subs, _start(subs), CFG)
    for got, sub in zip(res.poses, subs, strict=True):
        np.testing.assert_allclose(got, sub.pose_init.matrix(), atol=1e-9)


def test_one_session_is_left_alone_and_the_switch_turns_it_off() -> None:
    wrong = Pose(np.array([2.0, 1.5, 0.0]), rot_z(0.0))
    subs = _pair(street(), street(), wrong, Sigma(2.0, 2.0))
    one = [subs[0], replace(subs[1], session_id="sa", seq=1)]
    assert coarse_register(one, _start(one), CFG).metrics == {}

    from fusion.align import start_poses

    off, metrics = start_poses(subs, CFG.with_(coarse_register=False, odom_init=False, fine_register=False))
    assert metrics == {} and np.allclose(off["b"].t, wrong.t)
    on, metrics = start_poses(subs, CFG.with_(odom_init=False, fine_register=False))
    assert set(metrics) == {"sa", "sb"} and not np.allclose(on["b"].t, wrong.t)


def test_label_groups_match_confusable_classes_and_skip_unlabeled() -> None:
    g = label_groups(np.array([0, 1, 3, 2, 4, 9, 5, 6, 7, 8, 10, 11, 12, 40]))
    assert g[0] == -1
    assert g[1] == g[2]  # road, lane marking
    assert g[4] == g[5]  # terrain, vegetation
    assert g[6] == g[7] and g[8] == g[9] and g[10] == g[11]
    assert len({g[1], g[3], g[4], g[6], g[8], g[10]}) == 6
    assert g[12] == g[13] and g[12] not in {g[1], g[3], g[4], g[6], g[8], g[10]}  # appended labels: one group
