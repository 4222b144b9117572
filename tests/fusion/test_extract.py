"""Extraction on the global lattice: sphere orientation, narrow band, confidence filter, seams."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.band import narrow_band_sdf, tile_lattice
from fusion.extract import extract_mesh
from fusion.types import TileSpec

CENTRE = np.array([4.0, 4.0, 3.0])


def sphere(x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x - CENTRE, axis=1) - 2.0


def wavy(lift: float = 0.0):  # noqa: ANN201
    def fn(x: np.ndarray) -> np.ndarray:
        return x[:, 2] - (1.0 + lift + 0.4 * np.sin(0.7 * x[:, 0]) + 0.3 * np.cos(1.1 * x[:, 1]))

    return fn


def confident(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.ones(len(x)), np.full(len(x), 5)


def test_sphere_has_outward_normals_and_right_radius() -> None:
    mesh, _, stats = extract_mesh(sphere, confident, TileSpec(0, 0, 8.0), (0.0, 6.0), 0.25)
    v, f = mesh.vertices.astype(np.float64), mesh.faces
    assert len(f) > 500 and stats["band_points"] < np.prod(stats["lattice_shape"])
    assert np.abs(np.linalg.norm(v - CENTRE, axis=1) - 2.0).max() < 0.02
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    outward = np.einsum("ij,ij->i", n, v[f].mean(1) - CENTRE)
    assert (outward > 0).mean() > 0.99
    assert set(np.unique(mesh.vertex_labels)) == {5} and set(np.unique(mesh.face_labels)) == {5}


def test_narrow_band_matches_exact_values_near_the_surface() -> None:
    lat = tile_lattice(TileSpec(0, 0, 8.0), 0.0, 6.0, 0.25)
    vol, mask = narrow_band_sdf(sphere, lat, block=4)
    grid = np.stack(np.meshgrid(*[np.arange(lat.k0[a], lat.k1[a] + 1) for a in range(3)], indexing="ij"), -1)
    exact = sphere(grid.reshape(-1, 3) * 0.25).reshape(vol.shape)
    assert np.allclose(vol[mask], exact[mask])
    assert mask[np.abs(exact) < 0.3].all()  # every point near the surface is exact
    assert (np.sign(vol) == np.sign(exact))[np.abs(exact) > 1e-9].all()


def test_low_confidence_faces_are_dropped() -> None:
    def upper_unsure(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.where(x[:, 2] > 3.0, 0.2, 0.9), np.full(len(x), 2)

    mesh, _, _ = extract_mesh(sphere, upper_unsure, TileSpec(0, 0, 8.0), (0.0, 6.0), 0.25, c_th=0.7)
    assert len(mesh.faces) > 0
    assert mesh.vertices[:, 2].max() <= 3.0 + 0.3
    assert np.all(mesh.vertex_confidence >= 0.7)
    assert len(np.unique(mesh.faces)) == len(mesh.vertices)  # no unreferenced vertices


def _seam(mesh, x: float) -> np.ndarray:  # noqa: ANN001
    v = mesh.vertices[np.abs(mesh.vertices[:, 0] - x) < 1e-6].astype(np.float64)
    return v[np.lexsort((v[:, 2], v[:, 1]))]


def test_adjacent_tiles_of_the_same_field_share_seam_vertices() -> None:
    a, border_a, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    b, _, _ = extract_mesh(wavy(), confident, TileSpec(1, 0, 8.0), (-2.0, 4.0), 0.25)
    assert a.vertices[:, 0].min() >= 0 and a.vertices[:, 0].max() <= 8.0 + 1e-6
    assert b.vertices[:, 0].min() >= 8.0 - 1e-6
    sa, sb = _seam(a, 8.0), _seam(b, 8.0)
    assert len(sa) > 10 and sa.shape == sb.shape
    assert np.abs(sa - sb).max() < 1e-5
    assert border_a["x1"]["k"] == 32 and border_a["x1"]["sdf"].shape[0] == 33


def test_border_pins_make_different_fields_meet() -> None:
    a, border_a, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    b_free, _, _ = extract_mesh(wavy(0.1), confident, TileSpec(1, 0, 8.0), (-2.0, 4.0), 0.25)
    assert np.abs(_seam(a, 8.0)[:, 2].mean() - _seam(b_free, 8.0)[:, 2].mean()) > 0.05
    b, border_b, stats = extract_mesh(wavy(0.1), confident, TileSpec(1, 0, 8.0), (-2.0, 4.0), 0.25,
                                      border_pins=border_a)
    assert stats["pinned"] > 0
    sa, sb = _seam(a, 8.0), _seam(b, 8.0)
    assert sa.shape == sb.shape and np.abs(sa - sb).max() < 1e-5
    assert np.array_equal(border_b["x0"]["sdf"][:, 4:20], border_a["x1"]["sdf"][:, :16]) or stats["pinned"] > 0


def test_centroid_face_labels_keep_a_strip_narrower_than_a_voxel() -> None:
    def flat(x: np.ndarray) -> np.ndarray:
        return x[:, 2] - 1.0

    def strip(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # a 0.1 m wide "lane marking" between lattice columns (voxel 0.25 m): no vertex lies on it
        return np.ones(len(x)), np.where(np.abs(x[:, 0] - 4.125) < 0.05, 3, 1)

    tile = TileSpec(0, 0, 8.0)
    by_vertices, _, _ = extract_mesh(flat, strip, tile, (0.0, 2.0), 0.25)
    by_centroid, _, _ = extract_mesh(flat, strip, tile, (0.0, 2.0), 0.25, face_labels="centroid")
    assert 3 not in set(by_vertices.face_labels.tolist())
    c = by_centroid.vertices[by_centroid.faces].mean(1)
    marked = by_centroid.face_labels == 3
    assert marked.any() and np.all(np.abs(c[marked, 0] - 4.125) < 0.25)


def test_band_limited_marching_cubes_equals_a_full_pass() -> None:
    """Marching cubes restricted to cubes touching exact points (``cube_mask``) finds every triangle a
    full pass over the filled volume finds, on a scene with a thin pole and a sloped ground."""
    from skimage.measure import marching_cubes

    from fusion.band import cube_mask

    def scene(x: np.ndarray) -> np.ndarray:
        ground = x[:, 2] - (0.5 + 0.1 * x[:, 0])
        pole = np.linalg.norm(x[:, :2] - [3.1, 4.2], axis=1) - 0.15
        return np.minimum(np.minimum(ground, np.maximum(pole, x[:, 2] - 4.0)), sphere(x))

    lat = tile_lattice(TileSpec(0, 0, 8.0), -2.0, 10.0, 0.25)
    vol, mask = narrow_band_sdf(scene, lat, block=4, strip_points=5000)  # many strips
    assert 0 < mask.mean() < 0.8
    full_v, full_f, _, _ = marching_cubes(vol, 0.0, allow_degenerate=False)
    band_v, band_f, _, _ = marching_cubes(vol, 0.0, allow_degenerate=False, mask=cube_mask(mask))
    assert len(band_f) == len(full_f)
    key = lambda v, f: np.sort(np.round(v[f].reshape(len(f), -1), 5), axis=0)  # noqa: E731
    assert np.array_equal(key(band_v, band_f), key(full_v, full_f))


def test_half_blocks_evaluate_fewer_points_and_keep_every_triangle() -> None:
    """The band taken again on half blocks (``refine``) evaluates about half the points of whole band blocks
    on a scene with a thin pole, a sloped ground and a sphere, and marching cubes finds the same triangles."""
    from skimage.measure import marching_cubes

    from fusion.band import cube_mask

    def scene(x: np.ndarray) -> np.ndarray:
        ground = x[:, 2] - (0.5 + 0.1 * x[:, 0])
        pole = np.linalg.norm(x[:, :2] - [3.1, 4.2], axis=1) - 0.15
        return np.minimum(np.minimum(ground, np.maximum(pole, x[:, 2] - 4.0)), sphere(x))

    lat = tile_lattice(TileSpec(0, 0, 8.0), -2.0, 10.0, 0.25)
    whole, mask_whole = narrow_band_sdf(scene, lat, block=4, refine=False)
    half, mask_half = narrow_band_sdf(scene, lat, block=4, refine=True)
    assert mask_half.sum() < 0.7 * mask_whole.sum() and not (mask_half & ~mask_whole).any()
    key = lambda v, f: np.sort(np.round(v[f].reshape(len(f), -1), 5), axis=0)  # noqa: E731
    a = marching_cubes(whole, 0.0, allow_degenerate=False, mask=cube_mask(mask_whole))
    b = marching_cubes(half, 0.0, allow_degenerate=False, mask=cube_mask(mask_half))
    assert len(a[1]) > 1000 and np.array_equal(key(a[0], a[1]), key(b[0], b[1]))


def test_strips_do_not_change_the_volume() -> None:
    lat = tile_lattice(TileSpec(0, 0, 8.0), 0.0, 6.0, 0.25)
    one, mask_one = narrow_band_sdf(sphere, lat, block=4)
    many, mask_many = narrow_band_sdf(sphere, lat, block=4, strip_points=3000)
    assert np.array_equal(mask_one, mask_many)
    assert np.allclose(one, many, atol=1e-6)


def test_progress_counts_up_to_its_total() -> None:
    lat = tile_lattice(TileSpec(0, 0, 8.0), 0.0, 6.0, 0.25)
    calls: list[tuple[int, int]] = []
    narrow_band_sdf(sphere, lat, block=4, step=lambda done, total: calls.append((done, total)),
                    strip_points=4000)
    totals = {t for _, t in calls}
    assert len(totals) == 1 and len(calls) == totals.pop() > 2
    assert [d for d, _ in calls] == list(range(1, len(calls) + 1))


def test_pinned_border_confidence_and_labels_make_seams_agree() -> None:
    """Two fields that disagree on confidence and label near their shared border x = 8 m: tile b, pinned
    to tile a, keeps, drops and labels every seam vertex as tile a does (its own field would drop them)."""

    def sure(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.full(len(x), 0.9), np.full(len(x), 1)

    def unsure_near_border(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        conf = np.where((x[:, 0] < 8.6) & (x[:, 1] > 4.0), 0.3, 0.9)  # drops y > 4 along the border
        return conf, np.full(len(x), 2)

    tile_a, tile_b = TileSpec(0, 0, 8.0), TileSpec(1, 0, 8.0)
    a, border_a, _ = extract_mesh(wavy(), sure, tile_a, (-1.0, 3.0), 0.25)
    alone, _, _ = extract_mesh(wavy(0.1), unsure_near_border, tile_b, (-2.0, 4.0), 0.25)
    assert len(_seam(alone, 8.0)) < len(_seam(a, 8.0)) - 10  # without pins the seam has a gap
    b, border_b, stats = extract_mesh(wavy(0.1), unsure_near_border, tile_b, (-2.0, 4.0), 0.25,
                                      border_pins={"x0": border_a["x1"]})
    assert stats["seam_vertices"] > 10
    sa, sb = _seam(a, 8.0), _seam(b, 8.0)
    assert sa.shape == sb.shape and np.abs(sa - sb).max() < 1e-5
    on_b = np.abs(b.vertices[:, 0] - 8.0) < 1e-6
    assert np.all(b.vertex_labels[on_b] == 1) and np.allclose(b.vertex_confidence[on_b], 0.9)
    assert np.all(b.vertex_labels[~on_b] == 2)  # inside tile b its own field rules
    # the pinned values travel on: b's x0 plane now holds a's attributes where a had them
    dz = border_a["x1"]["k0"][1] - border_b["x0"]["k0"][1]  # b's slab starts lower
    overlap = border_b["x0"]["conf"][:, dz : dz + border_a["x1"]["conf"].shape[1]]
    assert np.array_equal(overlap, border_a["x1"]["conf"], equal_nan=True)


def test_borders_without_attributes_still_pin_the_sdf() -> None:
    """Border planes stored before confidence / label pins existed pin the SDF only."""
    a, border_a, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    old = {k: v for k, v in border_a["x1"].items() if k not in ("conf", "label")}
    b, _, stats = extract_mesh(wavy(0.1), confident, TileSpec(1, 0, 8.0), (-2.0, 4.0), 0.25, border_pins=old)
    assert stats["pinned"] > 0
    assert np.abs(_seam(a, 8.0) - _seam(b, 8.0)).max() < 1e-5


def test_surface_far_from_every_input_point_is_dropped_and_seams_still_agree() -> None:
    """A confident field everywhere (as an untrained grid is beyond the data): with support points only on
    the strip x < 5 m, the wavy surface is kept within ``support_m`` of them and nowhere else; the seam
    plane of the neighbour at x = 8 m carries the same zero confidence, so both tiles drop it alike."""
    xy = np.stack(np.meshgrid(np.arange(0.0, 5.0, 0.2), np.arange(0.0, 8.0, 0.2), indexing="ij"), -1).reshape(-1, 2)
    support = np.column_stack([xy, np.zeros(len(xy))])
    support[:, 2] = -wavy()(support)  # on the surface (wavy: s = z - h(x, y))
    full, _, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    kept, border, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25,
                                   support=support, support_m=1.0)
    assert full.vertices[:, 0].max() > 7.9  # without support every confident face stays
    assert 0 < len(kept.faces) < len(full.faces)
    assert kept.vertices[:, 0].max() <= 5.0 + 1.0 + 0.25  # support strip + radius (+ one voxel of faces)
    assert kept.vertices[:, 0].min() < 0.1
    assert np.nanmax(border["x1"]["conf"]) == 0.0  # the seam plane says "no surface" to the neighbour
    b, _, _ = extract_mesh(wavy(), confident, TileSpec(1, 0, 8.0), (-1.0, 3.0), 0.25, border_pins=border)
    assert len(_seam(b, 8.0)) == 0  # the neighbour (confident everywhere itself) drops the seam too


def test_band_skips_blocks_far_from_the_support_and_keeps_the_same_mesh(monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond the data an untrained field sits near zero and crosses it everywhere (here: a small ripple
    for x > 5 m): those blocks would all be in the narrow band. With support points only on x < 4 m, the
    blocks farther from them than any kept face can reach are not evaluated, and the mesh (faces, labels,
    confidence) and the seam planes are the ones the full band gives."""
    xy = np.stack(np.meshgrid(np.arange(0.0, 4.0, 0.2), np.arange(0.0, 16.0, 0.2), indexing="ij"), -1).reshape(-1, 2)
    support = np.column_stack([xy, np.zeros(len(xy))])
    support[:, 2] = -wavy()(support)

    def untrained_beyond(x: np.ndarray) -> np.ndarray:
        ripple = 0.05 * np.sin(3 * x[:, 0]) * np.sin(3 * x[:, 1]) * np.sin(3 * x[:, 2])
        return np.where(x[:, 0] < 5.0, wavy()(x), ripple)

    def run() -> tuple:
        return extract_mesh(untrained_beyond, confident, TileSpec(0, 0, 16.0), (-1.0, 3.0), 0.25,
                            support=support, support_m=1.0)

    mesh, border, stats = run()
    import fusion.extract as ex

    monkeypatch.setattr(ex, "near_support", lambda tree, radius_m, voxel_m: lambda c, h: np.ones(len(c), bool))
    full_mesh, full_border, full_stats = run()
    assert stats["band_points"] < 0.7 * full_stats["band_points"]  # the border planes' blocks stay
    assert stats["raw_faces"] < full_stats["raw_faces"]
    assert len(mesh.faces) > 100 and mesh.vertices[:, 0].max() < 4.0 + 1.0 + 0.25
    for name in ("vertices", "faces", "vertex_labels", "vertex_confidence", "face_labels"):
        assert np.array_equal(getattr(mesh, name), getattr(full_mesh, name)), name
    for plane in border:
        for key in border[plane]:
            assert np.array_equal(np.asarray(border[plane][key]), np.asarray(full_border[plane][key]), equal_nan=True)


