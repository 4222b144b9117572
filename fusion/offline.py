"""Offline fusion of a directory of submaps (``NAME.ply`` + ``NAME.json``): the tiles are grouped into
regions (tiles linked by overlapping submaps), each region's poses are aligned jointly (one pose per
submap, ``fusion.align``), then each tile is reconstructed with every submap held at its aligned pose;
neighbours reconstructed earlier pin the shared border so seam vertices coincide (DESIGN.md,
"Multi-tile consistency").

Output: ``OUT/tiles/{i}_{j}.ply`` (fused PLY, map frame), ``OUT/poses.json``
(``[{"session_id", "seq", "pose_gps", "pose_refined"}]``) and ``OUT/fusion.json`` (config, per-tile metrics).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fusion import geo, tiles
from fusion.drift import Drift, corrected_input
from fusion.errors import FusionError, FusionLibraryError
from fusion.meshio import read_submap_ply, write_fused_ply
from fusion.regions import regions
from fusion.types import (
    FusionResult,
    Pose,
    ProgressCallback,
    ProgressEvent,
    Sigma,
    SubmapInput,
    TileSpec,
    WarmKind,
)

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
    home: tuple[int, int]  # tile of the posed centre; no pose ownership any more (the ablation harness reads it)


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
               skipped: dict[str, str] | None = None,
               align_metrics: list[dict[str, Any]] | None = None, grow: bool = False,
               drifts: dict[str, Drift] | None = None,
               ) -> dict[tuple[int, int], FusionResult]:
    """Fuse ``tile_keys``: align each region, then reconstruct each tile with the poses fixed.

    1. Regions: the requested tiles linked by the submaps overlapping them (``fusion.regions``).
    2. Alignment (``fusion.align.align_region``): every submap of a region free, one pose per submap,
       starting from ``refined`` (a previous fusion) else GPS; the GPS prior anchors to the GPS fix.
       ``refined`` (submap id → map pose) is updated in place with the aligned poses.
    3. Reconstruction (``reconstruct_tile``): each tile with every submap held at its aligned pose, in sorted
       (i, j) order so neighbours reconstructed earlier pin the shared border. A tile's submaps: those whose
       GPS box or aligned surface reaches it (:func:`members`); ``grow``: the tiles only an aligned surface
       reaches are reconstructed too (else only ``tile_keys``).

    Tiles are processed in sorted order whatever order ``tile_keys`` lists them in, so the result does
    not depend on it. ``fixed_poses``: if given, every submap is held at that pose and alignment is
    skipped (e.g. true poses for an oracle). A tile (or region) the fusion finds no data in (its
    submaps only graze it through their GPS uncertainty) is recorded in ``skipped`` (else raised).
    ``align_metrics``: if given, each region's alignment metrics are appended to it. ``drifts`` (submap id →
    ``fusion.drift.Drift``, ``fine_drift``): updated in place like ``refined``; each submap is reconstructed
    corrected by its entry."""
    refined = {} if refined is None else refined
    drifts = {} if drifts is None else drifts
    keys = sorted({(int(i), int(j)) for i, j in tile_keys})
    fields: dict[tuple[int, int], dict[str, Any]] = {}
    if fixed_poses is None:
        _align_regions(submaps, keys, config, tile_size, progress, refined, skipped, align_metrics, fields, drifts)
    poses = fixed_poses if fixed_poses is not None else refined
    if grow:
        keys = sorted(set(keys).union(*members(submaps, poses, tile_size, config).values()))
    return reconstruct_tiles(submaps, keys, config, tile_size, progress, poses, on_tile, skipped, warm=fields,
                             drifts=drifts if fixed_poses is None else None)


def members(submaps: list[LoadedSubmap], poses: dict[str, Pose], tile_size: float,
            config: FusionConfig) -> dict[str, set[tuple[int, int]]]:
    """Each submap's tiles, as the service keeps them: those of its GPS box, joined by every tile its
    surface reaches (within ``refusion_band_m``) at its pose in ``poses``, where it has one: a submap whose
    GPS erred by more than its sigma is fused where the alignment put it (``fusion.tiles.surface_tiles``;
    the service's ``worker.results._join_surface_tiles``)."""
    out = {}
    for s in submaps:
        pose = poses.get(s.input.id)
        reach = [] if pose is None else tiles.surface_tiles(s.input.mesh.vertices, s.input.mesh.faces, pose,
                                                            tile_size, config.refusion_band_m)
        out[s.input.id] = set(s.tiles).union(reach)
    return out


def _staged(progress: ProgressCallback | None, label: str) -> ProgressCallback | None:
    """``progress`` with ``label`` in front of every event's stage."""
    if progress is None:
        return None

    def report(ev: ProgressEvent) -> None:
        progress(ProgressEvent(ev.iteration, ev.total, ev.losses, f"{label} {ev.stage}"))

    return report


def _skip_or_raise(skipped: dict[str, str] | None, what: str, exc: FusionError) -> None:
    if skipped is None:
        raise exc
    skipped[what] = exc.message


def _align_regions(submaps: list[LoadedSubmap], keys: list[tuple[int, int]], config: FusionConfig,
                   tile_size: float, progress: ProgressCallback | None, refined: dict[str, Pose],
                   skipped: dict[str, str] | None, align_metrics: list[dict[str, Any]] | None,
                   fields: dict[tuple[int, int], dict[str, Any]], drifts: dict[str, Drift]) -> None:
    """Align every region of ``keys`` (all its submaps free); ``refined`` gets the aligned poses,
    ``fields`` each tile's field state (the reconstruction's warm start), ``drifts`` the drift corrections."""
    from fusion.align import align_region

    by_id = {s.input.id: s for s in submaps}
    found = regions({s.input.id: s.tiles for s in submaps}, only=keys)
    for r, region in enumerate(found):
        inputs = [replace(by_id[sid].input, pose_init=refined.get(sid, by_id[sid].pose_gps),
                          pose_gps=by_id[sid].pose_gps, free=True) for sid in region.submaps]
        label = f"region {r + 1}/{len(found)} ({len(region.tiles)} tiles)"
        try:
            aligned = align_region(inputs, [TileSpec(i, j, tile_size) for i, j in region.tiles], config,
                                   progress=_staged(progress, label))
        except FusionError as exc:
            _skip_or_raise(skipped, "region " + ",".join(f"{i}_{j}" for i, j in region.tiles), exc)
            continue
        refined.update(aligned.poses)
        fields.update(aligned.fields)
        for sid in region.submaps:  # a re-alignment finds each submap's drift anew
            drifts.pop(sid, None)
        drifts.update(aligned.drifts)
        if align_metrics is not None:
            align_metrics.append(aligned.metrics | {"tiles": [list(t) for t in region.tiles]})


def reconstruct_tiles(submaps: list[LoadedSubmap], keys: list[tuple[int, int]], config: FusionConfig,
                       tile_size: float, progress: ProgressCallback | None, poses: dict[str, Pose],
                       on_tile: Callable[[tuple[int, int], FusionResult], None] | None,
                       skipped: dict[str, str] | None,
                       previous: dict[tuple[int, int], FusionResult] | None = None,
                       warm: dict[tuple[int, int], dict[str, Any]] | None = None,
                       drifts: dict[str, Drift] | None = None,
                       carried: Collection[tuple[int, int]] = (),
                       ) -> dict[tuple[int, int], FusionResult]:
    """Each tile in order with every submap of it (:func:`members`) held at ``poses`` (else its GPS pose); neighbours
    reconstructed earlier (here, else in ``previous``: the tiles a re-fusion leaves as they are) pin the
    shared border. ``warm``: field states by tile to start from (``reconstruct_tile``).

    ``previous``: the map before a session was added (its submaps held where they were, the new ones
    aligned against it): a tile of it re-fused here starts from its own field instead, with
    ``refusion_warm_fraction`` of the steps; a tile of ``carried`` (its field in ``previous`` carried along with
    its surface by a re-alignment that brought it no new submap) with ``refusion_carried_fraction``.
    ``drifts``: each submap's drift correction (``fusion.drift``), if any."""
    from fusion.reconstruct import reconstruct_tile

    drifts = drifts or {}
    results: dict[tuple[int, int], FusionResult] = {}
    before = previous or {}

    def border_of(k: tuple[int, int]) -> dict[str, Any] | None:
        done = results.get(k) or before.get(k)
        return done.border if done is not None else None

    reach = members(submaps, poses, tile_size, config)
    for n, key in enumerate(keys):
        inputs = [corrected_input(replace(s.input, pose_init=poses.get(s.input.id, s.pose_gps), free=False),
                                  drifts.get(s.input.id)) for s in submaps if key in reach[s.input.id]]
        pins = tiles.border_pins(*key, border_of)
        label = f"tile {key[0]}_{key[1]} ({n + 1}/{len(keys)})"
        last = before.get(key)
        start: dict[str, Any] | None = (warm or {}).get(key)
        kind: WarmKind = "alignment"
        if last is not None and last.field_state is not None and config.refusion_warm_fraction > 0:
            start, kind = last.field_state, "carried" if key in carried else "reconstruction"
        try:
            result = reconstruct_tile(inputs, TileSpec(key[0], key[1], tile_size), config,
                                      progress=_staged(progress, label), border_pins=pins or None,
                                      warm=start, warm_kind=kind)
        except FusionError as exc:
            _skip_or_raise(skipped, f"{key[0]}_{key[1]}", exc)
            continue
        results[key] = result
        if on_tile is not None:
            on_tile(key, result)
    return results


def fuse_directory(in_dir: str | Path, out_dir: str | Path, config: FusionConfig, tile_size: float = 64.0,
                   origin: str | None = None, progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Fuse every submap in ``in_dir`` into ``out_dir`` (see the module docstring). Tiles are
    reconstructed in (i, j) order. Returns a summary: tiles, submaps, per-region alignment and per-tile
    metrics."""
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
    align: list[dict[str, Any]] = []
    drifts: dict[str, Drift] = {}
    done = fuse_tiles(submaps, keys, config, tile_size, progress, refined, on_tile=write_tile, skipped=skipped,
                      align_metrics=align, grow=True, drifts=drifts)
    keys = sorted(set(keys) | set(done))  # with the tiles only an aligned surface reaches
    poses = [{"session_id": s.input.session_id, "seq": s.input.seq, "id": s.input.id, "pose_gps": s.pose_gps.to_json(),
              "pose_refined": refined[s.input.id].to_json() if s.input.id in refined else None,
              "drift_refined": drifts[s.input.id].to_json() if s.input.id in drifts else None} for s in submaps]
    poses.sort(key=lambda p: (p["session_id"], p["seq"]))
    (out / "poses.json").write_text(json.dumps(poses, indent=1))
    summary = {"tiles": [list(k) for k in keys], "submaps": len(submaps), "tile_size_m": tile_size,
               "config": config.to_dict(), "metrics": tile_metrics, "alignment": align,
               "skipped": skipped}
    (out / "fusion.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary
