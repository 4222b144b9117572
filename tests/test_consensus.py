"""Cross-session consensus targets (confidence supervision): transient objects, occluded road, facades."""

from __future__ import annotations

import numpy as np
import torch

from fusion.sampling import consensus_targets


def _plane(rng: np.random.Generator, x: tuple[float, float], y: tuple[float, float], z: float, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(*x, n), rng.uniform(*y, n), np.full(n, z)])


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