def test_pinned_border_outside_our_own_band_still_meets_the_neighbour() -> None:
    """Tile B's field has no surface near the shared border (its coarse pass puts the plane outside its
    narrow band), tile A's has one: with A's pins B still places every seam vertex A has."""
    a, border_a, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    empty = lambda x: np.full(len(x), 5.0)  # noqa: E731
    b, _, stats = extract_mesh(empty, confident, TileSpec(1, 0, 8.0), (-1.0, 3.0), 0.25, border_pins=border_a)
    assert stats["pinned"] > 0
    sa, sb = _seam(a, 8.0), _seam(b, 8.0)
    assert len(sa) > 10 and len(sb) == len(sa)
    assert np.abs(np.sort(sa[:, 1]) - np.sort(sb[:, 1])).max() < 1e-6


def test_tiles_of_different_heights_meet_on_their_shared_plane() -> None:
    """Each tile's height range comes from its own data. A wall crossing the border x = 8 m, tile A spanning
    z ∈ [-1, 2] and tile B z ∈ [-1, 5] (or the other way round): whichever is reconstructed second meets the
    first on the whole shared plane (B fused second drops the seam above A's top, A fused second grows its
    range to B's plane), and away from the border B keeps its full wall."""

    def wall(x: np.ndarray) -> np.ndarray:  # a 0.4 m wall across y = 4 m standing on the ground z = 0.3 m
        return np.minimum(np.abs(x[:, 1] - 4.0) - 0.2, x[:, 2] - 0.3)

    tile_a, tile_b = TileSpec(0, 0, 8.0), TileSpec(1, 0, 8.0)
    for first, second in (((tile_a, (-1.0, 2.0)), (tile_b, (-1.0, 5.0))), ((tile_b, (-1.0, 5.0)), (tile_a, (-1.0, 2.0)))):
        m1, border, _ = extract_mesh(wall, confident, first[0], first[1], 0.25)
        m2, _, _ = extract_mesh(wall, confident, second[0], second[1], 0.25, border_pins=border)
        s1, s2 = _seam(m1, 8.0), _seam(m2, 8.0)
        assert len(s1) > 10 and s1.shape == s2.shape
        assert np.abs(np.sort(s1, axis=0) - np.sort(s2, axis=0)).max() < 1e-5
        b = m1 if first[0] == tile_b else m2
        assert b.vertices[b.vertices[:, 0] > 9.0, 2].max() > 4.9  # B's wall stands to its top inside B


def test_voted_face_labels_take_the_data_majority_near_each_face() -> None:
    """``face_labels="vote"``: a 0.3 m sign the semantic head never predicts (it says road everywhere) is
    labelled from the posed input points near each face; faces with no labelled point near keep the head's."""
    from fusion.extract import voted_labels

    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 4, 4000), rng.uniform(0, 4, 4000), np.zeros(4000)])
    labels = np.where(np.abs(pts[:, 0] - 2.0) < 0.15, 8, 1)  # a 0.3 m strip of class 8 in class-1 ground
    queries = np.array([[2.0, 1.0, 0.0], [0.5, 1.0, 0.0], [2.0, 3.0, 0.05], [9.0, 9.0, 0.0]])
    head = np.array([1, 1, 1, 4])
    out = voted_labels(queries, head, pts, labels)
    assert out.tolist() == [8, 1, 8, 4]  # the strip, the ground, the strip again, no data near: the head's
    unlabelled = voted_labels(queries[:1], head[:1], pts, np.zeros(len(pts), np.int64))
    assert unlabelled.tolist() == [1]  # label 0 does not vote
    mesh, _, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25, face_labels="vote",
                              support=np.column_stack([pts[:, :2] * 2, -wavy()(np.column_stack([pts[:, :2] * 2, pts[:, 2]]))]),
                              support_m=1.0, support_labels=labels)
    assert set(np.unique(mesh.face_labels)) <= {1, 8} and (mesh.face_labels == 8).any()


