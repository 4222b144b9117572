"""Surface pool sampling (area weighting, tile box) and cross-session consensus targets (confidence
supervision: transient objects, occluded road, facades)."""

from __future__ import annotations

import numpy as np
import torch

from fusion.sampling import calibrated_confidence, consensus_targets, sample_surface_pool
from fusion.types import Pose, SemanticMesh, SubmapInput


def _plane(rng: np.random.Generator, x: tuple[float, float], y: tuple[float, float], z: float, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(*x, n), rng.uniform(*y, n), np.full(n, z)])


class _Scene:
    """Pool points of several sessions, added piece by piece: their positions, posed normals, sessions and
    whether they are of a movable class."""

    def __init__(self) -> None:
        self.pts: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.sess: list[np.ndarray] = []
        self.mov: list[np.ndarray] = []

    def add(self, p: np.ndarray, n: tuple[float, float, float], s: int, movable: bool = False) -> None:
        self.pts.append(p)
        self.nrm.append(np.tile(n, (len(p), 1)))
        self.sess.append(np.full(len(p), s))
        self.mov.append(np.full(len(p), movable))

    def __len__(self) -> int:
        return sum(len(p) for p in self.pts)

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(points, normals, sessions, movable)."""
        return (torch.tensor(np.concatenate(self.pts), dtype=torch.float32),
                torch.tensor(np.concatenate(self.nrm), dtype=torch.float32),
                torch.tensor(np.concatenate(self.sess)), torch.tensor(np.concatenate(self.mov)))


def test_consensus_separates_transients_from_the_static_world() -> None:
    rng = np.random.default_rng(0)
    pts, sess = [], []
    for s in range(5):  # five sessions drive the same 40 m street
        road = _plane(rng, (0, 40), (0, 8), 0.0, 4000)
        pts.append(road)
        sess.append(np.full(len(road), s))
    car = np.column_stack([rng.uniform(10, 14, 400), rng.uniform(2, 4, 400), rng.uniform(1.0, 2.0, 400)])
    pts.append(car)  # a parked car only session 0 saw
    sess.append(np.zeros(len(car), int))
    facade = np.column_stack([rng.uniform(0, 40, 8000), np.full(8000, 30.0), rng.uniform(0, 10, 8000)])
    pts.append(facade)  # a facade far from the street, seen by sessions 3 and 4 only
    sess.append(np.where(rng.random(8000) < 0.5, 3, 4))
    p = torch.tensor(np.concatenate(pts), dtype=torch.float32)
    s = torch.tensor(np.concatenate(sess))
    target = consensus_targets(p, s, near_m=0.5, cover_m=2.5).numpy()
    assert target.shape == (len(p),) and target.dtype == np.float32
    n_road = 5 * 4000
    road, car_t, fac = target[:n_road], target[n_road : n_road + 400], target[n_road + 400 :]
    road_xy = p[:n_road, :2].numpy()
    far_from_car = (np.abs(road_xy[:, 0] - 12) > 5) | (np.abs(road_xy[:, 1] - 3) > 4)
    assert road[far_from_car].mean() > 0.99  # everybody saw it
    assert np.abs(car_t - 0.2).max() < 1e-6  # one of the five sessions that covered it
    assert fac.min() == 1.0  # only its observers covered it
    assert 0.2 < target.mean() < 1.0


def test_free_space_evidence_counts_only_the_sessions_that_saw_through_a_surface() -> None:
    """Five sessions on one street. Session 0 alone saw a parked car (the others saw bare road there) and
    the whole of a 6 m wall at the street's edge; sessions 1-2 saw its lower 2 m only (a camera's vertical
    field of view), 3-4 nothing of it (their pavement ends 2 m short). The neighbourhood rule votes part of
    the wall down (covering sessions missed it); free-space evidence keeps all of it (nobody saw through
    it) and still drops the car."""
    rng = np.random.default_rng(3)
    scene = _Scene()
    add = scene.add
    for s in range(5):
        add(_plane(rng, (0, 40), (0, 8 if s < 3 else 6), 0.0, 4000), (0, 0, 1), s)
    car_top = _plane(rng, (10, 14), (2, 4), 1.6, 300)
    car_side = np.column_stack([rng.uniform(10, 14, 300), np.full(300, 2.0), rng.uniform(0.8, 1.6, 300)])
    add(car_top, (0, 0, 1), 0)
    add(car_side, (0, -1, 0), 0)
    wall_top = 6.0
    for s, top in ((0, wall_top), (1, 2.0), (2, 2.0)):
        add(np.column_stack([rng.uniform(0, 40, 3000), np.full(3000, 8.0), rng.uniform(0, top, 3000)]), (0, -1, 0), s)
    p, n, s, _ = scene.tensors()
    n_road = 5 * 4000
    car = slice(n_road, n_road + 600)
    wall0 = slice(n_road + 600, n_road + 3600)
    band = torch.zeros(len(p), dtype=torch.bool)
    band[wall0] = (p[wall0, 2] > 3.0) & (p[wall0, 2] < 4.5)  # above what 1-2 saw, within the others' cover

    free = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0)
    cover = consensus_targets(p, s, 0.5, 2.5)
    assert free[car].max() <= 0.2 + 1e-6  # four sessions saw bare road where it stood
    assert cover[band].max() < 0.7 and free[wall0].min() == 1.0
    road_xy = p[:n_road, :2]
    under_car = (road_xy[:, 0] > 10.5) & (road_xy[:, 0] < 13.5) & (road_xy[:, 1] > 2.5) & (road_xy[:, 1] < 3.5)
    assert free[:n_road][under_car].min() == 1.0  # the car's owner had nothing below it: no say
    # without the column (column_m tiny) nobody has evidence against anything: every target is 1
    assert consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=0.1).min() == 1.0


def test_what_overhangs_open_ground_is_not_seen_through() -> None:
    """Five sessions on one street. Session 0 alone saw a sign plate 2.2-2.8 m up beside its post, and the
    road beneath it (its rays passed under the plate, as the others' did), and a parked car: its roof, the
    side facing the street and its two ends reaching down to 0.25 m above the road, and no road under or
    behind it. The others saw bare road there. Plain free-space evidence drops the plate with the car; with
    ``overhang_m`` the plate keeps its 1 (its observer saw open ground 2 m under it) and the car is still
    dropped: its observer saw no ground under it, and its sides reach down to the road. Only a band of the
    roof along its edges, where the observer's road lies within a cell of a column that holds no point of
    the car's sides (sampling), passes for an overhang."""
    rng = np.random.default_rng(11)
    scene = _Scene()
    add = scene.add
    road0 = _plane(rng, (0, 40), (0, 8), 0.0, 8000)
    add(road0[~((road0[:, 0] > 10) & (road0[:, 0] < 14) & (road0[:, 1] > 2))], (0, 0, 1), 0)  # the car's shadow
    for s in range(1, 5):
        add(_plane(rng, (0, 40), (0, 8), 0.0, 4000), (0, 0, 1), s)
    n_before = len(scene)
    plate = np.column_stack([rng.uniform(25, 25.8, 300), np.full(300, 6.0), rng.uniform(2.2, 2.8, 300)])
    add(plate, (0, -1, 0), 0)
    add(np.column_stack([np.full(100, 25.4), np.full(100, 6.05), rng.uniform(0, 2.2, 100)]), (0, -1, 0), 0)  # post
    add(_plane(rng, (10, 14), (2, 4), 1.6, 300), (0, 0, 1), 0)  # the car
    add(np.column_stack([rng.uniform(10, 14, 300), np.full(300, 2.0), rng.uniform(0.25, 1.6, 300)]), (0, -1, 0), 0)
    for x, nx in ((10.0, -1.0), (14.0, 1.0)):
        add(np.column_stack([np.full(150, x), rng.uniform(2, 4, 150), rng.uniform(0.25, 1.6, 150)]), (nx, 0, 0), 0)
    p, n, s, _ = scene.tensors()
    plate_i = slice(n_before, n_before + 300)
    car = torch.zeros(len(p), dtype=torch.bool)
    car[n_before + 400:] = True
    car &= p[:, 2] > 0.8  # the lowest 0.75 m of the sides: no session has evidence that close to the road
    x, y = p[:, 0], p[:, 1]
    rim = car & (p[:, 2] > 1.55) & ((x < 10.5) | (x > 13.5) | (y < 2.5) | (y > 3.5))

    plain = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0)
    over = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, overhang_m=1.0)
    assert float(plain[plate_i].mean()) < 0.5  # four sessions "saw through" it to the road
    assert over[plate_i].min() == 1.0
    assert plain[car].max() <= 0.2 + 1e-6 and over[car & ~rim].max() <= 0.2 + 1e-6
    assert float((over[rim] > 0.2).float().mean()) < 0.5
    # a gap asked for wider than the 2.2 m of open ground under the plate: not an overhang
    assert float(consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, overhang_m=2.5)[plate_i].mean()) < 0.5


