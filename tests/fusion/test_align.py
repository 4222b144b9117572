"""Region alignment: one pose per submap across tiles; incremental alignment against frozen fields."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusion.align import align_levels, align_region
from fusion.types import Pose, TileSpec
from tests.scene import tiny_config, two_sessions

SIZE = 16.0
TILES = [TileSpec(0, 0, SIZE), TileSpec(1, 0, SIZE)]
SHIFT = Pose(np.array([8.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))  # the 16 m street spans x 8..24


def _scene(offset=(0.5, -0.4, 0.1), yaw_deg=1.0):
    """Two sessions, each one submap crossing the border x = 16 between tiles (0, 0) and (1, 0)."""
    subs, _ = two_sessions(offset=offset, yaw_deg=yaw_deg)
    out = []
    for s in subs:
        pose = SHIFT.compose(s.pose_init)
        out.append(replace(s, pose_init=pose, pose_gps=pose))
    return out


def _relative(poses: dict[str, Pose]) -> tuple[float, float]:
    rel = poses["a"].inverse().compose(poses["b"])
    return float(np.linalg.norm(rel.t)), float(np.degrees(2 * np.arccos(min(1.0, abs(rel.q[0])))))


def _config(**kw):
    return tiny_config(**({"align_iterations_per_tile": 40, "align_max_levels": 5, "surface_samples": 768, "space_samples": 768} | kw))


@pytest.mark.timeout(300)
def test_align_region_reduces_pose_error_across_the_border() -> None:
    subs = _scene()
    before = _relative({s.id: s.pose_init for s in subs})
    events = []
    res = align_region(list(reversed(subs)), list(reversed(TILES)), _config(), progress=events.append)
    after = _relative(res.poses)
    assert set(res.poses) == {"a", "b"}
    assert after[0] < 0.5 * before[0], (before, after)
    assert after[1] < before[1] + 0.3, (before, after)  # yaw: reconstruct_tile does not fix it in 80 steps here either
    m = res.metrics
    assert m["num_tiles"] == 2 and m["num_submaps"] == 2 and m["num_free"] == 2
    assert m["iterations"] == 2 * 40 and not m["incremental"]
    assert len(m["coarse"]["polish"]["rounds"]) == 3  # the fine registration once more after the field
    assert set(m["tile_pool_points"]) == {"0_0", "1_0"} and set(res.fields) == {(0, 0), (1, 0)}
    assert events and events[-1].stage == "align" and events[-1].iteration == events[-1].total
    # heads are shared by the tiles' fields
    f0, f1 = res.fields[(0, 0)], res.fields[(1, 0)]
    assert all(np.array_equal(f0[k].numpy(), f1[k].numpy()) for k in f0 if k.startswith(("geo.", "sem.")))


@pytest.mark.parametrize("steps", [20, 0])
def test_incremental_alignment_moves_only_the_new_submaps(steps: int) -> None:
    """A new submap is aligned onto a held map (its submaps fixed) and lands on the held street. With
    tracking steps (``align_incremental_iterations_per_tile`` 20) it tracks the frozen fields, which come back
    unchanged; with none (0, the default) the registrations alone place it, no field is tracked against or
    returned (each tile is re-fused from its own last field), and a first alignment still trains its fields
    (held fields of tiles outside the region do not make it an addition)."""
    subs = _scene(offset=(0.0, 0.0, 0.0), yaw_deg=0.0)
    cfg = _config(align_incremental_iterations_per_tile=steps)
    base = align_region([subs[0]], TILES, cfg.with_(align_iterations_per_tile=25))
    fixed = replace(subs[0], pose_init=base.poses["a"], free=False)
    new = replace(subs[1], pose_init=Pose(subs[1].pose_init.t + np.array([0.4, -0.3, 0.0]), subs[1].pose_init.q))
    res = align_region([fixed, new], TILES, cfg, frozen=base.fields)
    m = res.metrics
    assert set(res.poses) == {"b"} and m["incremental"]
    if steps:
        assert m["frozen_tiles"] == [[0, 0], [1, 0]] and m["iterations"] == 2 * steps
        for key, state in base.fields.items():  # the held fields are returned unchanged
            assert all(np.array_equal(state[k].numpy(), res.fields[key][k].numpy()) for k in state)
    else:
        assert m["registration_only"] and m["iterations"] == 0 and res.fields == {}
        elsewhere = {(9, 9): base.fields[(0, 0)]}  # a held field of no tile of the region: a first alignment
        assert align_region(subs, TILES, cfg.with_(align_iterations_per_tile=10), frozen=elsewhere).fields
    err_before = np.linalg.norm(new.pose_init.t - subs[1].pose_gps.t)
    err_after = np.linalg.norm(res.poses["b"].t - base.poses["a"].t)  # truth: b on a (same street)
    assert err_after < 0.5 * err_before, (err_before, err_after)


def test_an_alignment_without_field_steps_is_the_registration_alone() -> None:
    """``align_iterations_per_tile`` 0 (a re-alignment with ``realign_iterations_fraction`` 0, an addition):
    no field is trained or returned; the poses are where the registrations put them (``start_poses``), polished
    once more where the registration's matches proved tighter than its radii (gain > 1): the polish's weight is
    then above the registration's. Without that gain (``fine_polish_gain_max`` 1) nothing would change, and no
    polish runs."""
    from fusion.align import start_poses
    from fusion.config import FusionConfig

    subs = _scene()
    cfg = _config(align_iterations_per_tile=0)
    plain = align_region(subs, TILES, cfg.with_(fine_polish_gain_max=1.0))
    assert plain.fields == {} and plain.metrics["iterations"] == 0 and plain.metrics["registration_only"]
    assert "polish" not in plain.metrics["coarse"]
    start, _ = start_poses(subs, cfg)
    for sid, pose in plain.poses.items():
        assert np.allclose(pose.t, start[sid].t, atol=1e-6) and np.allclose(np.abs(pose.q), np.abs(start[sid].q), atol=1e-6)
    before = _relative({s.id: s.pose_init for s in subs})
    assert _relative(plain.poses)[0] < 0.5 * before[0], before

    res = align_region(subs, TILES, cfg)
    gain = res.metrics["coarse"]["fine"]["rounds"][-1]["gain"]
    assert gain > 1.5  # an exact street: the matches agree far tighter than the last radius
    assert res.metrics["coarse"]["polish"]["weight"] == pytest.approx(cfg.fine_weight * min(gain, cfg.fine_polish_gain_max))
    assert res.fields == {} and res.metrics["registration_only"]
    moved = max(np.linalg.norm(res.poses[sid].t - start[sid].t) for sid in start)
    assert moved > 1e-4  # the polish ran from the registration's poses
    assert _relative(res.poses)[0] <= _relative(plain.poses)[0] + 0.01, (_relative(plain.poses), _relative(res.poses))
    assert FusionConfig(realign_iterations_fraction=0.0).for_realignment().align_iterations_per_tile == 0
    with pytest.raises(ValueError, match="align_iterations_per_tile"):
        FusionConfig(align_iterations_per_tile=-1)
    with pytest.raises(ValueError, match="align_incremental_iterations_per_tile"):
        FusionConfig(align_incremental_iterations_per_tile=-1)


def test_align_levels_capped() -> None:
    cfg = tiny_config(align_max_levels=5)
    assert align_levels(0, 100, cfg) == cfg.lod_start_levels
    assert max(align_levels(i, 100, cfg) for i in range(100)) == 5


def ground_share(mesh) -> float:  # noqa: ANN001
    """The share of a mesh's faces on the street's ground plane (z ≈ 0)."""
    v = mesh.vertices[mesh.faces].mean(axis=1)
    return float(np.sum(np.abs(v[:, 2]) < 0.3)) / max(1, len(mesh.faces))


def test_reconstruction_starts_from_the_alignment_field() -> None:
    """A warm start carries the aligned field's surface: one step from it already extracts the street
    (a cold start's single step does not), a layout mismatch falls back to a cold start, and
    ``recon_warm_fraction`` 0 ignores the state."""
    from fusion.reconstruct import reconstruct_tile

    subs = _scene(offset=(0.0, 0.0, 0.0), yaw_deg=0.0)
    cfg = _config()
    aligned = align_region(subs, TILES, cfg)
    held = [replace(s, pose_init=aligned.poses[s.id], free=False) for s in subs]
    state = aligned.fields[(0, 0)]
    one_step = cfg.with_(iterations=3, recon_warm_fraction=1 / 3, schedule_min_fraction=1.0)
    warm = reconstruct_tile(held, TILES[0], one_step, warm=state)
    cold = reconstruct_tile(held, TILES[0], one_step)
    assert warm.metrics["warm_start"] and warm.metrics["iterations"] == 1
    assert not cold.metrics["warm_start"] and cold.metrics["iterations"] == 3
    assert len(warm.mesh.faces) > 0 and ground_share(warm.mesh) > 0.5
    assert ground_share(cold.mesh) < ground_share(warm.mesh) - 0.2, (ground_share(cold.mesh), ground_share(warm.mesh))
    other = reconstruct_tile(held, TILES[0], one_step.with_(num_levels=4), warm=state)
    assert not other.metrics["warm_start"]
    off = reconstruct_tile(held, TILES[0], one_step.with_(recon_warm_fraction=0.0), warm=state)
    assert not off.metrics["warm_start"] and off.metrics["iterations"] == 3


def test_a_refusion_starts_from_the_tiles_previous_reconstruction() -> None:
    """A reconstruction returns its trained field. Session b added, the tile's re-fusion starts from the
    field of the map before (session a), with ``refusion_warm_fraction`` of the steps: one step from it
    holds the street (a cold step does not). ``reconstruct_tiles`` re-fuses a tile of ``previous`` that way, a
    tile of ``carried`` with ``refusion_carried_fraction`` of the steps."""
    from fusion.offline import LoadedSubmap, reconstruct_tiles
    from fusion.reconstruct import reconstruct_tile

    held = [replace(s, free=False) for s in _scene(offset=(0.0, 0.0, 0.0), yaw_deg=0.0)]
    cfg = _config(iterations=60, schedule_min_fraction=1.0)
    first = reconstruct_tile(held[:1], TILES[0], cfg)
    assert first.field_state is not None and not first.metrics["warm_start"]
    once = cfg.with_(refusion_warm_fraction=1 / 60)
    again = reconstruct_tile(held, TILES[0], once, warm=first.field_state, warm_kind="reconstruction")
    cold = reconstruct_tile(held, TILES[0], once.with_(iterations=1))
    assert again.metrics["iterations"] == 1 and again.metrics["warm_kind"] == "reconstruction"
    assert ground_share(again.mesh) > 0.5 and ground_share(cold.mesh) < ground_share(again.mesh) - 0.2
    # as the alignment's warm start would: a third of the steps
    aligned = reconstruct_tile(held, TILES[0], once, warm=first.field_state)
    assert aligned.metrics["iterations"] == 20 and aligned.metrics["warm_kind"] == "alignment"

    loaded = [LoadedSubmap(s, s.pose_init, [(0, 0), (1, 0)], (0, 0)) for s in held]
    poses = {s.id: s.pose_init for s in held}
    refused = reconstruct_tiles(loaded, [(0, 0)], once, SIZE, None, poses, None, None, previous={(0, 0): first})
    assert refused[(0, 0)].metrics["warm_kind"] == "reconstruction" and refused[(0, 0)].metrics["iterations"] == 1
    # a field a re-alignment carried to a tile no new submap reaches: its own share of the steps
    fewer = once.with_(refusion_carried_fraction=1 / 30)
    carried = reconstruct_tiles(loaded, [(0, 0)], fewer, SIZE, None, poses, None, None, previous={(0, 0): first},
                                carried={(0, 0)})
    assert carried[(0, 0)].metrics["warm_kind"] == "carried" and carried[(0, 0)].metrics["iterations"] == 2


def test_incremental_tracking_uses_only_samples_near_the_held_map() -> None:
    """A frozen tile's field says nothing away from the data it was trained on: a new submap's samples
    track it only within ``align_track_support_m`` of the held submaps' surface."""
    import torch

    from fusion.align import _held_field
    from fusion.reconstruct import build_problem

    subs = _scene(offset=(0.0, 0.0, 0.0), yaw_deg=0.0)
    cfg = _config()
    state = align_region([subs[0]], TILES, cfg.with_(align_iterations_per_tile=3)).fields[(0, 0)]
    held = replace(subs[0], free=False)

    def kept(new, support: float) -> float:
        problem = build_problem([held, new], TILES[0], cfg.with_(align_track_support_m=support), torch.device("cpu"))
        n_new = int((problem.pool.submap == 1).sum())
        _held_field(problem, state, cfg.with_(align_track_support_m=support), torch.device("cpu"))
        return len(problem.pool.points) / n_new

    same = subs[1]  # the same street
    lifted = replace(subs[1], pose_init=Pose(subs[1].pose_init.t + np.array([0.0, 0.0, 6.5]), subs[1].pose_init.q))
    assert kept(same, 3.0) > 0.95
    assert kept(lifted, 3.0) == 0.0  # 3.5 m above the street's highest box: nothing to track
    assert kept(lifted, 0.0) == 1.0  # the mask off


def test_a_planar_step_moves_poses_only_in_x_y_and_yaw() -> None:
    import torch

    from fusion.poses import PoseSet
    from fusion.training import Optimiser

    poses = PoseSet(torch.eye(4, dtype=torch.float64)[None], torch.zeros(1, 3), torch.tensor([True]))
    opt = Optimiser([], poses, tiny_config(), iterations=10, warmup=0)
    target = torch.tensor([1.0, 2.0, 3.0, 0.1, 0.2, 0.3], dtype=torch.float64)
    for it in range(3):
        opt.step(it, ((torch.cat([poses.rho, poses.phi], dim=1)[0] - target) ** 2).sum(), planar=True)
    rho, phi = poses.rho.detach()[0], poses.phi.detach()[0]
    assert rho[0] > 0 and rho[1] > 0 and phi[2] > 0  # pulled toward the target
    assert rho[2] == 0 and phi[0] == 0 and phi[1] == 0  # height, roll and pitch held
    opt.step(3, ((torch.cat([poses.rho, poses.phi], dim=1)[0] - target) ** 2).sum())
    assert poses.rho.detach()[0, 2] > 0 and poses.phi.detach()[0, 0] > 0  # all six move after it
