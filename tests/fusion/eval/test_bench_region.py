"""Multi-tile bench helpers: the seam check, mesh merging and the variant rows (no fusion run)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from fusion.config import FusionConfig
from fusion.eval import bench_region, bench_seeds
from fusion.eval.bench_region import seam_gaps
from fusion.eval.scoring import merge_meshes
from fusion.types import FusedMesh, FusionResult


def _mesh(vertices: np.ndarray) -> FusedMesh:
    n = len(vertices)
    faces = np.array([[0, 1, 2]], np.int32) if n >= 3 else np.zeros((0, 3), np.int32)
    return FusedMesh(vertices.astype(np.float32), faces, np.ones(n, np.uint8), np.ones(n, np.float32),
                     np.ones(len(faces), np.uint8))


def _result(vertices: np.ndarray) -> FusionResult:
    return FusionResult(_mesh(vertices), {}, {}, {}, {})


def _strip(x_border: float, x_inner: float, ys: np.ndarray, z: float = 0.0) -> FusedMesh:
    """A strip of triangles between the border line x = ``x_border`` and x = ``x_inner`` over ``ys``."""
    n = len(ys)
    v = np.concatenate([np.column_stack([np.full(n, x_border), ys, np.full(n, z)]),
                        np.column_stack([np.full(n, x_inner), ys, np.full(n, z)])])
    faces = [[k, k + 1, n + k] for k in range(n - 1)] + [[k + 1, n + k + 1, n + k] for k in range(n - 1)]
    f = np.array(faces, np.int32)
    return FusedMesh(v.astype(np.float32), f, np.ones(2 * n, np.uint8), np.ones(2 * n, np.float32),
                     np.ones(len(f), np.uint8))


def test_seam_gaps_measure_the_stretch_of_border_one_tile_meets_alone() -> None:
    ys = np.arange(0.0, 10.01, 0.5)
    left = FusionResult(_strip(10.0, 9.5, ys), {}, {}, {}, {})
    out = seam_gaps({(0, 0): left, (1, 0): FusionResult(_strip(10.0, 10.5, ys), {}, {}, {}, {})}, 10.0, 0.25)
    assert out["seam_borders"] == 1 and out["seam_max_m"] == 0.0 and out["seam_far_share"] == 0.0
    # the right tile's surface stops short of the border for 3 m (3 <= y <= 6): a 3 m gap
    holed = np.concatenate([ys[ys <= 3.0], ys[ys >= 6.0]])
    right = _strip(10.0, 10.5, holed)
    keep = ~np.isclose(right.vertices[right.faces][:, :, 1].min(1), 3.0) | ~np.isclose(
        right.vertices[right.faces][:, :, 1].max(1), 6.0)  # no face bridging the hole
    right = FusedMesh(right.vertices, right.faces[keep], right.vertex_labels, right.vertex_confidence,
                      right.face_labels[keep])
    out = seam_gaps({(0, 0): left, (1, 0): FusionResult(right, {}, {}, {}, {})}, 10.0, 0.25)
    assert 3.0 - 0.25 <= out["seam_max_m"] <= 3.0 and 0 < out["seam_far_share"] < 0.2  # within a voxel (sampling)
    # the right tile's surface meets the border 0.6 m higher all along: a double surface the whole length
    out = seam_gaps({(0, 0): left, (1, 0): FusionResult(_strip(10.0, 10.5, ys, z=0.6), {}, {}, {}, {})}, 10.0, 0.25)
    assert abs(out["seam_max_m"] - 10.0) < 1e-6 and out["seam_far_share"] == 1.0


def test_a_face_touching_the_border_in_one_vertex_is_no_seam() -> None:
    """Only surface meeting the border along an edge makes a seam: a face of one tile touching the border
    line in a single vertex, the other tile with nothing near, is no gap."""
    touch = FusedMesh(np.array([[10.0, 5.0, 0.0], [9.5, 5.0, 0.0], [9.5, 5.5, 0.0]], np.float32),
                      np.array([[0, 1, 2]], np.int32), np.ones(3, np.uint8), np.ones(3, np.float32), np.ones(1, np.uint8))
    ys = np.arange(0.0, 3.01, 0.5)
    out = seam_gaps({(0, 0): FusionResult(touch, {}, {}, {}, {}),
                     (1, 0): FusionResult(_strip(10.0, 10.5, ys + 20.0), {}, {}, {}, {})}, 10.0, 0.25)
    assert out["seam_max_m"] == pytest.approx(3.0)  # the right tile's 3 m of border alone; the touch adds none


def test_merge_meshes_reindexes_faces() -> None:
    a = _mesh(np.eye(3))
    b = _mesh(np.eye(3) + 5)
    m = merge_meshes([a, FusedMesh.empty(), b])
    assert len(m.vertices) == 6 and m.faces.tolist() == [[0, 1, 2], [3, 4, 5]]


def test_without_detail_strips_the_faces_the_extraction_appended() -> None:
    """The bench scores the same fields' meshes without the upload faces (``detail_m=0``'s extraction, free)."""
    field = _mesh(np.eye(3))
    both = merge_meshes([field, _mesh(np.eye(3) + 5)])  # the field's face, then one upload face appended
    both.face_labels[1] = 7
    results = {(0, 0): FusionResult(both, {}, {"extract": {"detail_faces": 1}}, {}, {}),
               (1, 0): FusionResult(_mesh(np.eye(3) + 9), {}, {"extract": {}}, {}, {})}
    plain = bench_region.without_detail(results)
    assert plain is not None
    stripped = plain[(0, 0)].mesh
    assert stripped.faces.tolist() == [[0, 1, 2]] and np.array_equal(stripped.vertices, field.vertices)
    assert stripped.face_labels.tolist() == [field.face_labels[0]] and len(stripped.vertex_confidence) == 3
    assert plain[(1, 0)].mesh is results[(1, 0)].mesh
    assert bench_region.without_detail({(1, 0): results[(1, 0)]}) is None  # nothing added: no such row


def _fake_bench(monkeypatch: pytest.MonkeyPatch) -> tuple[list[str], list[FusionConfig]]:
    """The region bench with simulation, preparation and fusion replaced by recorders."""
    import fusion.eval.synth.simulate as simulate_module

    simulated: list[str] = []
    fused: list[FusionConfig] = []
    monkeypatch.setattr(simulate_module, "simulate", lambda *a, **k: simulated.append("simulate"))
    monkeypatch.setattr(bench_region, "prepare", lambda _d, cfg, **_: SimpleNamespace(submaps=[], config=cfg))

    def fake_fuse(ctx: Any, keys: Any, fixed: Any, config: FusionConfig | None = None) -> dict[str, Any]:
        fused.append(config or ctx.config)
        return {"geo_f": 0.5 + 0.1 * len(fused)}

    monkeypatch.setattr(bench_region, "_fuse", fake_fuse)
    return simulated, fused


def test_variants_are_fused_rows_with_their_overrides_on_the_same_data(monkeypatch: pytest.MonkeyPatch) -> None:
    simulated, fused = _fake_bench(monkeypatch)
    printed: list[str] = []
    report = bench_region.run_region_bench("tiny", sessions=2, tiles=2, rows=["fused"], out=printed.append,
                                           variants=["coarse_register=false", "sdf_robust_m=0.1,consensus=true"])
    assert simulated == ["simulate"]  # one fleet for every row
    assert list(report["rows"]) == ["fused", "coarse_register=false", "sdf_robust_m=0.1,consensus=true"]
    base = FusionConfig.preset("tiny")
    assert fused[0] == base
    assert fused[1] == base.with_(coarse_register=False)
    assert fused[2] == base.with_(sdf_robust_m=0.1, consensus=True)
    table = printed[0]
    assert "sdf_robust_m=0.1,consensus=true" in table and "0.800" in table  # the third row's geo F


def test_seeds_each_run_their_own_fleet_and_are_judged_across(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:  # noqa: ANN001
    """``--seeds``: one world and fleet per seed, each with the same rows; the figures per seed and their mean,
    and per condition of the verdict against the baseline the seeds it held on."""
    import json

    import fusion.eval.synth.simulate as simulate_module

    _fake_bench(monkeypatch)
    seeds: list[int] = []
    monkeypatch.setattr(simulate_module, "simulate", lambda *a, **k: seeds.append(k["seed"]))

    def fake_fuse(ctx: Any, keys: Any, fixed: Any, config: FusionConfig | None = None) -> dict[str, Any]:
        seed = seeds[-1]  # the fleet this row fuses: its figures depend on the seed
        return {"geo_f": 0.8 + 0.01 * seed, "sem_f": 0.4, "pose_trans_m": 0.3, "pose_rot_deg": 0.4 + 0.1 * seed,
                "transient_survival": 0.01}

    monkeypatch.setattr(bench_region, "_fuse", fake_fuse)
    monkeypatch.setattr(bench_region, "_baseline", lambda *a: {"geo_f": 0.6, "sem_f": 0.25, "pose_trans_m": 0.9,
                                                               "pose_rot_deg": 0.5})
    printed: list[str] = []
    path = tmp_path / "seeds.json"
    result = bench_seeds.run_region_seeds([0, 1, 2], json_path=path, out=printed.append, preset="tiny", tiles=2,
                                           rows=["fused", "gicp"])
    assert seeds == [0, 1, 2] and len(printed) == 4  # each seed's table, then the summary
    summary = result["summary"]
    geo = summary["rows"]["fused"]["geo_f"]
    assert geo["per_seed"] == pytest.approx([0.80, 0.81, 0.82]) and geo["mean"] == pytest.approx(0.81)
    rot = summary["checks"]["pose_rot_deg"]
    assert rot["per_seed"] == [True, False, False] and (rot["held"], rot["judged"]) == (1, 3)  # 0.4 / 0.5 / 0.6 vs 0.5
    geo_check = summary["checks"]["geo_f_miss_ratio"]
    assert geo_check["values"] == pytest.approx([0.5, 0.475, 0.45]) and geo_check["held"] == 3
    table = printed[-1]
    assert "across seeds 0, 1, 2 (sensor camera, preset tiny" in table
    assert "held on 1 of 3" in table and "0.50x ok" in table and "MISSED" in table
    saved = json.loads(path.read_text())
    assert set(saved["seeds"]) == {"0", "1", "2"} and saved["summary"]["checks"]["pose_rot_deg"]["held"] == 1
    with pytest.raises(ValueError, match="distinct"):
        bench_seeds.run_region_seeds([1, 1], out=printed.append)
    from fusion.eval import cli

    assert cli.main(["bench", "--tiles", "1", "--seeds", "0,1"]) != 0  # the one-tile bench has no seeds option
    with pytest.raises(SystemExit):
        cli.main(["bench", "--seeds", "0,x"])
    assert cli.main(["bench", "--seeds", "1,1"]) != 0  # the same seed twice: one line, nothing simulated


def _rows() -> dict[str, dict[str, Any]]:
    """A fused row and both baseline rows; of the baselines GICP has the better F, ICP the better rotation."""
    return {"fused": {"geo_f": 0.8, "sem_f": 0.4, "pose_trans_m": 0.4, "pose_rot_deg": 0.5, "transient_survival": 0.02},
            "icp": {"geo_f": 0.5, "sem_f": 0.2, "pose_trans_m": 1.0, "pose_rot_deg": 0.45},
            "gicp": {"geo_f": 0.6, "sem_f": 0.25, "pose_trans_m": 0.9, "pose_rot_deg": 0.6}}


def test_a_camera_fleet_is_judged_by_its_miss_rates_against_the_best_baseline_of_the_run() -> None:
    versus = bench_region.against_baseline(_rows(), "camera")
    assert versus is not None
    assert versus["baseline_geo_f"] == 0.6 and versus["baseline_pose_rot_deg"] == 0.45  # per figure the best
    assert versus["geo_f_miss_ratio"] == pytest.approx(0.2 / 0.4)
    assert versus["sem_f_miss_ratio"] == pytest.approx(0.6 / 0.75)
    assert versus["checks"] == {"geo_f_miss_ratio": True, "sem_f_miss_ratio": False, "pose_trans_m": True,
                                "pose_rot_deg": False, "transient_survival": True}
    report = {"rows": _rows(), "against_baseline": versus, "sensor": "camera", "submaps": 1, "sessions": 1, "tiles": 1,
              "tile_size_m": 64.0, "preset": "tiny", "seed": 0, "simulate_s": 0.0, "memory": {"peak_rss_mib": 1.0}}
    table = bench_region.format_region_table(report)
    assert "sem_f          0.400 vs 0.250, miss ratio 0.80x MISSED (needs 0.475)" in table
    # with the uploads at their true poses in the same run: what the bound asks beside what the input holds
    rows = _rows() | {"concat": {"geo_f": 0.9, "sem_f": 0.45}}
    with_uploads = bench_region.against_baseline(rows, "camera")
    assert with_uploads is not None
    assert with_uploads["sem_f_needed"] == pytest.approx(0.475) and with_uploads["sem_f_uploads"] == 0.45
    assert with_uploads["geo_f_needed"] == pytest.approx(0.72) and with_uploads["geo_f_uploads"] == 0.9
    assert versus["sem_f_uploads"] is None  # no concat row: nothing said about the input
    assert "miss ratio 0.80x MISSED (needs 0.475; the uploads at their true poses: 0.450)" in (
        bench_region.format_region_table(report | {"rows": rows, "against_baseline": with_uploads}))
    assert "target sem_f" not in table  # the exact fleet's absolute targets are not a camera fleet's
    assert "sensor camera, preset" in table
    report |= {"camera": ["depth_sigma_10m=0.3"], "world": ["junction=t"]}  # the overrides the fleet ran with
    assert "sensor camera (--camera depth_sigma_10m=0.3 --world junction=t), preset" in (
        bench_region.format_region_table(report))


def test_an_exact_fleet_needs_the_baselines_f_and_its_poses_within_the_slack() -> None:
    rows = _rows()
    rows["fused"] |= {"geo_f": 0.6, "sem_f": 0.24, "pose_trans_m": 0.92, "pose_rot_deg": 0.49}
    versus = bench_region.against_baseline(rows, "exact")
    assert versus is not None
    assert versus["checks"] == {"geo_f": True, "sem_f": False, "pose_trans_m": True, "pose_rot_deg": True}
    assert versus["sem_f_needed"] == 0.25  # an exact fleet's F: at least the baseline's
    rows["fused"]["pose_trans_m"] = 0.94  # 0.04 m over the best baseline's
    assert bench_region.against_baseline(rows, "exact")["checks"]["pose_trans_m"] is False  # type: ignore[index]
    assert bench_region.against_baseline({"fused": rows["fused"]}, "exact") is None  # no baseline row: nothing to say
    report = {"rows": rows, "against_baseline": None, "sensor": "exact", "submaps": 1, "sessions": 1, "tiles": 1,
              "tile_size_m": 64.0, "preset": "tiny", "seed": 0, "simulate_s": 0.0, "memory": {"peak_rss_mib": 1.0}}
    assert "target sem_f          0.240 (target 0.8) MISSED" in bench_region.format_region_table(report)
    report["rows"] = {"gicp": rows["gicp"]}  # no fused row (e.g. --rows add_sessions): no targets to judge
    assert "target" not in bench_region.format_region_table(report)


def test_a_bad_variant_fails_before_anything_is_simulated(monkeypatch: pytest.MonkeyPatch) -> None:
    from fusion.eval import cli

    simulated, fused = _fake_bench(monkeypatch)
    with pytest.raises(ValueError, match="no_such_field"):
        bench_region.run_region_bench("tiny", tiles=2, variants=["no_such_field=1"], out=lambda _: None)
    assert cli.main(["bench", "--tiles", "2", "--variant", "coarse_register=maybe"]) != 0
    assert cli.main(["bench", "--tiles", "1", "--variant", "coarse_register=false"]) != 0
    assert simulated == [] and fused == []


def test_every_ablation_component_is_a_valid_override() -> None:
    base = FusionConfig()
    for component in bench_region.COMPONENTS:
        assert base.with_overrides(component.split(",")) != base, component


@pytest.mark.timeout(300)
def test_add_session_aligns_only_the_new_session_and_refuses_only_its_tiles(tmp_path) -> None:  # noqa: ANN001
    """The ``add_session`` row: the last session arrives in a map of the others; only its submaps are free
    in the (incremental, fields frozen) alignment, and only the tiles it touches are reconstructed again."""
    from fusion.eval.bench_context import prepare
    from fusion.eval.synth.fleet import FleetParams
    from fusion.eval.synth.simulate import simulate
    from fusion.eval.synth.world import WorldParams

    simulate(tmp_path, seed=6, sessions=2, gps_noise=(0.5, 0.5), sensor="exact",
             world_params=WorldParams(core_max=(64.0, 32.0), margin=10.0, ground_res=0.5),
             fleet_params=FleetParams(submap_length=15.0, sensor_range=10.0, submap_res=0.8, drive_margin=2.0))
    # two sessions: the second would re-align the map jointly (realign_share), not be tracked against it
    config = FusionConfig.preset("tiny").with_(coarse_register=False, realign_share=2.0)
    ctx = prepare(tmp_path, config, tile_size=32.0, region=((0.0, 0.0), (64.0, 32.0)))
    keys = [(0, 0), (1, 0)]
    row = bench_region._add_session(ctx, keys)
    last = max(s.input.session_id for s in ctx.submaps)
    new = [s for s in ctx.submaps if s.input.session_id == last]
    align = row["alignment"][0]
    assert row["new_session"] == last and row["new_submaps"] == len(new) > 0
    assert align["incremental"] and align["num_free"] == len(new) < align["num_submaps"]
    # re-fused: the tiles the new surface reaches, at most those its GPS uncertainty reaches (which dirty them)
    refused = {tuple(k) for k in row["additions"][0]["refused"]}
    assert refused <= {t for s in new for t in s.tiles} and row["tiles_refused"] == len(refused) >= 1
    assert row["tiles_fused"] == 2
    # the tiny preset on a 64 m × 32 m world maps coarsely (the full fusion: geo F 0.43); what must hold is that
    # the addition leaves a map (a surface) and poses better than the uploads' GPS (0.12 m vs 0.52 m, seed 6)
    gps = bench_region._pose_figures(ctx, {s.input.id: s.pose_gps for s in ctx.submaps})
    assert row["recon_cpu_s_per_tile"] > 0  # process CPU time beside the wall time (shared machines)
    assert row["add_s"] > 0 and row["geo_f"] > 0.2 and row["pose_trans_m"] < 0.5 * gps["pose_trans_m"]


@pytest.mark.timeout(300)
def test_add_sessions_adds_the_last_two_one_after_the_other(tmp_path) -> None:  # noqa: ANN001
    """The ``add_sessions`` row: the second-last session is added to a map of the others, then the last to
    that map. With ``realign_share`` 1/2 the first (one of two sessions) re-aligns the map jointly: every
    submap free, every tile reconstructed; the second (one of three) is tracked against it: only its own
    submaps free, the others held at the re-aligned poses."""
    from fusion.eval.bench_context import prepare
    from fusion.eval.synth.fleet import FleetParams
    from fusion.eval.synth.simulate import simulate
    from fusion.eval.synth.world import WorldParams

    simulate(tmp_path, seed=6, sessions=3, gps_noise=(0.5, 0.5), sensor="exact",
             world_params=WorldParams(core_max=(64.0, 32.0), margin=10.0, ground_res=0.5),
             fleet_params=FleetParams(submap_length=15.0, sensor_range=10.0, submap_res=0.8, drive_margin=2.0))
    config = FusionConfig.preset("tiny").with_(coarse_register=False, realign_share=0.5)
    ctx = prepare(tmp_path, config, tile_size=32.0, region=((0.0, 0.0), (64.0, 32.0)))
    row = bench_region._add_session(ctx, [(0, 0), (1, 0)], count=2)
    order = sorted({s.input.session_id for s in ctx.submaps})
    size = {sid: sum(s.input.session_id == sid for s in ctx.submaps) for sid in order}
    first, second = row["additions"]
    assert (first["session"], second["session"]) == (order[1], order[2]) and row["new_session"] == order[2]
    both = size[order[0]] + size[order[1]]
    assert first["realigned"] and not first["alignment"]["incremental"] and row["realigned"] == [order[1]]
    assert first["alignment"]["num_free"] == first["alignment"]["num_submaps"] == both and first["tiles_refused"] == 2
    assert not second["realigned"] and second["alignment"]["incremental"]
    assert second["alignment"]["num_free"] == size[order[2]] and second["alignment"]["num_submaps"] == len(ctx.submaps)
    assert row["add_s"] == second["add_s"] > 0
    assert row["geo_f"] > 0.2 and row["poses"] == len(ctx.submaps)
    with pytest.raises(ValueError, match="needs 4 sessions"):
        bench_region._add_session(ctx, [(0, 0), (1, 0)], count=3)


def test_a_realignment_carries_each_refused_tiles_field_only_when_asked() -> None:
    """``_carried``: with ``refusion_carry`` the field of each tile to re-fuse moves with the tile's surface (its
    frame takes a point back by the motion, in the tile's frame); a tile not re-fused, or without a field, and
    every tile with the switch off, keep their last result as it was."""
    import torch

    from tests.fusion.test_placement import SHIFT, _at, _submap

    subs = [_submap("a", seed=1), _submap("b", seed=2)]
    before = {"a": _at(10, 10), "b": _at(80, 10)}
    after = {k: SHIFT.compose(v) for k, v in before.items()}
    results = {key: FusionResult(FusedMesh.empty(), {}, {}, {}, {}, field_state={"w": torch.ones(1)})
               for key in [(0, 0), (1, 0)]}
    on = FusionConfig.preset("tiny").with_(refusion_carry=True)
    out, carried = bench_region._carried(subs, results, before, after, [(1, 0)], 64.0, on, {}, {})
    assert carried == {(1, 0)} and out[(0, 0)] is results[(0, 0)]  # not re-fused
    corner = np.eye(4)
    corner[0, 3] = 64.0
    want = np.linalg.inv(np.linalg.inv(corner) @ SHIFT.matrix() @ corner)
    assert np.allclose(out[(1, 0)].field_state["norm.frame"].double().numpy(), want, atol=1e-5)
    assert torch.equal(out[(1, 0)].field_state["w"], torch.ones(1))
    off = bench_region._carried(subs, results, before, after, [(1, 0)], 64.0, on.with_(refusion_carry=False), {}, {})
    assert off == (results, set())
    bare = {**results, (1, 0): FusionResult(FusedMesh.empty(), {}, {}, {}, {})}
    assert bench_region._carried(subs, bare, before, after, [(1, 0)], 64.0, on, {}, {})[1] == set()