def test_a_movable_object_needs_a_second_witness_where_no_session_saw_through_it() -> None:
    """Three sessions; two drove street A, one drove street B alone and saw a parked car there. Nobody saw
    through that car (free-space evidence keeps it at 1); as a movable class it has one witness: 0. The car
    both street-A sessions saw, and street B's road and wall, stay at 1. With one session in the pool, or
    the rule off (``movable_sessions`` 1), the lone car keeps its 1."""
    rng = np.random.default_rng(5)
    scene = _Scene()
    add = scene.add
    for s in (0, 1):  # street A, y 0..8, with a car both saw
        add(_plane(rng, (0, 40), (0, 8), 0.0, 3000), (0, 0, 1), s)
        add(_plane(rng, (10, 14), (2, 4), 1.6, 300), (0, 0, 1), s, movable=True)
    add(_plane(rng, (0, 40), (30, 38), 0.0, 3000), (0, 0, 1), 2)  # street B, session 2 alone
    add(_plane(rng, (20, 24), (32, 34), 1.6, 300), (0, 0, 1), 2, movable=True)
    add(np.column_stack([rng.uniform(0, 40, 1000), np.full(1000, 38.0), rng.uniform(0, 4, 1000)]), (0, -1, 0), 2)
    p, n, s, m = scene.tensors()
    lone = torch.zeros(len(p), dtype=torch.bool)
    lone[2 * 3300 + 3000: 2 * 3300 + 3300] = True
    assert bool(m[lone].all()) and int(m.sum()) == 900

    plain = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0)
    asked = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2)
    assert plain.min() == 1.0  # nobody saw through anything: the free-space rule keeps the lone car
    assert asked[lone].max() == 0.0
    assert asked[~lone].min() == 1.0  # the car two sessions saw, the roads and the wall
    assert consensus_targets(p, s, 0.5, 2.5, normals=n, movable=m, movable_sessions=1).min() == 1.0
    only_b = s == 2
    assert consensus_targets(p[only_b], s[only_b], 0.5, 2.5, normals=n[only_b], movable=m[only_b],
                             movable_sessions=2).min() == 1.0


