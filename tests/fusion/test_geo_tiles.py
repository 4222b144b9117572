"""fusion.geo (geodetic ↔ map frame) and fusion.tiles (tile maths, extraction lattice)."""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest

from fusion.errors import PoseError
from fusion.geo import geodetic_to_map, map_to_geodetic, parse_origin
from fusion.tiles import (
    border_pins,
    home_tile,
    lattice_range,
    posed_bbox,
    submap_tiles,
    surface_tiles,
    tile_bounds,
    tile_of,
    tiles_for_box,
)
from fusion.types import Pose, SemanticMesh, Sigma, matrix_to_quat, quat_to_matrix

ORIGIN = (48.2620, 11.6670, 480.0)
IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def yaw(degrees: float) -> np.ndarray:
    half = math.radians(degrees) / 2
    return np.array([math.cos(half), 0.0, 0.0, math.sin(half)])


# ------------------------------------------------------------------------------------------ geo


def test_parse_origin() -> None:
    assert parse_origin("48.2620,11.6670,480.0") == ORIGIN
    assert parse_origin(" -33.9 , 151.2 , 0 ") == (-33.9, 151.2, 0.0)
    for bad in ("48.2,11.6", "a,b,c", "91,0,0", "0,181,0", "nan,0,0", ""):
        with pytest.raises(ValueError):
            parse_origin(bad)


def test_origin_maps_to_zero() -> None:
    pose = geodetic_to_map(*ORIGIN, IDENTITY_Q, ORIGIN)
    np.testing.assert_allclose(pose.t, 0.0, atol=1e-6)
    np.testing.assert_allclose(pose.q, IDENTITY_Q, atol=1e-12)


def test_point_100_m_east() -> None:
    lat, lon, alt = pymap3d.enu2geodetic(100.0, 0.0, 0.0, *ORIGIN)
    pose = geodetic_to_map(lat, lon, alt, yaw(30), ORIGIN)
    np.testing.assert_allclose(pose.t, [100.0, 0.0, 0.0], atol=1e-6)
    # 100 m away the ENU axes differ by ~1e-5 rad: the heading survives almost unchanged
    assert abs(np.dot(pose.q, yaw(30))) > 1 - 1e-8


def test_local_enu_axes_are_rotated_into_the_map_frame() -> None:
    lat, lon, alt = pymap3d.enu2geodetic(100_000.0, 0.0, 0.0, *ORIGIN)
    pose = geodetic_to_map(lat, lon, alt, IDENTITY_Q, ORIGIN)
    up_there = pose.rotation() @ [0.0, 0.0, 1.0]
    # the local vertical 100 km east leans east by ~0.9° (100 km / earth radius)
    assert up_there[0] == pytest.approx(math.sin(100_000 / 6_371_000), rel=0.02)
    # and the ECEF direction of "up" there, seen from the origin's ENU, agrees with pymap3d
    expected = np.array(pymap3d.ecef2enuv(*pymap3d.enu2uvw(0, 0, 1, lat, lon), ORIGIN[0], ORIGIN[1]))
    np.testing.assert_allclose(up_there, expected, atol=1e-12)


def test_geodetic_round_trip() -> None:
    q = matrix_to_quat(quat_to_matrix(yaw(-70)) @ quat_to_matrix(np.array([0.99, 0.1, 0.0, 0.0]) / 0.995))
    lat, lon, alt = pymap3d.enu2geodetic(-3000.0, 1500.0, 20.0, *ORIGIN)
    pose = geodetic_to_map(lat, lon, alt, q, ORIGIN)
    back_lat, back_lon, back_alt, back_q = map_to_geodetic(pose, ORIGIN)
    assert (back_lat, back_lon) == pytest.approx((lat, lon), abs=1e-9)
    assert back_alt == pytest.approx(alt, abs=1e-4)
    assert abs(np.dot(back_q, q)) == pytest.approx(1.0, abs=1e-12)


def test_geodetic_quaternion_validation() -> None:
    pose = geodetic_to_map(*ORIGIN, np.array([1.0005, 0.0, 0.0, 0.0]), ORIGIN)  # normalised
    assert np.linalg.norm(pose.q) == pytest.approx(1.0)
    with pytest.raises(PoseError):
        geodetic_to_map(*ORIGIN, np.array([2.0, 0.0, 0.0, 0.0]), ORIGIN)
    with pytest.raises(PoseError):
        geodetic_to_map(*ORIGIN, np.array([np.nan, 0.0, 0.0, 0.0]), ORIGIN)
    with pytest.raises(PoseError):
        geodetic_to_map(95.0, 0.0, 0.0, IDENTITY_Q, ORIGIN)


