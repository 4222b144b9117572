"""Fine registration (fusion.register): joint point-to-plane ICP of every submap before the field."""

from __future__ import annotations

import numpy as np
import torch

from fusion.register import _correspondences, fine_register
from fusion.types import Pose, Sigma, SubmapInput
from tests.fusion.test_coarse import _block
from tests.scene import rot_z, tiny_config

CFG = tiny_config(fine_register=True)


def _pair(wrong: Pose, free_a: bool = True) -> list[SubmapInput]:
    """Two sessions of one submap each over the same block (the truth: both at identity); ``b`` starts at
    ``wrong``. GPS fixes at the truth, 2 m / 2°."""
    sigma = Sigma(2.0, 2.0)
    return [SubmapInput("a", "sa", 0, _block(), Pose.identity(), Pose.identity(), sigma, free=free_a,
                        pose_gps=Pose.identity()),
            SubmapInput("b", "sb", 0, _block(extra_box=True), wrong, Pose.identity(), sigma, pose_gps=Pose.identity())]


def _run(subs: list[SubmapInput], **changes: object):  # noqa: ANN202
    start = [s.pose_init.matrix() for s in subs]
    gps = torch.tensor(np.stack([s.pose_gps.matrix() for s in subs]))
    return fine_register(subs, start, gps, CFG.with_(**changes))


def _relative(poses: list[np.ndarray]) -> tuple[float, float]:
    rel = np.linalg.inv(poses[0]) @ poses[1]
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1))))


def test_a_submap_half_a_metre_and_two_degrees_off_is_registered_onto_the_other() -> None:
    wrong = Pose(np.array([0.6, -0.5, 0.3]), rot_z(2.0))
    res = _run(_pair(wrong))
    t, deg = _relative(res.poses)
    assert t < 0.05 and deg < 0.2, (t, deg)  # started 0.84 m / 2° apart
    rounds = res.metrics["rounds"]
    assert all(r["matches"] > 0 for r in rounds)
    assert rounds[-1]["median_residual_m"] < 0.02


def test_a_fixed_submap_holds_and_the_free_one_moves_onto_it() -> None:
    wrong = Pose(np.array([-0.5, 0.4, -0.2]), rot_z(-1.5))
    subs = _pair(wrong, free_a=False)
    res = _run(subs)
    np.testing.assert_allclose(res.poses[0], subs[0].pose_init.matrix(), atol=1e-12)
    t, deg = _relative(res.poses)
    assert t < 0.05 and deg < 0.2, (t, deg)


def test_submaps_farther_apart_than_the_largest_radius_are_not_matched_and_keep_their_poses() -> None:
    wrong = Pose(np.array([0.0, 60.0, 0.0]), rot_z(0.0))  # another street: nothing within 2 m
    subs = _pair(wrong)
    subs[1].pose_gps = wrong  # its GPS agrees: nothing pulls it
    res = _run(subs)
    assert all(r["matches"] == 0 for r in res.metrics["rounds"])
    for got, s in zip(res.poses, subs, strict=True):
        np.testing.assert_allclose(got, s.pose_init.matrix(), atol=1e-6)


def test_correspondences_skip_the_own_submap_and_disagreeing_normals() -> None:
    # submap 0: a floor point and a wall point; submap 1: a floor point 0.1 m above the first, a wall
    # point right next to submap 0's floor point (but facing sideways)
    posed = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.0, 0.0, 0.1], [0.02, 0.0, 0.0]])
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, 1.0], [1.0, 0, 0]])
    owner = np.array([0, 0, 1, 1])
    src, dst = _correspondences(posed, normals, owner, radius=0.5, min_dot=0.7)
    pairs = dict(zip(src.tolist(), dst.tolist(), strict=True))
    assert pairs[0] == 2  # floor to floor, though submap 1's wall point lies nearer
    assert pairs[1] == 3 and pairs[2] == 0 and pairs[3] == 1  # never a point of its own submap


def test_the_alignment_start_runs_it_after_the_coarse_stage_and_the_switch_turns_it_off() -> None:
    from fusion.align import start_poses

    wrong = Pose(np.array([0.4, 0.3, 0.25]), rot_z(1.0))
    subs = _pair(wrong)
    cfg = CFG.with_(coarse_register=False, odom_init=False)
    on, metrics = start_poses(subs, cfg)
    t, _ = _relative([on["a"].matrix(), on["b"].matrix()])
    assert "fine" in metrics and t < 0.05
    off, metrics = start_poses(subs, cfg.with_(fine_register=False))
    assert "fine" not in metrics and np.allclose(off["b"].t, wrong.t)