def test_a_second_witness_is_asked_only_where_a_second_session_was_there() -> None:
    """``movable_cover_m``: session 0 drove street A and street B, session 1 street A only. A car on street B
    (only session 0 within 5 m) is kept; a car on street A that session 1 passed within 5 m without seeing it
    (its road has a hole under the car: no free-space evidence) is dropped; a car both saw stays. Without
    the cover radius the street-B car is dropped too (the tile holds two sessions)."""
    rng = np.random.default_rng(7)
    scene = _Scene()

    def add(p: np.ndarray, s: int, movable: bool = False) -> None:
        scene.add(p, (0.0, 0.0, 1.0), s, movable)

    add(_plane(rng, (0, 40), (0, 8), 0.0, 3000), 0)  # street A
    road_1 = _plane(rng, (0, 40), (0, 8), 0.0, 3000)
    add(road_1[~((road_1[:, 0] > 28) & (road_1[:, 0] < 36) & (road_1[:, 1] < 6))], 1)  # a hole under car 2
    for s in (0, 1):
        add(_plane(rng, (10, 14), (2, 4), 1.6, 300), s, movable=True)  # car 1: both saw it
    add(_plane(rng, (30, 34), (2, 4), 1.6, 300), 0, movable=True)  # car 2: session 0 only
    add(_plane(rng, (0, 40), (30, 38), 0.0, 3000), 0)  # street B, session 0 alone
    add(_plane(rng, (20, 24), (32, 34), 1.6, 300), 0, movable=True)  # car 3
    p, n, s, m = scene.tensors()
    car1 = m & (p[:, 0] < 20) & (p[:, 1] < 10)
    car2 = m & (p[:, 0] > 20) & (p[:, 1] < 10)
    car3 = m & (p[:, 1] > 10)
    assert int(car1.sum()) == 600 and int(car2.sum()) == 300 and int(car3.sum()) == 300

    assert consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0).min() == 1.0  # free space drops none
    covered = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2,
                                movable_cover_m=5.0)
    assert covered[car1].min() == 1.0 and covered[car3].min() == 1.0 and covered[~m].min() == 1.0
    assert covered[car2].max() == 0.0
    anywhere = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2)
    assert anywhere[car2].max() == 0.0 and anywhere[car3].max() == 0.0 and anywhere[car1].min() == 1.0


def test_a_witness_is_a_surface_within_the_consensus_radius() -> None:
    """Two sessions saw the flank of one parked car 0.9 m apart (depth error along the viewing ray) and the car
    at 0.3 m; session 0 alone saw a third car on a street it drove alone. A witness is a surface within the 0.5 m
    radius: the car seen 0.3 m apart stays, the one seen 0.9 m apart is dropped like the lone one (the limit)."""
    rng = np.random.default_rng(6)
    pts, sess, mov = [], [], []
    for s, y, x in ((0, 2.0, 10.0), (1, 2.9, 10.0), (0, 2.0, 20.0), (1, 2.3, 20.0)):
        pts += [_plane(rng, (0, 40), (-6, 0), 0.0, 2000),
                np.column_stack([rng.uniform(x, x + 4, 300), np.full(300, y), rng.uniform(0.8, 1.6, 300)])]
        sess += [np.full(2000, s), np.full(300, s)]
        mov += [np.zeros(2000, bool), np.ones(300, bool)]
    pts.append(np.column_stack([rng.uniform(30, 34, 300), np.full(300, 40.0), rng.uniform(0.8, 1.6, 300)]))
    sess.append(np.zeros(300, int))
    mov.append(np.ones(300, bool))
    p = torch.tensor(np.concatenate(pts), dtype=torch.float32)
    s = torch.tensor(np.concatenate(sess))
    m = torch.tensor(np.concatenate(mov))
    apart = m & (p[:, 1] < 10) & (p[:, 0] < 15)
    close = m & (p[:, 1] < 10) & (p[:, 0] > 15)
    lone = m & (p[:, 1] > 10)
    n = torch.where(m[:, None], torch.tensor([0.0, -1.0, 0.0]), torch.tensor([0.0, 0.0, 1.0]))
    near_any = consensus_targets(p, s, 0.5, 2.5, normals=n, movable=m, movable_sessions=2)
    assert near_any[apart].max() == 0.0 and near_any[lone].max() == 0.0
    assert near_any[close].min() == 1.0 and near_any[~m].min() == 1.0



