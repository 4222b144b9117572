"""Offline fusion of a directory of submaps (``NAME.ply`` + ``NAME.json``), tile by tile, the way the
service does it: every submap's home tile owns its refined pose; fusing a tile frees its home submaps
and holds the others at their current (refined, else GPS) map-frame pose; neighbours fused earlier
pin the shared border so seam vertices coincide.

Output: ``OUT/tiles/{i}_{j}.ply`` (fused PLY, map frame), ``OUT/poses.json``
(``[{"session_id", "seq", "pose_gps", "pose_refined"}]``) and ``OUT/fusion.json`` (config, per-tile metrics).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusion import geo, tiles
from fusion.errors import FusionError, FusionLibraryError
from fusion.meshio import read_submap_ply, write_fused_ply
from fusion.types import FusionResult, Pose, ProgressCallback, ProgressEvent, Sigma, SubmapInput, TileSpec

if TYPE_CHECKING:
    from fusion.config import FusionConfig

DEFAULT_ORIGIN = "48.2620,11.6670,480.0"


class OfflineInputError(FusionLibraryError):
    """A submap file pair that cannot be read; the message names the file."""

    code = "invalid_submap_file"


@dataclass
class LoadedSubmap:
    """A submap read from disk: the fusion input (pose_init = GPS, map frame) and its tiles."""

    input: SubmapInput
    pose_gps: Pose
    tiles: list[tuple[int, int]]
    home: tuple[int, int]


def _sigma(meta: dict, key: str, default: Sigma) -> Sigma:
    s = meta.get(key)
    if s is None:
        return default
    return Sigma(float(s["trans_m"]), float(s["rot_deg"]))


def _gps_pose(gps: dict, origin: tuple[float, float, float]) -> Pose:
    if "pose" in gps:
        return Pose.from_json(gps["pose"])
    return geo.geodetic_to_map(float(gps["lat"]), float(gps["lon"]), float(gps["alt"]), np.asarray(gps["q"], float), origin)


def load_submap(ply_path: Path, tile_size: float, origin: tuple[float, float, float]) -> LoadedSubmap:
    """Read and validate one ``NAME.ply`` + ``NAME.json``; raises ``OfflineInputError`` naming the file."""
    meta_path = ply_path.with_suffix(".json")
    try:
        mesh = read_submap_ply(ply_path.read_bytes())
    except FusionLibraryError as exc:
        raise OfflineInputError(f"{ply_path}: {exc.message}") from exc
    if not meta_path.exists():
        raise OfflineInputError(f"{meta_path}: missing (each NAME.ply needs a NAME.json meta file)")
    try:
        meta = json.loads(meta_path.read_text())
        # class attributes of a dataclass field with a default hold that default
        gps_sigma = _sigma(meta, "gps_sigma", SubmapInput.gps_sigma)
        odo_sigma = _sigma(meta, "odometry_sigma", SubmapInput.odometry_sigma)
        pose_gps = _gps_pose(meta["gps"], origin)
        sm = SubmapInput(id=ply_path.stem, session_id=str(meta["session_id"]), seq=int(meta["seq"]), mesh=mesh,
                         pose_init=pose_gps, odometry=Pose.from_json(meta["odometry"]), gps_sigma=gps_sigma,
                         odometry_sigma=odo_sigma, pose_gps=pose_gps)
    except FusionLibraryError as exc:
        raise OfflineInputError(f"{meta_path}: {exc.message}") from exc
    except (KeyError, TypeError, ValueError) as exc:
        raise OfflineInputError(f"{meta_path}: invalid meta ({type(exc).__name__}: {exc})") from exc
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return LoadedSubmap(sm, pose_gps, tiles.submap_tiles(lo, hi, pose_gps, gps_sigma, tile_size),
                        tiles.home_tile((lo, hi), pose_gps, tile_size))


def load_directory(in_dir: str | Path, tile_size: float = 64.0, origin: str | None = None) -> list[LoadedSubmap]:
    """Every ``NAME.ply`` (with its ``NAME.json``) directly in ``in_dir``, sorted by name."""
    directory = Path(in_dir)
    if not directory.is_dir():
        raise OfflineInputError(f"{directory}: not a directory")
    paths = sorted(directory.glob("*.ply"))
    if not paths:
        raise OfflineInputError(f"{directory}: no NAME.ply submap files")
    org = geo.parse_origin(origin or DEFAULT_ORIGIN)
    return [load_submap(p, tile_size, org) for p in paths]


def fuse_tiles(submaps: list[LoadedSubmap], tile_keys: list[tuple[int, int]], config: FusionConfig,
               tile_size: float = 64.0, progress: ProgressCallback | None = None,
               refined: dict[str, Pose] | None = None, fixed_poses: dict[str, Pose] | None = None,
               on_tile: Callable[[tuple[int, int], FusionResult], None] | None = None,
               skipped: dict[str, str] | None = None) -> dict[tuple[int, int], FusionResult]:
    """Fuse ``tile_keys`` in order. ``refined`` (submap id → map pose) is updated in place with the
    poses each tile's home submaps get. ``fixed_poses``: if given, every submap is held at that pose
    (no pose optimisation; e.g. true poses for an oracle). A tile the fusion finds no data in (its
    submaps only graze it through their GPS uncertainty) is recorded in ``skipped`` (else raised)."""
    from fusion.reconstruct import fuse_tile

    refined = {} if refined is None else refined
    results: dict[tuple[int, int], FusionResult] = {}
    for n, key in enumerate(tile_keys):
        inputs = []
        for s in submaps:
            if key not in s.tiles:
                continue
            if fixed_poses is not None:
                inputs.append(replace(s.input, pose_init=fixed_poses[s.input.id], free=False))
            else:
                pose = refined.get(s.input.id, s.pose_gps)
                inputs.append(replace(s.input, pose_init=pose, free=s.home == key))
        pins = tiles.border_pins(*key, lambda k: results[k].border if k in results else None)

        def tile_progress(ev: ProgressEvent, n: int = n, key: tuple[int, int] = key) -> None:
            stage = f"tile {key[0]}_{key[1]} ({n + 1}/{len(tile_keys)}) {ev.stage}"
            progress(ProgressEvent(ev.iteration, ev.total, ev.losses, stage))  # type: ignore[misc]

        try:
            result = fuse_tile(inputs, TileSpec(key[0], key[1], tile_size), config,
                               progress=tile_progress if progress else None, border_pins=pins or None)
        except FusionError as exc:
            if skipped is None:
                raise
            skipped[f"{key[0]}_{key[1]}"] = exc.message
            continue
        refined.update(result.poses)
        results[key] = result
        if on_tile is not None:
            on_tile(key, result)
    return results


def fuse_directory(in_dir: str | Path, out_dir: str | Path, config: FusionConfig, tile_size: float = 64.0,
                   origin: str | None = None, progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Fuse every submap in ``in_dir`` into ``out_dir`` (see the module docstring). Tiles are fused in
    (i, j) order. Returns a summary: tiles, submaps, per-tile metrics."""
    submaps = load_directory(in_dir, tile_size, origin)
    keys = sorted({k for s in submaps for k in s.tiles})
    out = Path(out_dir)
    (out / "tiles").mkdir(parents=True, exist_ok=True)
    refined: dict[str, Pose] = {}
    tile_metrics: dict[str, Any] = {}

    def write_tile(key: tuple[int, int], result: FusionResult) -> None:
        (out / "tiles" / f"{key[0]}_{key[1]}.ply").write_bytes(write_fused_ply(result.mesh))
        tile_metrics[f"{key[0]}_{key[1]}"] = result.metrics

    skipped: dict[str, str] = {}
    fuse_tiles(submaps, keys, config, tile_size, progress, refined, on_tile=write_tile, skipped=skipped)
    poses = [{"session_id": s.input.session_id, "seq": s.input.seq, "id": s.input.id, "pose_gps": s.pose_gps.to_json(),
              "pose_refined": refined[s.input.id].to_json() if s.input.id in refined else None} for s in submaps]
    poses.sort(key=lambda p: (p["session_id"], p["seq"]))
    (out / "poses.json").write_text(json.dumps(poses, indent=1))
    summary = {"tiles": [list(k) for k in keys], "submaps": len(submaps), "tile_size_m": tile_size,
               "config": config.to_dict(), "metrics": tile_metrics,
               "skipped": skipped}
    (out / "fusion.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary
