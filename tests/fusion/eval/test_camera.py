"""The camera sensor model: each error of a camera pipeline exists, sits where it should and scales with
its parameter; the exact sensor still writes today's output."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from fusion.eval.synth import camera as cm
from fusion.eval.synth.camera import CameraSensor
from fusion.eval.synth.fleet import FleetParams
from fusion.eval.synth.simulate import load_ground_truth, simulate
from fusion.eval.synth.visibility import FieldOfView, visible_faces
from fusion.eval.synth.world import WorldParams
from fusion.labels import LABEL_BY_NAME
from fusion.meshio import read_submap_ply
from fusion.types import Pose

TINY_WORLD = {"core_max": (32.0, 32.0), "margin": 14.0, "ground_res": 0.5}
TINY_FLEET = {"submap_length": 15.0, "sensor_range": 14.0, "submap_res": 0.6}
L = {name: label.id for name, label in LABEL_BY_NAME.items()}
FORWARD = np.eye(3)[None]  # one camera looking along +x (columns: forward, left, up)

# A camera that only limits what it sees: every error off.
NO_ERRORS = CameraSensor(depth_sigma_10m=0.0, white_noise_m=0.0, scale_sigma=0.0, bend_yaw_deg_per_m=0.0,
                         bend_pitch_deg_per_m=0.0, bleed_prob=0.0, confusion=(), thin_miss=(), hole_rate=0.0)


def _grid(size: float = 40.0, step: float = 0.25, x0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat square grid (z = 0) from (x0, -size/2): vertices and upward faces."""
    xs = np.arange(x0, x0 + size + step / 2, step)
    ys = np.arange(-size / 2, size / 2 + step / 2, step)
    gx, gy = np.meshgrid(xs, ys)
    v = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    nx = len(xs)
    ix, iy = np.meshgrid(np.arange(nx - 1), np.arange(len(ys) - 1))
    a = (iy * nx + ix).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return v, f


def _areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


# -- exact: today's output -------------------------------------------------------------------------
def _fingerprint(records: list, gt) -> str:
    h = hashlib.sha256()
    for r in records:
        h.update(np.round(r.mesh.vertices, 4).astype(np.float64).tobytes())
        h.update(r.mesh.faces.astype(np.int64).tobytes())
        h.update(r.mesh.face_labels.astype(np.int64).tobytes())
        h.update(np.round(np.concatenate([r.pose_gps.t, r.pose_gps.q, r.odometry.t]), 6).tobytes())
    h.update(gt.observed.tobytes())
    h.update(gt.transient_observed.tobytes())
    return h.hexdigest()


def test_exact_sensor_writes_todays_output(tmp_path) -> None:
    """Digest of the exact sensor's uploads and observed truth, recorded before the camera model existed
    (vertices rounded to 0.1 mm). Both the default fleet and ``sensor="exact"`` give it."""
    recorded = "4ac6deaf9cf50f651e24904d23d131cb14de82b3aabb4072c23403c4577d66cf"
    for i, sensor in enumerate((None, "exact")):
        out = tmp_path / str(i)
        records = simulate(out, seed=3, sessions=2, world_params=WorldParams(**TINY_WORLD),
                           fleet_params=FleetParams(**TINY_FLEET), sensor=sensor)
        assert _fingerprint(records, load_ground_truth(out)) == recorded


def test_sensor_model_names_and_the_sensor_flag() -> None:
    import argparse

    from fusion.eval import cli

    assert cli.SENSORS == cm.SENSORS
    assert isinstance(cm.sensor_model("camera"), CameraSensor) and cm.sensor_model("exact") is None
    with pytest.raises(ValueError, match="unknown sensor"):
        cm.sensor_model("lidar")
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    assert parser.parse_args(["simulate", "out"]).sensor == "camera"
    assert parser.parse_args(["bench"]).sensor == "camera"
    assert parser.parse_args(["bench", "--sensor", "exact"]).sensor == "exact"
    with pytest.raises(SystemExit):
        parser.parse_args(["simulate", "out", "--sensor", "lidar"])


# -- field of view and range ----------------------------------------------------------------------
def test_field_of_view_keeps_only_what_lies_ahead_in_range() -> None:
    v, f = _grid(size=60.0, x0=-30.0)
    c = v[f].mean(axis=1)
    n = np.tile([0.0, 0.0, 1.0], (len(f), 1))
    sensor = np.array([[0.0, 0.0, 1.6]])
    everywhere = visible_faces(c, n, sensor, 20.0, [])
    seen = visible_faces(c, n, sensor, 20.0, [], fov=FieldOfView(FORWARD, 90.0, 60.0))
    d = c - sensor
    assert everywhere[c[:, 0] < -2].any()  # without a field of view: all round
    assert not seen[c[:, 0] <= 0].any()  # nothing behind the camera
    assert not seen[np.linalg.norm(d, axis=1) > 20.0].any()  # nothing beyond the range
    assert not seen[np.abs(d[:, 1]) > d[:, 0] * np.tan(np.radians(45.0)) + 1e-9].any()  # nor outside 90°
    # the vertical field of view hides the ground right in front of the camera: 1.6 m / tan(30°) = 2.8 m
    assert not seen[(c[:, 0] < 2.6) & (np.abs(c[:, 1]) < 0.5)].any() and seen[(c[:, 0] > 3.0) & (c[:, 0] < 4.0)
                                                                               & (np.abs(c[:, 1]) < 0.5)].all()
    wide = visible_faces(c, n, sensor, 20.0, [], fov=FieldOfView(FORWARD, 150.0, 60.0))
    assert wide.sum() > 1.5 * seen.sum() and not (seen & ~wide).any()


@pytest.fixture(scope="module")
def camera_sim(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("camera")
    records = simulate(out, seed=3, sessions=2, world_params=WorldParams(**TINY_WORLD),
                       fleet_params=FleetParams(**TINY_FLEET, camera=replace(NO_ERRORS, range_m=14.0)))
    return out, records


def test_camera_submaps_hold_only_what_lies_ahead(camera_sim) -> None:
    """Without errors a camera submap is the world ahead of the vehicle: in its local frame (x forward from
    the first camera position) nothing lies behind the start, and nothing beyond the range of the stretch."""
    out, records = camera_sim
    for r in records:
        x = r.mesh.vertices[:, 0]
        assert x.min() > -1.0
        assert x.max() < 15.0 + 14.0 + 1.0
        mesh = read_submap_ply((out / f"{r.name}.ply").read_bytes())  # a valid upload
        assert len(mesh.faces) == len(r.mesh.faces) > 500
    gt = load_ground_truth(out)
    assert gt.info["sensor"] == "camera"
    assert 0.05 < gt.observed.mean() < 0.9


# -- depth ----------------------------------------------------------------------------------------
def _depth_offsets(points: np.ndarray, cam: CameraSensor, draws: int) -> np.ndarray:
    """Signed displacement along the viewing ray from a camera at the origin looking along +x (draws, n)."""
    cams = np.zeros((1, 3))
    out = []
    for k in range(draws):
        moved = cm.depth_error(points, cams, FORWARD, cam, np.random.default_rng(k))
        ray = points / np.linalg.norm(points, axis=1, keepdims=True)
        d = moved - points
        assert np.allclose(np.cross(d, ray), 0.0, atol=1e-9)  # along the ray only
        out.append(np.einsum("ij,ij->i", d, ray))
    return np.array(out)


def test_depth_error_lies_along_the_ray_grows_with_range_and_scales_with_sigma() -> None:
    cam = replace(NO_ERRORS, depth_sigma_10m=0.1, depth_exponent=1.5, depth_corr_m=3.0)
    points = np.array([[5.0, 1.0, -1.6], [10.0, 1.0, -1.6], [20.0, 1.0, -1.6]])
    sd = _depth_offsets(points, cam, 400).std(axis=0)
    rho = np.linalg.norm(points, axis=1)
    expected = 0.1 * (rho / 10.0) ** 1.5
    assert np.allclose(sd, expected, rtol=0.15)
    assert sd[2] / sd[0] > 6.0  # (20 / 5)^1.5 = 8: grows with range
    doubled = _depth_offsets(points, replace(cam, depth_sigma_10m=0.2), 400).std(axis=0)
    assert np.allclose(doubled / sd, 2.0, rtol=0.05)


def test_depth_error_is_smooth_not_white() -> None:
    """Neighbours 0.3 m apart move together; points far beyond the correlation length do not."""
    cam = replace(NO_ERRORS, depth_sigma_10m=0.1, depth_corr_m=3.0)
    points = np.array([[10.0, 0.0, -1.6], [10.0, 0.3, -1.6], [10.0, 12.0, -1.6]])
    off = _depth_offsets(points, cam, 400)
    near = np.corrcoef(off[:, 0], off[:, 1])[0, 1]
    far = np.corrcoef(off[:, 0], off[:, 2])[0, 1]
    assert near > 0.95 and abs(far) < 0.2
    assert np.corrcoef(*_depth_offsets(points[:2], replace(cam, depth_corr_m=0.1), 400).T)[0, 1] < 0.2


def test_random_field_has_unit_variance_and_the_stated_correlation() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    g = np.array([cm.random_field(pts, 2.0, np.random.default_rng(k)) for k in range(3000)])
    assert abs(g[:, 0].std() - 1.0) < 0.05
    assert abs(np.corrcoef(g.T)[0, 1] - np.exp(-0.5)) < 0.06  # exp(-r²/2ℓ²) at r = ℓ


# -- scale and bend --------------------------------------------------------------------------------
def test_scale_error_multiplies_distances_by_one_factor_per_submap() -> None:
    v, _ = _grid(size=30.0, step=3.0, x0=1.0)  # the origin itself excluded (distance 0)
    cam = replace(NO_ERRORS, scale_sigma=0.02)
    factors = []
    for k in range(300):
        moved = cm.drift(v, cam, np.random.default_rng(k))
        ratio = np.linalg.norm(moved[1:] - moved[0], axis=1) / np.linalg.norm(v[1:] - v[0], axis=1)
        assert np.allclose(ratio, ratio[0])  # one factor for the whole submap, about its origin
        assert np.allclose(np.linalg.norm(moved, axis=1)[1:] / np.linalg.norm(v, axis=1)[1:], ratio[0])
        factors.append(ratio[0])
    assert abs(np.std(factors) - 0.02) < 0.003 and abs(np.mean(factors) - 1.0) < 0.004
    assert np.allclose(cm.drift(v, NO_ERRORS, np.random.default_rng(0)), v)


def test_bend_moves_points_quadratically_with_distance_ahead() -> None:
    ahead = np.array([[10.0, 0.0, 0.0], [20.0, 0.0, 0.0], [40.0, 0.0, 0.0]])
    for axis, key in ((1, "bend_yaw_deg_per_m"), (2, "bend_pitch_deg_per_m")):
        cam = replace(NO_ERRORS, **{key: 0.01})
        off = np.array([cm.drift(ahead, cam, np.random.default_rng(k))[:, axis] for k in range(400)])
        sd = off.std(axis=0)
        assert np.allclose(sd, np.radians(0.01) * ahead[:, 0] ** 2 / 2, rtol=0.15)  # κ x² / 2
        other = 3 - axis  # the other of y, z stays put
        assert np.allclose([cm.drift(ahead, cam, np.random.default_rng(k))[:, other] for k in range(5)], 0.0,
                           atol=1e-9)


# -- the segmenter ---------------------------------------------------------------------------------
def test_bleed_changes_labels_only_near_class_borders_and_scales_with_its_width() -> None:
    v, f = _grid(size=40.0)
    c = v[f].mean(axis=1)
    labels = np.where(c[:, 0] < 20.0, L["road"], L["sidewalk"])
    border = np.abs(c[:, 0] - 20.0)
    for width in (0.5, 1.0):
        cam = replace(NO_ERRORS, bleed_width_m=width, bleed_prob=0.5)
        changed = np.zeros(len(f), bool)
        shares = []
        for k in range(8):
            new = cm.bleed(c, labels, cam, np.random.default_rng(k))
            moved = new != labels
            assert set(np.unique(new[moved])) <= {L["road"], L["sidewalk"]}
            changed |= moved
            shares.append(moved[border <= width - 0.2].mean())
        assert border[changed].max() <= width + 1e-9  # only within the bleed width of the border
        assert border[changed].max() > width - 0.3  # and up to it
        assert 0.3 < np.mean(shares) < 0.7  # bleed_prob of the border strip


def test_confusion_only_between_the_named_classes_at_their_rates() -> None:
    v, f = _grid(size=60.0)
    c = v[f].mean(axis=1)
    stripes = [L["road"], L["sidewalk"], L["terrain"], L["building"], L["vehicle"], L["vegetation"]]
    labels = np.array(stripes)[np.minimum((c[:, 0] // 10).astype(int), len(stripes) - 1)]
    cam = replace(NO_ERRORS, confusion=(("road", "sidewalk", 0.2), ("terrain", "vegetation", 0.1)), label_corr_m=1.0)
    rates = {L["road"]: [], L["terrain"]: []}
    for k in range(6):
        new = cm.confuse(c, labels, cam, np.random.default_rng(k))
        moved = new != labels
        pairs = {(int(a), int(b)) for a, b in zip(labels[moved], new[moved], strict=True)}
        assert pairs == {(L["road"], L["sidewalk"]), (L["terrain"], L["vegetation"])}
        for cls in rates:
            rates[cls].append(moved[labels == cls].mean())
    assert 0.12 < np.mean(rates[L["road"]]) < 0.28 and 0.05 < np.mean(rates[L["terrain"]]) < 0.16


def test_thin_classes_are_missed_at_their_rate_and_take_the_class_around() -> None:
    road_v, road_f = _grid(size=40.0)
    mark_v, mark_f = _grid(size=40.0, step=0.1)
    keep = np.abs(mark_v[mark_f].mean(axis=1)[:, 1]) < 0.1  # a 0.2 m wide marking along x, 2 cm up
    mark_v = mark_v + [0.0, 0.0, 0.02]
    v = np.concatenate([road_v, mark_v])
    f = np.concatenate([road_f, mark_f[keep] + len(road_v)])
    c = v[f].mean(axis=1)
    labels = np.concatenate([np.full(len(road_f), L["road"]), np.full(int(keep.sum()), L["lane_marking"])])
    marking = labels == L["lane_marking"]
    for rate in (0.2, 0.6):
        cam = replace(NO_ERRORS, thin_miss=(("lane_marking", rate),), thin_corr_m=1.0)
        missed = []
        for k in range(10):
            new = cm.miss_thin(c, labels, cam, np.random.default_rng(k))
            assert np.array_equal(new[~marking], labels[~marking])
            assert set(np.unique(new[marking])) <= {L["lane_marking"], L["road"]}  # the class underneath
            missed.append((new[marking] != L["lane_marking"]).mean())
        assert abs(np.mean(missed) - rate) < 0.12
    none = cm.miss_thin(c, labels, replace(NO_ERRORS, thin_miss=(("lane_marking", 0.0),)), np.random.default_rng(0))
    assert np.array_equal(none, labels)


def test_systematic_share_repeats_the_same_mistakes_on_every_pass() -> None:
    v, f = _grid(size=40.0)
    c = v[f].mean(axis=1)
    labels = np.full(len(f), L["road"])
    place = cm.Place(Pose(np.array([100.0, 50.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])), seed=7)  # seen by two submaps

    def agreement(share: float) -> float:
        cam = replace(NO_ERRORS, confusion=(("road", "sidewalk", 0.3),), label_systematic=share)
        a = cm.confuse(c, labels, cam, np.random.default_rng(1), place) != labels
        b = cm.confuse(c, labels, cam, np.random.default_rng(2), place) != labels
        return float((a & b).sum() / (a | b).sum())

    assert agreement(1.0) == 1.0
    assert agreement(0.0) < 0.35 < agreement(0.7) < 1.0


def test_systematic_depth_share_repeats_the_same_depth_error() -> None:
    v, _ = _grid(size=20.0, step=1.0, x0=5.0)
    v[:, 2] = -1.6
    place = cm.Place(Pose(np.array([30.0, -20.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0])), seed=7)

    def passes(share: float) -> tuple[np.ndarray, np.ndarray]:
        cam = replace(NO_ERRORS, depth_sigma_10m=0.2, depth_systematic=share)
        return tuple(cm.depth_error(v, np.zeros((1, 3)), FORWARD, cam, np.random.default_rng(k), place) - v
                     for k in (1, 2))  # type: ignore[return-value]

    a, b = passes(1.0)
    assert np.allclose(a, b) and np.abs(a).max() > 0.05
    a, b = passes(0.0)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] < 0.5


# -- holes and the whole pipeline -----------------------------------------------------------------
def test_holes_remove_about_their_rate_of_area_and_keep_the_mesh_valid() -> None:
    v, f = _grid(size=40.0)
    total = _areas(v, f).sum()
    labels = np.full(len(f), L["road"])
    cams, rots = np.array([[0.0, 0.0, 1.6]]), FORWARD
    for rate in (0.05, 0.2):
        cam = replace(NO_ERRORS, hole_rate=rate, hole_size_m=1.5)
        lost = []
        for k in range(6):
            mesh = cm.degrade(v, f, labels, cams, rots, cam, np.random.default_rng(k))
            assert mesh.faces.max() == len(mesh.vertices) - 1 and len(np.unique(mesh.faces)) == len(mesh.vertices)
            lost.append(1.0 - _areas(mesh.vertices, mesh.faces).sum() / total)
        assert abs(np.mean(lost) - rate) < 0.4 * rate
    whole = cm.degrade(v, f, labels, cams, rots, NO_ERRORS, np.random.default_rng(0))
    assert np.allclose(whole.vertices, v) and np.array_equal(whole.faces, f)


def test_default_camera_submaps_are_noisier_than_exact_ones_but_on_the_surface(camera_sim, tmp_path) -> None:
    """At its true pose a default camera submap still lies on the world, but less tightly than an exact one."""
    from scipy.spatial import cKDTree

    from fusion.eval.metrics import sample_surface

    out, _ = camera_sim
    gt = load_ground_truth(out)
    tree = cKDTree(sample_surface(gt.vertices, gt.faces, density=50).points)

    def median_distance(sensor: str) -> float:
        records = simulate(tmp_path / sensor, seed=3, sessions=2, world_params=WorldParams(**TINY_WORLD),
                           fleet_params=FleetParams(**TINY_FLEET), sensor=sensor)
        return float(np.median(np.concatenate([tree.query(r.pose_true.apply(r.mesh.vertices[::10]))[0]
                                               for r in records])))

    exact, camera = median_distance("exact"), median_distance("camera")
    assert exact < camera < 0.2


# -- overrides of the camera model and the world (--camera, --world) --------------------------------
def test_camera_and_world_overrides_parse_each_fields_type() -> None:
    from fusion.eval.synth.world import world_overrides

    cam = cm.sensor_model("camera", ["depth_sigma_10m=0.3", "thin_miss=pole:0.2, traffic_sign:0.4",
                                     "confusion=road:sidewalk:0.05"])
    assert isinstance(cam, CameraSensor) and cam.depth_sigma_10m == 0.3 and cam.hfov_deg == CameraSensor().hfov_deg
    assert cam.thin_miss == (("pole", 0.2), ("traffic_sign", 0.4)) and cam.confusion == (("road", "sidewalk", 0.05),)
    world = world_overrides(WorldParams(), ["max_grade=0.1", "junction=t", "n_roads=3", "marking_dash=2,4",
                                            "class_mix=vehicle:2,vegetation:0.5"])
    assert (world.max_grade, world.junction, world.n_roads, world.marking_dash) == (0.1, "t", 3, (2.0, 4.0))
    assert world.class_mix["vehicle"] == 2.0 and world.class_mix["vegetation"] == 0.5
    assert world.class_mix["building"] == 1.0  # a class-mix override merges into the default mix
    assert world_overrides(WorldParams(), ["n_roads=none"]).n_roads is None
    for bad, message in ((["range=20"], "expected KEY=VALUE with KEY a CameraSensor field"),
                         (["thin_miss=polee:0.2"], "is not a valid"), (["hfov_deg=wide"], "is not a valid float")):
        with pytest.raises(ValueError, match=message):
            cm.sensor_model("camera", bad)
    with pytest.raises(ValueError, match="need the camera sensor"):
        cm.sensor_model("exact", ["range_m=30"])
    for bad, message in ((["seed=4"], "set by the command"), (["core_max=10,10"], "set by the command"),
                         (["junction=roundabout"], "expected one of cross, t, random"),
                         (["marking_dash=3"], "is not a valid tuple"), (["class_mix=car:2"], "is not a valid")):
        with pytest.raises(ValueError, match=message):
            world_overrides(WorldParams(), bad)


def test_overrides_reach_the_simulated_fleet_and_world(tmp_path) -> None:
    """A camera that maps only 8 m ahead uploads far less surface than the default's 20 m; the world override
    is what the ground truth records; both are recorded with it."""
    def area(out, **kw) -> float:
        records = simulate(out, seed=3, sessions=2, world_params=WorldParams(**TINY_WORLD),
                           fleet_params=FleetParams(**TINY_FLEET), sensor="camera", **kw)
        return float(sum(_areas(r.mesh.vertices, r.mesh.faces).sum() for r in records))

    default, short = area(tmp_path / "a"), area(tmp_path / "b", camera=["range_m=8"], world=["max_grade=0.08"])
    assert short < 0.6 * default
    info = load_ground_truth(tmp_path / "b").info
    assert info["fleet"]["camera"]["range_m"] == 8.0 and info["world"]["max_grade"] == 0.08
    assert load_ground_truth(tmp_path / "a").info["fleet"]["camera"]["range_m"] == CameraSensor().range_m


def test_a_bad_override_is_one_line_on_the_command_line_and_writes_nothing(tmp_path, capsys) -> None:
    from fusion.eval import cli

    for argv, message in ((["--camera", "depth=0.3"], "fleetmap: error: --camera 'depth=0.3': expected KEY=VALUE"),
                          (["--sensor", "exact", "--camera", "range_m=30"], "fleetmap: error: --camera camera overrides need"),
                          (["--world", "junction=y"], "fleetmap: error: --world junction='y': expected one of")):
        assert cli.main(["simulate", str(tmp_path / "out"), *argv]) == 2
        err = capsys.readouterr().err
        assert err.startswith(message) and err.count("\n") == 1, err
        assert not (tmp_path / "out").exists()
        assert cli.main(["bench", "--tiles", "2", *argv]) == 2
        assert capsys.readouterr().err.startswith(message)