def test_thin_faces_move_back_in_by_the_inflation_and_seams_stay() -> None:
    """``deflate_labels``: a wall the field holds 0.25 m out on each side (a 0.3 m pole's samples inflated by
    0.1 m) is reported 0.15 m out once its faces move 0.1 m in; the ground's faces and every vertex on the
    tile's border planes (where the wall crosses them) stay where they were."""

    def ground_and_wall(x: np.ndarray) -> np.ndarray:
        wall = np.maximum(np.abs(x[:, 1] - 4.0) - 0.25, x[:, 2] - 3.0)
        return np.minimum(x[:, 2] - 0.5, wall)

    def wall_is_a_pole(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(len(x)), np.where((np.abs(x[:, 1] - 4.0) < 0.4) & (x[:, 2] > 0.7), 7, 1)

    tile = TileSpec(0, 0, 8.0)
    plain, _, _ = extract_mesh(ground_and_wall, wall_is_a_pole, tile, (0.0, 4.0), 0.1, face_labels="centroid")
    thin, _, _ = extract_mesh(ground_and_wall, wall_is_a_pole, tile, (0.0, 4.0), 0.1, face_labels="centroid",
                              deflate_labels=[7], deflate_m=0.1)
    assert np.array_equal(plain.faces, thin.faces) and np.array_equal(plain.face_labels, thin.face_labels)
    v0, v1 = plain.vertices.astype(np.float64), thin.vertices.astype(np.float64)
    side = (v0[:, 2] > 1.2) & (v0[:, 2] < 2.5) & (v0[:, 0] > 0.5) & (v0[:, 0] < 7.5)
    assert side.sum() > 100
    assert np.abs(np.abs(v0[side, 1] - 4.0) - 0.25).max() < 0.02
    assert np.abs(np.abs(v1[side, 1] - 4.0) - 0.15).max() < 0.02
    assert np.allclose(v1[side][:, [0, 2]], v0[side][:, [0, 2]], atol=0.02)  # in along the normal, not up
    ground = np.abs(v0[:, 1] - 4.0) > 1.0
    assert np.array_equal(v0[ground], v1[ground])
    border = (np.abs(v0[:, 0]) < 1e-6) | (np.abs(v0[:, 0] - 8.0) < 1e-6)
    assert (border & (np.abs(v0[:, 1] - 4.0) < 0.3)).any() and np.array_equal(v0[border], v1[border])


def test_faces_on_a_class_boundary_split_and_follow_a_strip_narrower_than_a_voxel() -> None:
    def flat(x: np.ndarray) -> np.ndarray:
        return x[:, 2] - 1.1

    def strip(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # a 0.15 m "lane marking" inside one 0.25 m lattice column
        return np.ones(len(x)), np.where((x[:, 0] >= 4.0) & (x[:, 0] < 4.15), 3, 1)

    def precision_recall(mesh) -> tuple[float, float]:  # noqa: ANN001
        v, f = mesh.vertices.astype(np.float64), mesh.faces
        w = np.random.default_rng(0).dirichlet(np.ones(3), size=(len(f), 16))
        x = np.einsum("fkj,fjd->fkd", w, v[f])[..., 0]
        area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)[:, None]
        on, marked = (x >= 4.0) & (x < 4.15), (mesh.face_labels == 3)[:, None]
        hit = (area * (on & marked)).sum()
        return hit / (area * marked).sum(), hit / (area * on).sum()

    tile = TileSpec(0, 0, 8.0)
    plain, _, _ = extract_mesh(flat, strip, tile, (0.0, 2.0), 0.25, face_labels="centroid")
    split, _, stats = extract_mesh(flat, strip, tile, (0.0, 2.0), 0.25, face_labels="centroid", split_labels=True)
    (p0, r0), (p1, r1) = precision_recall(plain), precision_recall(split)
    assert p1 > p0 + 0.1 and r1 > r0 + 0.1, (p0, r0, p1, r1)
    # only the boundary faces split (one column of cells along the strip), the surface is unchanged
    assert 0 < stats["split_faces"] <= 4 * 32
    assert len(split.faces) == len(plain.faces) + 3 * stats["split_faces"]
    assert np.allclose(split.vertices[:, 2], 1.1, atol=1e-5)
    def area(mesh) -> float:  # noqa: ANN001
        a, b, c = (mesh.vertices[mesh.faces[:, k]].astype(np.float64) for k in range(3))
        return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2)

    assert area(split) == pytest.approx(area(plain), rel=1e-6)
    assert len(split.vertex_labels) == len(split.vertices) == len(split.vertex_confidence)