# ------------------------------------------------------------------------------------------ tiles


def test_tile_of_floor_division_and_borders() -> None:
    assert tile_of(0.0, 0.0, 64) == (0, 0)
    assert tile_of(63.999, 64.0, 64) == (0, 1)
    assert tile_of(-0.001, -64.0, 64) == (-1, -1)
    assert tile_of(-64.001, 130.0, 64) == (-2, 2)
    with pytest.raises(ValueError):
        tile_of(0.0, 0.0, 0)


def test_tile_bounds() -> None:
    assert tile_bounds(-2, 3, 64) == ((-128, 192), (-64, 256))
    (x0, y0), _ = tile_bounds(-2, 3, 64)
    assert tile_of(x0, y0, 64) == (-2, 3)


def test_tiles_for_box_half_open() -> None:
    assert tiles_for_box((1, 1), (10, 10), 64) == [(0, 0)]
    # max side exactly on x = 64 touches tile 1; min side exactly on 0 stays in tile 0
    assert tiles_for_box((0, 0), (64, 10), 64) == [(0, 0), (1, 0)]
    assert tiles_for_box((-1, -65), (1, -64), 64) == [(-1, -2), (-1, -1), (0, -2), (0, -1)]
    with pytest.raises(ValueError):
        tiles_for_box((5, 5), (1, 1), 64)