def test_the_road_beneath_a_car_is_no_witness_of_its_lower_body() -> None:
    """Session 0 saw a car (a 4 × 2 m box from 0.15 to 1.6 m over the road, no road beneath it); session 1
    drove by when it was gone and saw the bare road there. A witness is any surface within the 0.5 m radius (a
    cube of 0.25 m cells), so the road counted for the car's body up to 0.75 m: it kept 1 there. With
    ``movable_below_m`` 0.25 a witness lies at most one cell below: only what is within 0.5 m of the road keeps
    it. A car both sessions saw keeps every point either way (its witnesses stand level with it), and so does
    the road; ``movable_below_m`` at the radius is the plain cube."""
    rng = np.random.default_rng(8)
    scene = _Scene()

    def box(x0: float, s: int) -> None:
        for y in (2.0, 4.0):  # the flanks
            scene.add(np.column_stack([rng.uniform(x0, x0 + 4, 400), np.full(400, y), rng.uniform(0.15, 1.6, 400)]),
                      (0.0, 1.0 if y > 3 else -1.0, 0.0), s, movable=True)
        scene.add(_plane(rng, (x0, x0 + 4), (2, 4), 1.6, 300), (0.0, 0.0, 1.0), s, movable=True)  # the roof

    for s in (0, 1):
        road = _plane(rng, (0, 40), (0, 8), 0.0, 4000)
        under = (road[:, 1] > 2) & (road[:, 1] < 4) & (((road[:, 0] > 10) & (road[:, 0] < 14)) | (road[:, 0] > 24)
                                                       & (road[:, 0] < 28))
        scene.add(road[~under if s == 1 else ~(under & (road[:, 0] < 20))], (0.0, 0.0, 1.0), s)
        box(24.0, s)  # the parked car both saw: nothing under it in either session
    box(10.0, 0)  # the car only session 0 saw; session 1's road runs beneath it
    p, n, s, m = scene.tensors()
    lone = m & (p[:, 0] < 20)
    both = m & (p[:, 0] > 20)
    low = lone & (p[:, 2] < 0.5)
    body = lone & (p[:, 2] >= 0.5)
    lower_body = body & (p[:, 2] < 0.75)
    assert int(lone.sum()) == 1100 and int(both.sum()) == 2200

    cube = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2)
    level = consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2,
                              movable_below_m=0.25)
    assert cube[lower_body].min() == 1.0 and cube[low].min() == 1.0  # the road witnessed the lower body
    assert level[body].max() == 0.0 and level[low].min() == 1.0
    assert level[both].min() == 1.0 and cube[both].min() == 1.0
    assert torch.equal(level[~m], cube[~m]) and level[~m].min() == 1.0
    assert torch.equal(consensus_targets(p, s, 0.5, 2.5, normals=n, column_m=3.0, movable=m, movable_sessions=2,
                                         movable_below_m=0.5), cube)

def test_calibrated_confidence_keeps_what_enough_observers_saw() -> None:
    """c_th 0.7, keep 0.55: 2 of 3 and 3 of 5 observers keep a surface (the raw fraction, 0.67 and 0.6,
    dropped both), 1 of 2, 1 of 3 and 2 of 5 do not. Monotone, 0 and 1 fixed; keep = c_th is the raw fraction."""
    f = torch.tensor([0.0, 0.2, 1 / 3, 0.4, 0.5, 0.55, 0.6, 2 / 3, 1.0])
    t = calibrated_confidence(f, keep_fraction=0.55, c_th=0.7)
    assert t[0] == 0.0 and t[-1] == 1.0 and abs(float(t[5]) - 0.7) < 1e-6
    assert (t[1:5] < 0.7).all() and (t[6:] > 0.7).all()
    assert (t.diff() > 0).all()
    assert torch.allclose(calibrated_confidence(f, keep_fraction=0.7, c_th=0.7), f)
    # three sessions; the third has a 3 m hole in its road: the others' road there stays above c_th
    rng = np.random.default_rng(2)
    a, b, c = (_plane(rng, (0, 10), (0, 4), 0.0, 2000) for _ in range(3))
    c = c[np.abs(c[:, 0] - 5) > 1.5]
    p = torch.tensor(np.concatenate([a, b, c]), dtype=torch.float32)
    s = torch.tensor(np.repeat([0, 1, 2], [len(a), len(b), len(c)]))
    raw = consensus_targets(p, s, 0.5, 2.5)[: len(a)]
    cal = consensus_targets(p, s, 0.5, 2.5, keep_fraction=0.55, c_th=0.7)[: len(a)]
    in_hole = torch.tensor(np.abs(a[:, 0] - 5) < 0.5)
    assert raw[in_hole].max() < 0.7 < cal[in_hole].min()