def _quad_grid(x0: float, x1: float, y0: float, y1: float, z: float, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A flat square grid of triangles at height ``z`` (an upload's surface)."""
    xs, ys = np.meshgrid(np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1), indexing="ij")
    v = np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])
    k = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = k.ravel(), k.ravel() + n + 1, k.ravel() + n + 2, k.ravel() + 1
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def test_upload_faces_the_field_lost_join_the_mesh_where_it_is_confident() -> None:
    """The field holds the ground (z = 1) only. The uploads have the ground too (on the field's surface: not
    added), a small plate 1.5 m above it in a confident place (added, as measured, labelled there), one in an
    unconfident place (a car the consensus dropped: not added), and one across the tile border (its faces go
    to the tile their centre lies in, so the two tiles never both hold one)."""
    def flat(x: np.ndarray) -> np.ndarray:
        return x[:, 2] - 1.0

    def attrs(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        unsure = (np.abs(x[:, 0] - 6.2) < 0.5) & (np.abs(x[:, 1] - 6.2) < 0.5) & (x[:, 2] > 2.0)
        return np.where(unsure, 0.1, 0.9), np.where(x[:, 2] > 2.0, 7, 1)

    pieces = [_quad_grid(0.5, 7.5, 0.5, 7.5, 1.0, 16), _quad_grid(2.0, 2.4, 2.0, 2.4, 2.5, 2),
              _quad_grid(6.0, 6.4, 6.0, 6.4, 2.5, 2), _quad_grid(7.8, 8.2, 3.0, 3.4, 2.5, 4)]
    offsets = np.cumsum([0] + [len(v) for v, _ in pieces[:-1]])
    detail = (np.concatenate([v for v, _ in pieces]), np.concatenate([f + o for (_, f), o in zip(pieces, offsets, strict=True)]))
    tile = TileSpec(0, 0, 8.0)
    plain, _, _ = extract_mesh(flat, attrs, tile, (0.0, 3.0), 0.25, face_labels="centroid")
    mesh, _, stats = extract_mesh(flat, attrs, tile, (0.0, 3.0), 0.25, face_labels="centroid", detail=detail,
                                  detail_m=0.4)
    right, _, right_stats = extract_mesh(flat, attrs, TileSpec(1, 0, 8.0), (0.0, 3.0), 0.25, face_labels="centroid",
                                         detail=detail, detail_m=0.4)
    added = mesh.vertices[mesh.faces[len(plain.faces):]].mean(axis=1)
    assert np.array_equal(mesh.faces[:len(plain.faces)], plain.faces)  # the field's mesh is unchanged
    plate = (np.abs(added[:, 0] - 2.2) < 0.3) & (np.abs(added[:, 1] - 2.2) < 0.3)
    border = np.abs(added[:, 0] - 8.0) < 0.3
    assert plate.sum() == 8 and np.all(np.abs(added[:, 2] - 2.5) < 1e-6)  # every face of the plate, where it was
    assert plate.sum() + border.sum() == stats["detail_faces"] == len(added)  # no ground, no unconfident plate
    assert np.all(mesh.face_labels[len(plain.faces):] == 7)
    assert np.all(mesh.vertex_confidence[len(plain.vertices):] >= 0.7)
    assert np.all(added[border, 0] < 8.0) and border.sum() == 16  # the border plate's left half here ...
    right_added = right.vertices[right.faces[-right_stats["detail_faces"]:]].mean(axis=1)
    assert right_stats["detail_faces"] == 16 and np.all(right_added[:, 0] >= 8.0)  # ... its right half there
    off, _, off_stats = extract_mesh(flat, attrs, tile, (0.0, 3.0), 0.25, face_labels="centroid", detail=detail,
                                     detail_m=0.0)
    assert len(off.faces) == len(plain.faces) and "detail_faces" not in off_stats


def test_upload_detail_joins_a_tile_where_the_field_left_no_surface() -> None:
    """A tile whose field holds no surface at all (free space everywhere, confident) still gets the upload faces
    of a plate the field did not form; with detail off it stays empty."""
    def free(x: np.ndarray) -> np.ndarray:
        return np.full(len(x), 5.0)

    def attrs(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.full(len(x), 0.9), np.full(len(x), 7)

    detail = _quad_grid(2.0, 2.4, 2.0, 2.4, 2.5, 2)
    tile = TileSpec(0, 0, 8.0)
    empty, _, _ = extract_mesh(free, attrs, tile, (0.0, 3.0), 0.25, face_labels="centroid")
    mesh, _, stats = extract_mesh(free, attrs, tile, (0.0, 3.0), 0.25, face_labels="centroid", detail=detail,
                                  detail_m=0.4)
    assert len(empty.faces) == 0
    assert stats["detail_faces"] == len(mesh.faces) == 8 and np.all(mesh.face_labels == 7)
    assert np.allclose(np.sort(mesh.vertices, axis=0), np.sort(detail[0].astype(np.float32), axis=0))


def test_detail_faces_are_those_farther_than_the_gap_from_the_dense_surface_samples() -> None:
    """The upload faces ``detail_faces`` picks are exactly those whose centre has no sample of the field's
    whole mesh (``surface_samples`` at a third of the gap) within the gap, though it samples only the mesh
    faces within reach of centres with no mesh vertex that close."""
    from scipy.spatial import cKDTree

    from fusion.extract import detail_faces, surface_samples

    mesh, _, _ = extract_mesh(wavy(), confident, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.25)
    v, f = mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)
    rng = np.random.default_rng(3)
    centres = np.column_stack([rng.uniform(0, 8, 3000), rng.uniform(0, 8, 3000), np.zeros(3000)])
    centres[:, 2] = -wavy()(np.column_stack([centres[:, :2], np.zeros(3000)])) + rng.uniform(-0.8, 0.8, 3000)
    tiny = np.array([[0.0, 0, 0], [0.02, 0, 0], [0, 0.02, 0]])
    up_v = (centres[:, None, :] + tiny).reshape(-1, 3)
    up_f = np.arange(len(up_v)).reshape(-1, 3)
    got = detail_faces(v, f, up_v, up_f, TileSpec(0, 0, 8.0), (-1.0, 3.0), 0.4, 0.25)
    c = up_v[up_f].mean(axis=1)
    dense = cKDTree(surface_samples(v, f, 0.4 / 3, 0.25 * np.sqrt(2))).query(c, distance_upper_bound=0.4)[0]
    inside = (c[:, 0] < 8.0) & (c[:, 1] < 8.0)
    want = np.flatnonzero(inside & ~np.isfinite(dense))
    assert 100 < len(want) < 2500 and np.array_equal(np.sort(got), want)


def test_labels_that_contradict_the_geometry_take_the_heads_best_other_label() -> None:
    """Ground at z = 1 with a 0.3 m kerb at x = 6.1, a 0.8 m pillar from the ground to z = 3 at (3, 4). The head
    calls the pillar's lower part sidewalk (a pole the segmenter missed: its second choice is pole) and a level
    strip of the ground building (a wall's class bled onto the pavement: second choice sidewalk). With the
    relabelling the raised steep sidewalk faces become pole, the level building faces at ground height
    sidewalk; the kerb's steep faces (raised only 0.3 m) and the pillar's foot stay sidewalk, its top pole."""
    sidewalk, building, pole = 2, 5, 7

    def sdf(x: np.ndarray) -> np.ndarray:
        ground = x[:, 2] - np.where(x[:, 0] > 6.1, 1.3, 1.0)
        d = np.abs(x - np.array([3.0, 4.0, 2.0])) - np.array([0.4, 0.4, 1.0])
        pillar = np.linalg.norm(np.maximum(d, 0), axis=1) + np.minimum(d.max(axis=1), 0)
        return np.minimum(ground, pillar)

    def logits(x: np.ndarray) -> np.ndarray:
        out = np.zeros((len(x), 12))
        on_pillar = (np.abs(x[:, 0] - 3.0) < 0.6) & (np.abs(x[:, 1] - 4.0) < 0.6) & (x[:, 2] > 1.1)
        strip = (x[:, 0] > 1.0) & (x[:, 0] < 2.0) & ~on_pillar
        out[:, sidewalk] = 3.0
        out[:, pole] = np.where(on_pillar, np.where(x[:, 2] > 2.5, 4.0, 2.0), 0.0)
        out[:, building] = np.where(strip, 4.0, 1.0)
        return out

    def attrs(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.ones(len(x)), logits(x).argmax(axis=1)

    def label_among(x: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        return np.where(allowed, logits(x), -np.inf).argmax(axis=1)

    tile = TileSpec(0, 0, 8.0)
    plain, _, _ = extract_mesh(sdf, attrs, tile, (0.0, 4.0), 0.25, face_labels="centroid")
    mesh, _, stats = extract_mesh(sdf, attrs, tile, (0.0, 4.0), 0.25, face_labels="centroid",
                                  relabel=([1, 2, 3, 4], label_among, 12))
    assert np.array_equal(mesh.faces, plain.faces)  # labels only
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    c = tri.mean(axis=1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    steep = np.abs(n[:, 2]) < 0.5 * np.linalg.norm(n, axis=1)
    pillar = (np.abs(c[:, 0] - 3.0) < 0.6) & (np.abs(c[:, 1] - 4.0) < 0.6) & (c[:, 2] > 1.1)
    sides_low = pillar & steep & (c[:, 2] > 1.5) & (c[:, 2] < 2.4)
    assert sides_low.sum() > 20 and np.all(plain.face_labels[sides_low] == sidewalk)
    assert np.all(mesh.face_labels[sides_low] == pole)
    foot = pillar & steep & (c[:, 2] < 1.3)
    assert foot.any() and np.all(mesh.face_labels[foot] == sidewalk)
    assert np.all(mesh.face_labels[pillar & (c[:, 2] > 2.9)] == pole)
    strip = (c[:, 0] > 1.1) & (c[:, 0] < 1.9) & ~steep
    assert strip.sum() > 20 and np.all(plain.face_labels[strip] == building)
    assert np.all(mesh.face_labels[strip] == sidewalk)
    kerb = (np.abs(c[:, 0] - 6.1) < 0.3) & (np.abs(n[:, 2]) < 0.7 * np.linalg.norm(n, axis=1))
    assert kerb.any() and np.all(mesh.face_labels[kerb] == sidewalk)
    assert stats["relabelled_faces"] == int((mesh.face_labels != plain.face_labels).sum())
