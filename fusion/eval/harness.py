"""The :class:`Harness` the ablation studies (``fusion.eval.ablations``) run on, backed by :mod:`fusion.eval.bench`: the same simulated fleet, tile,
offline fusion path (``fusion.offline.fuse_tiles``) and scoring (``bench.evaluate_both``: the
gauge-aligned scoring of ``fusion.eval.scoring``; ``bench.pose_figures``) as ``fleetmap bench``, so ablation rows compare with
the bench table: ``geo_*``/``sem_f`` gauge-aligned, ``abs_geo_f``/``abs_sem_f`` in the map frame.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fusion.eval import bench
from fusion.types import FusedMesh, Pose, SubmapInput, TileSpec

Row = dict[str, Any]
Scores = dict[str, float]


class Harness(Protocol):
    """What the studies need from the bench (all frames: map frame, metres). ``scenario``: whatever
    ``simulate`` returns (the bench's: :class:`Scenario`)."""

    base_config: Any  # the FusionConfig the bench fuses with

    def simulate(self, **overrides: Any) -> Any:
        """A synthetic fleet + one tile (overrides: ``sessions``, ``submap_length``, ``gps_sigma_m``,
        ``gps_sigma_deg``, ``seed``, ``vertex_noise_m``, ``sensor``)."""

    def fuse(self, scenario: Any, config: Any) -> tuple[FusedMesh, dict[str, Pose], float]:
        """The neural fusion of the scenario's tile: (mesh, refined poses, seconds)."""

    def evaluate(self, scenario: Any, mesh: FusedMesh, poses: dict[str, Pose]) -> Scores:
        """The bench's P/R/F and pose RMSE keys (see the module docstring)."""

    def submaps(self, scenario: Any) -> list[SubmapInput]:
        """The tile's fusion inputs."""

    def tile(self, scenario: Any) -> TileSpec:
        """The scenario's tile."""

    def uploaded_mb_per_km(self, scenario: Any) -> float:
        """Uploaded data per driven km, MB."""

    def field_mb_per_km(self, scenario: Any, config: Any) -> float:
        """Stored neural-field size per km of road in the tile, MB."""


@dataclass
class Scenario:
    """One simulated fleet prepared for the bench tile; sizes in bytes, distances in km."""

    ctx: bench.BenchContext
    upload_bytes: int
    driven_km: float
    road_km_in_tile: float


def _driven_km(records: list[Any], submap_length: float) -> float:
    """Distance the sessions drove: gaps between consecutive submap origins plus one submap per session."""
    by_session: dict[str, list[Any]] = {}
    for r in records:
        by_session.setdefault(r.session_id, []).append(r)
    total = 0.0
    for recs in by_session.values():
        recs.sort(key=lambda r: r.seq)
        t = np.array([r.pose_true.t for r in recs])
        total += float(np.linalg.norm(np.diff(t, axis=0), axis=1).sum()) + submap_length
    return total / 1000.0


def _road_km(ctx: bench.BenchContext) -> float:
    """Road length in the tile, km: road-labelled ground-truth area over the road width."""
    from fusion.labels import LABEL_BY_NAME

    gt = ctx.points.gt_all
    road = int(np.sum(gt.labels == LABEL_BY_NAME["road"].id))
    density = bench.metrics.DEFAULT_DENSITY  # points per m² of the sampled truth
    width = 2.0 * float(ctx.truth.info.get("world", {}).get("road_half_width", 5.5))
    return max(road / density / width / 1000.0, 1e-6)


class BenchHarness:
    """The :class:`Harness` backed by :mod:`fusion.eval.bench`: its simulated fleet, tile (``bench.TILE``),
    offline fusion and scoring."""

    def __init__(self, config: Any, defaults: dict[str, Any]) -> None:
        self.base_config = config
        self.defaults = defaults  # simulation parameters ``simulate`` overrides

    def simulate(self, **overrides: Any) -> Scenario:
        from fusion.eval.synth.fleet import FleetParams
        from fusion.eval.synth.simulate import simulate

        p = {**self.defaults, **overrides}
        with tempfile.TemporaryDirectory(prefix="fleetmap-ablation-") as tmp:
            records = simulate(
                tmp,
                seed=p["seed"],
                sessions=p["sessions"],
                gps_noise=(p["gps_sigma_m"], p["gps_sigma_deg"]),
                fleet_params=FleetParams(submap_length=p["submap_length"], vertex_noise_m=p["vertex_noise_m"]),
                sensor=p.get("sensor", "camera"),
                camera=p.get("camera", ()),
                world=p.get("world", ()),
            )
            upload = sum(f.stat().st_size for f in Path(tmp).glob("*.ply"))
            upload += sum(f.stat().st_size for f in Path(tmp).glob("*.json"))
            ctx = bench.prepare(Path(tmp), self.base_config)
        return Scenario(ctx, upload, _driven_km(records, p["submap_length"]), _road_km(ctx))

    def fuse(self, s: Scenario, cfg: Any) -> tuple[FusedMesh, dict[str, Pose], float]:
        from fusion.offline import fuse_tiles

        t0 = time.perf_counter()
        refined: dict[str, Pose] = {}  # the alignment's poses (the reconstruction holds every pose)
        result = fuse_tiles(s.ctx.submaps, [bench.TILE], cfg, bench.TILE_SIZE, refined=refined)[bench.TILE]
        return result.mesh, refined, time.perf_counter() - t0

    def evaluate(self, s: Scenario, mesh: FusedMesh, poses: dict[str, Pose]) -> Scores:
        """Reconstruction figures gauge-aligned like the bench's fused row (plain keys: the mesh moved by
        ``bench.gauge_transform`` of the tile's submaps as posed by this fusion; submaps without a
        refined pose count at GPS) and in the absolute map frame (``abs_geo_f``, ``abs_sem_f``)."""
        out: Scores = {}
        if len(mesh.faces):
            figs = bench.evaluate_both(s.ctx, mesh, poses)
            out.update({k: float(figs[k]) for k in ("geo_p", "geo_r", "geo_f", "sem_f", "abs_geo_f", "abs_sem_f")})
        else:
            out.update({k: 0.0 for k in ("geo_p", "geo_r", "geo_f", "sem_f", "abs_geo_f", "abs_sem_f")})
        full = {sm.input.id: sm.pose_gps for sm in s.ctx.submaps} | poses
        pf = bench.pose_figures(s.ctx, full)
        out.update(
            {
                "trans_m": float(pf.get("pose_trans_m", np.nan)),
                "rot_deg": float(pf.get("pose_rot_deg", np.nan)),
            }
        )
        return out

    def submaps(self, s: Scenario) -> list[SubmapInput]:
        """The tile's inputs as the offline path builds them: home submaps free, others held at GPS."""
        return [replace(sm.input, free=sm.home == bench.TILE) for sm in s.ctx.submaps if bench.TILE in sm.tiles]

    def tile(self, s: Scenario) -> TileSpec:
        return TileSpec(bench.TILE[0], bench.TILE[1], bench.TILE_SIZE)

    def uploaded_mb_per_km(self, s: Scenario) -> float:
        return s.upload_bytes / 1e6 / max(s.driven_km, 1e-9)

    def field_mb_per_km(self, s: Scenario, cfg: Any) -> float:
        """Stored neural-field size (grid + heads, float32) per km of road in the tile."""
        import torch

        from fusion.field import SemanticSDFField
        from fusion.grids.dense import grid_size_bytes

        m, size = cfg.tile_margin_m, bench.TILE_SIZE
        z = s.ctx.points.gt_all.points[:, 2] if len(s.ctx.points.gt_all) else np.zeros(1)
        lo = torch.tensor([-m, -m, float(z.min()) - cfg.slab_pad_m])
        hi = torch.tensor(
            [size + m, size + m, min(float(z.max()) + cfg.slab_pad_m, float(lo[2]) + cfg.slab_max_m)]
        )
        field = SemanticSDFField(cfg, lo, hi)
        heads = sum(
            p.numel() * p.element_size() for n, p in field.named_parameters() if not n.startswith("grid.")
        )
        grid = grid_size_bytes(field.grid)
        if (
            cfg.grid_type == "octree"
        ):  # sized as allocated around the truth (the fusion allocates around the data)
            pts = torch.tensor(s.ctx.points.gt_all.points, dtype=torch.float32)
            pts -= torch.tensor([bench.TILE[0] * size, bench.TILE[1] * size, 0.0])
            field.grid.allocate(field.norm(pts))  # type: ignore[operator]
            grid = grid_size_bytes(field.grid)
        return (grid + heads) / 1e6 / s.road_km_in_tile


def bench_harness(args: argparse.Namespace) -> BenchHarness:
    """Harness with the bench's defaults taken from ``args`` (preset, sessions, seed, GPS noise, sensor)."""
    from fusion.config import FusionConfig
    from fusion.eval.synth.fleet import FleetParams

    defaults = {
        "sessions": getattr(args, "sessions", 5),
        "seed": getattr(args, "seed", 0),
        "gps_sigma_m": getattr(args, "gps_noise_m", 1.5),
        "gps_sigma_deg": getattr(args, "gps_noise_deg", 1.5),
        "submap_length": FleetParams().submap_length,
        "vertex_noise_m": getattr(args, "vertex_noise_m", FleetParams().vertex_noise_m),
        "sensor": getattr(args, "sensor", "camera"),
        "camera": getattr(args, "camera", []),
        "world": getattr(args, "world", []),
    }
    return BenchHarness(FusionConfig.preset(getattr(args, "preset", "cpu")), defaults)