def test_consensus_of_a_single_session_is_one_and_empty_input_is_empty() -> None:
    rng = np.random.default_rng(1)
    p = torch.tensor(_plane(rng, (0, 5), (0, 5), 1.0, 500), dtype=torch.float32)
    assert torch.all(consensus_targets(p, torch.zeros(500, dtype=torch.long), 0.5, 2.5) == 1.0)
    empty = consensus_targets(torch.zeros(0, 3), torch.zeros(0, dtype=torch.long), 0.5, 2.5)
    assert empty.shape == (0,)


def test_huge_boxes_fall_back_to_coarser_cells() -> None:
    p = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [5000.0, 5000.0, 50.0]])
    s = torch.tensor([0, 1, 1])
    t = consensus_targets(p, s, 0.5, 2.5, max_cells=1 << 16)
    assert t.tolist() == [1.0, 1.0, 1.0]


def _square(size: float, label: int) -> SemanticMesh:
    v = np.array([[0, 0, 0], [size, 0, 0], [size, size, 0], [0, size, 0]], float)
    return SemanticMesh(v, np.array([[0, 1, 2], [0, 2, 3]]), np.array([label, label]))


def test_surface_pool_is_area_weighted_inside_the_box_and_exactly_sized() -> None:
    # a 4 m and a 2 m square (local frames), the small one posed at x = 10 m; the box cuts the big
    # one in half, so the pool should hold the two inside areas (8 m², 4 m²) 2:1
    small_pose = np.eye(4)
    small_pose[0, 3] = 10.0
    submaps = [
        SubmapInput("a", "s", 0, _square(4.0, 1), Pose.identity(), Pose.identity()),
        SubmapInput("b", "s", 1, _square(2.0, 2), Pose.from_matrix(small_pose), Pose.identity()),
    ]
    lo, hi = np.array([-1.0, -1.0, -1.0]), np.array([20.0, 2.0, 1.0])
    pts, nrm, lab, own = sample_surface_pool(submaps, [np.eye(4), small_pose], lo, hi, 30_000,
                                             np.random.default_rng(0))
    assert len(pts) == len(nrm) == len(lab) == len(own) == 30_000
    posed = np.where(own[:, None] == 1, pts + [10.0, 0, 0], pts)
    assert np.all((posed >= lo) & (posed <= hi))
    assert np.allclose(pts[:, 2], 0.0) and np.allclose(np.abs(nrm[:, 2]), 1.0)
    assert np.array_equal(lab, np.where(own == 0, 1, 2))
    assert abs((own == 0).mean() - 2 / 3) < 0.02
    # uniform over the inside area: the big square's kept half splits evenly in x
    assert abs((pts[own == 0, 0] < 2.0).mean() - 0.5) < 0.02


def test_class_balance_weighs_by_the_whole_submaps_not_the_part_in_the_box() -> None:
    # a 4 m square of class 1 (half of it in the box) and a 2 m square of class 2 (all in): by the submaps'
    # own areas (16 / 4 m²) class 2's share is 0.2 and its weight (0.5 / 0.2) = 2.5, so the pool holds
    # 4 · 2.5 : 8 of classes 2 : 1 (0.556 of the points); the in-box areas alone (8 / 4) would give 0.43
    small_pose = np.eye(4)
    small_pose[0, 3] = -3.0
    submaps = [
        SubmapInput("a", "s", 0, _square(4.0, 1), Pose.identity(), Pose.identity()),
        SubmapInput("b", "s", 1, _square(2.0, 2), Pose.from_matrix(small_pose), Pose.identity()),
    ]
    lo, hi = np.array([-5.0, -1.0, -1.0]), np.array([2.0, 5.0, 1.0])
    _, _, lab, _ = sample_surface_pool(submaps, [np.eye(4), small_pose], lo, hi, 40_000, np.random.default_rng(1),
                                       class_balance=1.0, class_weight_max=4.0)
    assert abs((lab == 2).mean() - 10 / 18) < 0.015
