"""Offline fusion of a directory of uploads: tiles in the fused PLY format, one pose per submap,
clear one-line errors for bad files, and the CLI's error contract."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion.eval.synth.fleet import FleetParams
from fusion.eval.synth.simulate import simulate
from fusion.eval.synth.world import WorldParams

TILE = 32.0


def tiny_config():
    from fusion.config import FusionConfig

    return FusionConfig.preset("cpu").with_(
        iterations=30, pose_warmup=3, surface_samples=512, space_samples=512, pool_points=20_000, num_levels=6,
        lod_start_levels=3, max_resolution=64, geo_hidden=32, sem_hidden=32, extract_voxel_m=0.5, tile_margin_m=4.0,
        consensus=False, c_th=0.3, align_iterations_per_tile=30,
    )


@pytest.fixture(scope="module")
def uploads(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny world whose data lies inside tile (0, 0) of 64 m: one tile to fuse."""
    out = tmp_path_factory.mktemp("uploads")
    simulate(out, seed=5, sessions=2, gps_noise=(0.3, 0.3),
             world_params=WorldParams(core_min=(16.0, 16.0), core_max=(48.0, 48.0), margin=8.0, ground_res=0.5),
             fleet_params=FleetParams(submap_length=15.0, sensor_range=8.0, submap_res=0.8, drive_margin=0.0))
    return out


