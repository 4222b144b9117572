"""The content-proportional schedule: a tile's steps scale with the surface it holds, a full tile keeps them."""

from __future__ import annotations

import numpy as np
import torch

from fusion.align import align_region
from fusion.config import FusionConfig
from fusion.reconstruct import reconstruct_tile
from fusion.schedule import content_iterations, tile_content
from fusion.types import TileSpec
from tests.scene import tiny_config, two_sessions

CFG = FusionConfig.preset("cpu")  # 2 m voxels, full at 1 × the box's ground area, floor 1/3
LO, HI = np.zeros(3), np.array([80.0, 80.0, 10.0])  # a 64 m tile box with 8 m margins: 6400 m² of ground


def _plane(x0: float, x1: float, y0: float, y1: float, step: float = 0.25, z: float = 0.1) -> np.ndarray:
    gx, gy = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step), indexing="ij")
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)


def test_content_is_the_observed_surface_over_the_box_ground_area() -> None:
    assert tile_content(_plane(0, 80, 0, 80), LO, HI, CFG) == 1.0
    assert abs(tile_content(_plane(0, 80, 0, 20), LO, HI, CFG) - 0.25) < 1e-9
    assert abs(tile_content(_plane(0, 8, 0, 8), LO, HI, CFG) - 64 / 6400) < 1e-9
    assert tile_content(np.zeros((0, 3)), LO, HI, CFG) == 0.0
    # a second session on the same street counts once; the input type does not matter
    street = _plane(0, 80, 0, 20)
    twice = np.concatenate([street, street + 0.05])
    assert tile_content(torch.tensor(twice), torch.tensor(LO), torch.tensor(HI), CFG) == tile_content(street, LO, HI, CFG)
    # a wall adds its area: content is surface, not footprint (its 10 cubes along the street count once)
    wall = np.stack([np.full(800, 40.5), np.repeat(np.arange(0.5, 80, 1.0), 10), np.tile(np.arange(0.5, 10, 1.0), 80)], 1)
    assert abs(tile_content(np.concatenate([street, wall]), LO, HI, CFG) - (1600 + 800 - 10 * 4) / 6400) < 1e-9
    # sessions up to a voxel apart (GPS error before the alignment) count about once
    assert tile_content(np.concatenate([street, street + [0.9, 0.7, 0.0]]), LO, HI, CFG) < 1.2 * 0.25
    # the reference scales it: full at half the ground area
    assert tile_content(street, LO, HI, CFG.with_(schedule_full_cover=0.25)) == 1.0


def test_iterations_scale_with_content_between_floor_and_full() -> None:
    assert content_iterations(300, [1.0], CFG) == 300  # a full tile keeps the full schedule
    assert content_iterations(300, [0.5], CFG) == 150
    assert content_iterations(300, [0.01], CFG) == 100  # floor: a third of a tile's schedule
    assert content_iterations(300, [0.0], CFG) == 100
    # a region: the sum of its tiles' content; grazed tiles add ~nothing, never more than a full tile each
    assert content_iterations(300, [1.0, 1.0, 0.01, 0.01], CFG) == 606
    assert content_iterations(300, [1.0, 0.5, 0.0], CFG) == 450
    assert content_iterations(300, [2.0, 2.0], CFG) == 600
    assert content_iterations(300, [0.02] * 9, CFG) == 100
    assert content_iterations(300, [0.1] * 9, CFG) == 270
    assert content_iterations(300, [0.5], CFG.with_(schedule_min_fraction=0.1)) == 150
    assert content_iterations(300, [0.3], CFG.with_(schedule_min_fraction=1.0)) == 300
    assert content_iterations(10, [0.0], CFG) == 4
    assert content_iterations(10, [0.0], CFG.with_(schedule_min_fraction=0.0)) == 1


def test_reconstruct_and_align_record_their_scheduled_steps() -> None:
    """The 16 m test street (two sessions, GPS-posed) in its 24 m tile box, full at 2 × the box's ground
    area: about half the steps; the full schedule once its content reaches a full tile."""
    subs, _ = two_sessions()
    tile = TileSpec(0, 0, 16.0)
    cfg = tiny_config(iterations=40, schedule_min_fraction=0.1, schedule_full_cover=2.0)
    res = reconstruct_tile(subs, tile, cfg)
    content = res.metrics["content"]
    assert 0.3 < content < 0.8
    assert res.metrics["iterations"] == round(40 * content) == res.config["iterations"]
    full = reconstruct_tile(subs, tile, cfg.with_(schedule_full_cover=0.5))
    assert full.metrics["content"] == 1.0 and full.metrics["iterations"] == 40
    aligned = align_region(subs, [tile, TileSpec(5, 5, 16.0)], cfg.with_(align_iterations_per_tile=20))
    assert aligned.metrics["num_tiles"] == 1 and aligned.metrics["skipped"]
    assert aligned.metrics["iterations"] == round(20 * aligned.metrics["tile_content"]["0_0"]) < 20