def test_posed_bbox_transforms_corners() -> None:
    pose = Pose(np.array([100.0, -50.0, 2.0]), yaw(90))
    lo, hi = posed_bbox(np.array([0.0, 0.0, 0.0]), np.array([10.0, 2.0, 1.0]), pose)
    np.testing.assert_allclose(lo, [98.0, -50.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(hi, [100.0, -40.0, 3.0], atol=1e-9)


def test_submap_tiles_grow_by_uncertainty() -> None:
    lo, hi = np.array([-5.0, -5.0, 0.0]), np.array([5.0, 5.0, 2.0])
    pose = Pose(np.array([32.0, 32.0, 0.0]), IDENTITY_Q)
    assert submap_tiles(lo, hi, pose, Sigma(0.0, 0.0), 64) == [(0, 0)]
    # translation sigma alone grows [27, 37] to [0, 64]: x = 64 touches tile 1 (half-open tiles)
    assert submap_tiles(lo, hi, pose, Sigma(27.0, 0.0), 64) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert submap_tiles(lo, hi, pose, Sigma(27.5, 0.0), 64) == [
        (i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)
    ]
    assert submap_tiles(lo, hi, pose, Sigma(26.9, 0.0), 64) == [(0, 0)]
    # rotation sigma: a lever of |corner| = 7.3 m over 180° sweeps 14.6 m; over 2° about 0.25 m
    near_border = Pose(np.array([58.9, 32.0, 0.0]), IDENTITY_Q)
    assert submap_tiles(lo, hi, near_border, Sigma(0.0, 0.0), 64) == [(0, 0)]
    assert submap_tiles(lo, hi, near_border, Sigma(0.0, 2.0), 64) == [(0, 0), (1, 0)]


def test_surface_tiles_follow_the_posed_faces_not_the_box() -> None:
    # an L of two thin strips: its bounding box covers tile (1, 1), its faces do not come near it
    v = np.array([[0, 0, 0], [100, 0, 0], [100, 2, 0], [0, 2, 0], [0, 2, 0], [2, 2, 0], [2, 100, 0], [0, 100, 0]],
                 dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    at = Pose(np.array([10.0, 10.0, 0.0]), IDENTITY_Q)  # strips along y = 10..12 and x = 10..12
    lo, hi = posed_bbox(v.min(0), v.max(0), at)
    assert (1, 1) in tiles_for_box(lo[:2], hi[:2], 64)
    assert surface_tiles(v, f, at, 64) == [(0, 0), (0, 1), (1, 0)]
    # a band reaches a tile only when the faces come within it of the tile's square
    near = Pose(np.array([10.0, 60.0, 0.0]), IDENTITY_Q)  # the x strip at y = 60..62, 2 m below tile row 1
    assert (1, 1) not in surface_tiles(v, f, near, 64, band_m=1.9)
    assert (1, 1) in surface_tiles(v, f, near, 64, band_m=2.1)
    # the pose moves the surface: turned by 180° about z the strips lie in negative x and y
    assert surface_tiles(v, f, Pose(np.array([-1.0, -1.0, 0.0]), yaw(180)), 64) == [(-2, -1), (-1, -2), (-1, -1)]
    # one big face over a tile corner reaches all four tiles, and every tile its box spans
    big = np.array([[60, 60, 0], [70, 60, 0], [60, 200, 0]], dtype=float)
    assert surface_tiles(big, np.array([[0, 1, 2]]), Pose(np.zeros(3), IDENTITY_Q), 64) == [
        (0, 0), (0, 1), (0, 2), (0, 3), (1, 0), (1, 1), (1, 2), (1, 3)]
    assert surface_tiles(v, f[:0], at, 64) == []
    # a band wider than a tile reaches the tiles beyond the next one too
    assert surface_tiles(big, np.array([[0, 1, 2]]), Pose(np.zeros(3), IDENTITY_Q), 64, band_m=70.0) == [
        (i, j) for i in range(-1, 3) for j in range(-1, 5)]
    with pytest.raises(ValueError, match="band"):
        surface_tiles(v, f, at, 64, band_m=-1.0)


def test_surface_tiles_are_every_tile_some_face_box_meets() -> None:
    # the definition face by face, on faces of all sizes scattered over negative and positive tiles
    rng = np.random.default_rng(3)
    centres = rng.uniform(-150, 150, (400, 1, 3))
    v = (centres + rng.normal(0, 1, (400, 3, 3)) * rng.choice([0.5, 5.0, 40.0], (400, 1, 1))).reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    pose = Pose(np.array([3.0, -7.0, 1.0]), yaw(30))
    xy = pose.apply(v)[:, :2][f]
    for band in (0.0, 2.0):
        lo = np.floor((xy.min(axis=1) - band) / 64).astype(int)
        hi = np.floor((xy.max(axis=1) + band) / 64).astype(int)
        want = {(i, j) for a, b in zip(lo, hi, strict=True)
                for i in range(a[0], b[0] + 1) for j in range(a[1], b[1] + 1)}
        assert surface_tiles(v, f, pose, 64, band_m=band) == sorted(want)


def test_home_tile_of_posed_centre() -> None:
    mesh = SemanticMesh(
        vertices=np.array([[0.0, 0.0, 0.0], [10.0, 4.0, 1.0], [2.0, 2.0, 0.0]]),
        faces=np.array([[0, 1, 2]]),
        face_labels=np.array([1]),
    )
    pose = Pose(np.array([-3.0, 60.0, 0.0]), IDENTITY_Q)  # centre (5, 2) -> (2, 62)
    assert home_tile(mesh, pose, 64) == (0, 0)
    assert home_tile((np.zeros(3), np.array([10.0, 4.0, 1.0])), pose, 64) == (0, 0)
    assert home_tile(np.array([5.0, 4.5, 0.0]), pose, 64) == (0, 1)
    turned = Pose(np.array([-3.0, 60.0, 0.0]), yaw(180))  # centre (5, 2) -> (-8, 58)
    assert home_tile(mesh, turned, 64) == (-1, 0)


def test_lattice_range_multiples_of_step() -> None:
    assert lattice_range(0.0, 64.0, 0.2) == (0, 320)  # 64 / 0.2 is 320.00000000000006
    assert lattice_range(0.0, 64.0, 0.2, inside=True) == (0, 320)
    assert lattice_range(-64.0, 0.0, 0.2) == (-320, 0)  # neighbours share the border point
    assert lattice_range(-12.8, 0.0, 0.2)[0] == -64


def test_lattice_range_covers_or_stays_inside_non_multiples() -> None:
    assert lattice_range(0.05, 0.95, 0.2) == (0, 5)
    assert lattice_range(0.05, 0.95, 0.2, inside=True) == (1, 4)
    assert lattice_range(-0.3, -0.1, 0.1) == (-3, -1)
    assert lattice_range(1.0, 1.0, 0.5) == (2, 2)
    with pytest.raises(ValueError):
        lattice_range(0.0, 1.0, 0.0)
    with pytest.raises(ValueError):
        lattice_range(2.0, 1.0, 0.1)


def test_border_pins_take_the_neighbours_opposite_side() -> None:
    borders = {(1, 0): {"x0": "left plane of (1, 0)", "x1": "right"}, (0, -1): {"y1": "top of (0, -1)"}}
    assert border_pins(0, 0, borders.get) == {"x1": "left plane of (1, 0)", "y0": "top of (0, -1)"}
    assert border_pins(5, 5, borders.get) == {}
