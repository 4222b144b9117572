"""Holding the map's placement across a joint re-alignment, and the tiles it changed (``fusion.placement``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.drift import Drift
from fusion.placement import hold_placement, settle_realignment, tile_motion
from fusion.types import Pose, SemanticMesh, SubmapInput


def _submap(sid: str, size: float = 10.0, seed: int = 0) -> SubmapInput:
    """A bumpy square patch ``size`` m wide (local frame, origin at a corner), so rotation is observable."""
    rng = np.random.default_rng(seed)
    n = 6
    xs, ys = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), rng.uniform(0, 1.5, n * n)], axis=1)
    quads = [(a * n + b, (a + 1) * n + b, a * n + b + 1) for a in range(n - 1) for b in range(n - 1)]
    faces = np.array(quads, np.int64)
    mesh = SemanticMesh(vertices, faces, np.ones(len(faces), np.int64))
    return SubmapInput(id=sid, session_id=sid, seq=0, mesh=mesh, pose_init=Pose.identity(), odometry=Pose.identity())


def _at(x: float, y: float, yaw_deg: float = 0.0) -> Pose:
    half = math.radians(yaw_deg) / 2
    return Pose(np.array([x, y, 0.0]), np.array([math.cos(half), 0.0, 0.0, math.sin(half)]))


SHIFT = Pose(np.array([0.3, -0.2, 0.05]), np.array([math.cos(0.002), 0.0, 0.0, math.sin(0.002)]))  # 0.23° of yaw


def _close(a: Pose, b: Pose, tol: float = 1e-9) -> bool:
    return bool(np.allclose(a.matrix(), b.matrix(), atol=tol))


def test_hold_placement_takes_back_a_motion_of_the_whole_map_and_keeps_the_relative_poses() -> None:
    subs = [_submap("a", seed=1), _submap("b", seed=2), _submap("new", seed=3)]
    before = {"a": _at(5, 5, 10), "b": _at(30, 8, -20)}
    after = {k: SHIFT.compose(p) for k, p in before.items()} | {"new": SHIFT.compose(_at(50, 5, 3))}
    held = hold_placement(subs, before, after)
    assert _close(held["a"], before["a"], 1e-6) and _close(held["b"], before["b"], 1e-6)
    assert _close(held["new"], _at(50, 5, 3), 1e-6)  # the new submap moves with the map
    for x, y in [("a", "b"), ("a", "new")]:  # relative poses are exactly the alignment's
        assert _close(held[x].inverse().compose(held[y]), after[x].inverse().compose(after[y]), 1e-9)


def test_hold_placement_leaves_the_reshaping_in_the_map() -> None:
    """Only the least-squares rigid part goes: a submap the re-alignment moved against the others still
    moved relative to them, and the rest barely moves."""
    subs = [_submap(k, seed=i) for i, k in enumerate("abcd")]
    before = {k: _at(12 * i, 0) for i, k in enumerate("abcd")}
    after = {k: SHIFT.compose(p) for k, p in before.items()}
    after["d"] = SHIFT.compose(_at(36.4, 0))  # d alone moved 0.4 m along x
    held = hold_placement(subs, before, after)
    assert abs((held["d"].t[0] - held["a"].t[0]) - 36.4) < 1e-6
    assert np.linalg.norm(held["a"].t - before["a"].t) < 0.15  # a quarter of d's 0.4 m, split by the fit
    assert held["d"].t[0] - before["d"].t[0] > 0.25


def test_hold_placement_needs_submaps_held_before() -> None:
    subs = [_submap("new")]
    after = {"new": _at(3, 4)}
    assert hold_placement(subs, {}, after) == after


def test_tile_motion_counts_a_surface_in_every_tile_it_is_near_at_either_pose() -> None:
    subs = [_submap("a"), _submap("far"), _submap("new")]
    before = {"a": _at(53, 10), "far": _at(200, 200)}  # a: x 53..63, within 2 m of tile (1, 0)
    after = {"a": _at(53.1, 10), "far": _at(200, 200), "new": _at(10, 80)}
    motion = tile_motion(subs, before, after, tile_size=64.0, band_m=2.0)
    assert motion[(0, 0)] == pytest.approx(0.1) and motion[(1, 0)] == pytest.approx(0.1)
    assert motion[(3, 3)] == pytest.approx(0.0)
    assert motion[(0, 1)] == math.inf  # the new submap's tile
    assert (2, 0) not in motion and (0, 2) not in motion
    assert (1, 0) not in tile_motion(subs, before, after, tile_size=64.0, band_m=0.5)  # 1 m short of it


def test_tile_motion_sees_a_changed_drift_correction() -> None:
    subs = [_submap("a")]
    pose = {"a": _at(5, 5)}
    bent = Drift(log_scale=0.01)
    motion = tile_motion(subs, pose, pose, 64.0, 2.0, drifts_after={"a": bent})
    assert 0.03 < motion[(0, 0)] < 0.01 * math.hypot(10, 10) * 1.1  # 1 % of scale, at most the patch's diagonal
    assert tile_motion(subs, pose, pose, 64.0, 2.0, {"a": bent}, {"a": bent})[(0, 0)] == pytest.approx(0.0)


def test_settle_realignment_keeps_the_tiles_whose_surface_stood_still() -> None:
    subs = [_submap("a", seed=1), _submap("b", seed=2), _submap("new", seed=3)]
    before = {"a": _at(10, 10), "b": _at(80, 10)}
    after = {"a": SHIFT.compose(before["a"]), "b": SHIFT.compose(_at(80.02, 10)),
             "new": SHIFT.compose(_at(10, 20))}
    tiles = [(0, 0), (1, 0), (2, 0)]
    poses, kept, motion = settle_realignment(subs, before, after, tiles, tile_size=64.0, band_m=2.0, hold=True,
                                             keep_m=0.05)
    assert kept == [(1, 0), (2, 0)]  # (0, 0) has the new session; (2, 0) holds nothing
    assert motion[(0, 0)] == math.inf and motion[(1, 0)] < 0.05
    assert np.linalg.norm(poses["a"].t - before["a"].t) < 0.02  # the 0.36 m of the whole map taken back
    assert settle_realignment(subs, before, after, tiles, tile_size=64.0, band_m=2.0, hold=True, keep_m=0.0)[1] == []
    unheld, kept_unheld, _ = settle_realignment(subs, before, after, tiles, tile_size=64.0, band_m=2.0, hold=False,
                                                keep_m=0.05)
    assert unheld == after and kept_unheld == [(2, 0)]  # the whole map moved: only the empty tile stays


def test_settle_realignment_holds_nothing_where_a_held_submap_pins_the_map() -> None:
    """A submap the re-alignment did not free (it reaches outside the region) fixes the gauge already:
    moving the rest rigidly would tear the region off it."""
    subs = [_submap("a"), _submap("border")]
    before = {"a": _at(10, 10)}
    after = {"a": _at(10.3, 10)}
    poses, kept, motion = settle_realignment(subs, before, after, [(0, 0)], tile_size=64.0, band_m=2.0, hold=True,
                                             keep_m=0.05)
    assert poses == after and kept == [] and motion[(0, 0)] == pytest.approx(0.3)


def test_tile_carry_is_each_tiles_rigid_motion_in_its_own_frame() -> None:
    """A map moved rigidly: every tile's carry is that motion, in the tile's frame (the map frame less its
    lower corner); a tile no surface reaches has none; a submap that moved on its own moves its tiles' carry
    towards its own motion, in least squares over the faces."""
    from fusion.placement import tile_carry

    subs = [_submap("a", seed=1), _submap("b", seed=2), _submap("c", seed=3), _submap("new", seed=4)]
    before = {"a": _at(10, 10), "b": _at(80, 10), "c": _at(60, 60, 30)}
    after = {k: SHIFT.compose(v) for k, v in before.items()} | {"new": _at(20, 20)}
    tiles = [(0, 0), (1, 0), (2, 0), (0, 1), (1, 1)]
    carry = tile_carry(subs, before, after, tiles, tile_size=64.0, band_m=2.0)
    assert sorted(carry) == [(0, 0), (0, 1), (1, 0), (1, 1)]  # c spans four tiles; (2, 0) is empty
    for (i, j), m in carry.items():
        corner = np.eye(4)
        corner[:3, 3] = [i * 64.0, j * 64.0, 0.0]
        assert np.allclose(m, np.linalg.inv(corner) @ SHIFT.matrix() @ corner, atol=1e-9)

    bent = after | {"b": _at(80.3, 10)}  # b alone moved on, 0.3 m along x
    alone = tile_carry(subs, before, bent, [(1, 0)], tile_size=64.0, band_m=2.0)[(1, 0)]
    shared = tile_carry(subs, before, bent, [(0, 0)], tile_size=64.0, band_m=2.0)[(0, 0)]
    assert np.allclose(shared, carry[(0, 0)], atol=1e-9)  # (0, 0) holds a and c only
    b_only = tile_carry([subs[1]], before, bent, [(1, 0)], tile_size=64.0, band_m=2.0)[(1, 0)]
    assert np.allclose(b_only[:3, 3], [0.3, 0.0, 0.0], atol=1e-9) and np.allclose(b_only[:3, :3], np.eye(3))
    assert 0.0 < alone[0, 3] - carry[(1, 0)][0, 3] < 0.3  # c's faces there pull it back towards the shift


def test_quiet_tiles_are_those_no_new_submap_reaches() -> None:
    """A tile a new submap reaches has infinite motion (``tile_motion``); one no face reaches is not quiet."""
    from fusion.placement import quiet_tiles

    motion = {(0, 0): math.inf, (1, 0): 0.3, (2, 0): 0.0}
    assert quiet_tiles([(2, 0), (0, 0), (1, 0), (3, 0)], motion) == [(1, 0), (2, 0)]