@pytest.fixture(scope="module")
def multi_tile_uploads(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny world spread over several 32 m tiles."""
    out = tmp_path_factory.mktemp("uploads32")
    simulate(out, seed=6, sessions=2, gps_noise=(0.5, 0.5),
             world_params=WorldParams(core_max=(TILE, TILE), margin=10.0, ground_res=0.5),
             fleet_params=FleetParams(submap_length=15.0, sensor_range=10.0, submap_res=0.8, drive_margin=2.0))
    return out


@pytest.mark.timeout(300)
def test_fuse_directory_writes_tiles_and_poses(uploads: Path, tmp_path: Path) -> None:
    """End to end with the real reconstruct_tile and a tiny config (a few seconds on an idle 2-core CPU)."""
    from fusion.meshio import read_fused_ply
    from fusion.offline import fuse_directory

    events = []
    summary = fuse_directory(uploads, tmp_path, tiny_config(), tile_size=64.0, progress=events.append)
    assert summary["tiles"] == [[0, 0]]
    tiles = sorted((tmp_path / "tiles").glob("*.ply"))
    assert (tmp_path / "tiles" / "0_0.ply").exists()
    assert len(tiles) == len(summary["metrics"])
    mesh = read_fused_ply((tmp_path / "tiles" / "0_0.ply").read_bytes())
    assert len(mesh.faces) > 0
    # clipped to its tile (map frame)
    assert mesh.vertices[:, :2].min() >= -1e-3 and mesh.vertices[:, :2].max() <= 64.0 + 1e-3
    poses = json.loads((tmp_path / "poses.json").read_text())
    n_submaps = len(list(uploads.glob("*.ply")))
    assert len(poses) == n_submaps
    assert {frozenset(p) for p in poses} == {frozenset({"session_id", "seq", "id", "pose_gps", "pose_refined",
                                                        "drift_refined"})}
    assert all(p["pose_refined"] is not None for p in poses)
    found = [p["drift_refined"] for p in poses if p["drift_refined"] is not None]  # fine_drift: on by default
    assert found and all(set(d) == {"scale", "bend_yaw_rad_per_m", "bend_pitch_rad_per_m", "axis"} for d in found)
    assert any(not np.allclose(p["pose_gps"]["t"], p["pose_refined"]["t"]) for p in poses)
    assert events and events[-1].stage.startswith("tile ")


def _fake_fuse_tile(calls: list, warmed: list | None = None):
    """A stand-in ``reconstruct_tile``: records (tile, inputs, pins) in ``calls`` and whether it was
    given a warm-start field in ``warmed``."""
    from fusion.types import FusedMesh, FusionResult

    warmed = [] if warmed is None else warmed

    def fake(submaps, tile, config, progress=None, border_pins=None, device=None, warm=None,
             warm_kind="alignment"):
        calls.append((tile, {s.id: (s.free, s.pose_init) for s in submaps}, border_pins))
        warmed.append(warm is not None)
        border = {side: {"tile": (tile.i, tile.j), "side": side} for side in ("x0", "x1", "y0", "y1")}
        return FusionResult(FusedMesh.empty(), {}, {"points_per_s": 1.0}, {}, border)

    return fake


@pytest.mark.timeout(300)
def test_region_aligned_then_tiles_reconstructed_with_fixed_poses(
        multi_tile_uploads: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Real (tiny) region alignment, stand-in reconstruction: every tile is reconstructed with every
    submap held at its aligned pose, in sorted order, neighbours pin the shared border; the poses do
    not depend on the order the tiles were listed in."""
    import fusion.reconstruct
    from fusion.offline import fuse_tiles, load_directory

    submaps = load_directory(multi_tile_uploads, TILE)
    keys = sorted({k for s in submaps for k in s.tiles})
    assert len(keys) > 1
    cfg = tiny_config().with_(align_iterations_per_tile=3)  # a few steps: poses move, order must not matter
    runs = []
    for order in (keys, list(reversed(keys)), keys[1::2] + keys[0::2]):
        calls: list = []
        warmed: list = []
        monkeypatch.setattr(fusion.reconstruct, "reconstruct_tile", _fake_fuse_tile(calls, warmed))
        refined: dict = {}
        align: list = []
        fuse_tiles(submaps, order, cfg, TILE, refined=refined, align_metrics=align)
        runs.append((calls, refined))
        trained = set(align[0]["tile_pool_points"])  # the tiles the alignment trained a field in
        assert warmed == [f"{t.i}_{t.j}" in trained for t, _, _ in calls] and any(warmed)
        assert len(align) == 1 and align[0]["num_free"] == len(submaps)
        assert [(t.i, t.j) for t, _, _ in calls] == keys  # sorted, whatever the order given
        fused: set = set()
        for tile, inputs, pins in calls:
            for sid, (free, pose) in inputs.items():
                assert not free and np.allclose(pose.t, refined[sid].t)
            left = (tile.i - 1, tile.j)
            if left in fused:
                assert pins["x0"] == {"tile": left, "side": "x1"}
            fused.add((tile.i, tile.j))
    assert set(runs[0][1]) == {s.input.id for s in submaps}
    assert any(not np.allclose(runs[0][1][s.input.id].t, s.pose_gps.t) for s in submaps)
    for _, refined in runs[1:]:
        for sid, pose in runs[0][1].items():
            assert np.allclose(refined[sid].t, pose.t, atol=1e-6) and np.allclose(refined[sid].q, pose.q, atol=1e-6)


@pytest.mark.timeout(300)
def test_with_fine_drift_each_tile_holds_the_corrected_submaps_and_poses_json_the_corrections(
        multi_tile_uploads: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fusion.reconstruct
    from fusion.drift import Drift
    from fusion.offline import fuse_directory, load_directory
    from fusion.types import FusedMesh, FusionResult

    meshes: dict = {}

    def fake(submaps, tile, config, progress=None, border_pins=None, device=None, warm=None, warm_kind="alignment"):
        meshes.update({s.id: s.mesh.vertices for s in submaps})
        return FusionResult(FusedMesh.empty(), {}, {}, {}, {})

    monkeypatch.setattr(fusion.reconstruct, "reconstruct_tile", fake)
    fuse_directory(multi_tile_uploads, tmp_path, tiny_config().with_(align_iterations_per_tile=0, fine_drift=True),
                   tile_size=TILE)
    found = {p["id"]: p["drift_refined"] for p in json.loads((tmp_path / "poses.json").read_text())}
    assert any(found.values())
    for s in load_directory(multi_tile_uploads, TILE):
        expected = Drift.from_json(found[s.input.id]).apply(s.input.mesh.vertices)
        np.testing.assert_allclose(meshes[s.input.id], expected)


def test_cli_refuses_an_unknown_setting_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "fusion.eval.cli", "fuse", str(tmp_path), "--out", str(tmp_path / "o"),
                           "--set", "fine_drift_typo=true"], capture_output=True, text=True, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "fine_drift_typo" in proc.stderr


def test_fixed_poses_skip_alignment(multi_tile_uploads: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fusion.align
    import fusion.reconstruct
    from fusion.offline import fuse_tiles, load_directory

    def no_align(*args, **kwargs):
        raise AssertionError("alignment must not run with fixed poses")

    calls: list = []
    warmed: list = []
    monkeypatch.setattr(fusion.reconstruct, "reconstruct_tile", _fake_fuse_tile(calls, warmed))
    monkeypatch.setattr(fusion.align, "align_region", no_align)
    submaps = load_directory(multi_tile_uploads, TILE)
    fixed = {s.input.id: s.pose_gps for s in submaps}
    keys = sorted({k for s in submaps for k in s.tiles})
    out = fuse_tiles(submaps, keys, tiny_config(), TILE, fixed_poses=fixed)
    assert sorted(out) == keys and all(not free for _, inputs, _ in calls for free, _ in inputs.values())
    assert warmed and not any(warmed)  # no alignment, no field to start from


def test_a_submap_posed_where_its_gps_box_did_not_reach_is_fused_there(multi_tile_uploads: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """As in the service: a submap joins every tile its surface reaches at its aligned pose, beside those of
    its GPS box (a GPS error beyond its sigma); ``grow`` reconstructs the tiles only such a surface reaches."""
    import fusion.reconstruct
    from fusion.offline import fuse_tiles, load_directory
    from fusion.types import Pose

    submaps = load_directory(multi_tile_uploads, TILE)
    keys = sorted({k for s in submaps for k in s.tiles})
    moved = submaps[0]
    far = (max(i for i, _ in keys) + 3, 0)  # no GPS box comes near it
    shift = np.array([far[0] * TILE + TILE / 2, 0.0, 0.0]) - moved.pose_gps.apply(moved.input.mesh.vertices).mean(0)
    shift[1] = 0.0
    fixed = {s.input.id: s.pose_gps for s in submaps}
    fixed[moved.input.id] = Pose(moved.pose_gps.t + shift, moved.pose_gps.q)
    for grow in (False, True):
        calls: list = []
        monkeypatch.setattr(fusion.reconstruct, "reconstruct_tile", _fake_fuse_tile(calls))
        fuse_tiles(submaps, keys, tiny_config(), TILE, fixed_poses=fixed, grow=grow)
        done = [(t.i, t.j) for t, _, _ in calls]
        assert done == sorted(done)
        held = {(t.i, t.j): set(inputs) for t, inputs, _ in calls}
        assert all(moved.input.id in held[k] for k in moved.tiles)  # its GPS box's tiles keep it
        extra = set(done) - set(keys)
        assert (far in extra) == grow and set(keys) <= set(done)
        assert all(held[k] == {moved.input.id} and k[0] > max(i for i, _ in keys) for k in extra)


def test_bad_ply_names_the_file(uploads: Path, tmp_path: Path) -> None:
    from fusion.offline import OfflineInputError, load_directory

    for p in uploads.glob("s00_000.*"):
        (tmp_path / p.name).write_bytes(p.read_bytes())
    (tmp_path / "broken.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    (tmp_path / "broken.json").write_text("{}")
    with pytest.raises(OfflineInputError) as exc:
        load_directory(tmp_path)
    assert "broken.ply" in exc.value.message and "\n" not in exc.value.message


def test_missing_meta_names_the_file(uploads: Path, tmp_path: Path) -> None:
    from fusion.offline import OfflineInputError, load_directory

    (tmp_path / "a.ply").write_bytes((uploads / "s00_000.ply").read_bytes())
    with pytest.raises(OfflineInputError, match="a.json"):
        load_directory(tmp_path)
    (tmp_path / "a.json").write_text(json.dumps({"session_id": "x", "seq": 0, "gps": {}}))
    with pytest.raises(OfflineInputError, match="a.json"):
        load_directory(tmp_path)


def test_cli_error_is_one_line_exit_2(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "fusion.eval.cli", "fuse", str(tmp_path / "nope"), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "nope" in proc.stderr


def test_cli_module_does_not_import_torch() -> None:
    code = "import sys, argparse, fusion.eval.cli as c; p = argparse.ArgumentParser(); c.register(p.add_subparsers()); " \
           "print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "False"
