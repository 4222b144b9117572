"""What a job reads. A reconstruct job: the fusion config, the tile's aligned submaps held at their
refined poses, the neighbours' border pins, the tile's alignment field (the warm start), and the input
fingerprint that makes it idempotent. An
align job: every submap touching the region's tiles, the unaligned ones free.

Frames: submap meshes are in their local frame; ``pose_init`` maps local → map frame (the refined pose
once an alignment refined it, else the GPS pose).
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import select, tuple_
from sqlalchemy.orm import Session

from fusion.config import FusionConfig
from fusion.drift import Drift, corrected_input
from fusion.meshio import MeshLimits, read_submap_ply
from fusion.tiles import border_pins
from fusion.types import Pose, Sigma, SubmapInput, TileSpec, WarmKind, quat_to_matrix, rotation_angle_deg
from service.settings import Settings, fusion_config
from service.store.blobs import BlobStore
from service.store.models import Submap, SubmapTile, Tile, TileVersion


@dataclass
class TileInputs:
    """Everything ``reconstruct_tile`` needs for one tile, plus the fingerprint of it.

    ``submaps`` is empty until :func:`load_meshes` read the mesh blobs (the fingerprint needs none).
    """

    tile: TileSpec
    config: FusionConfig
    rows: list[tuple[Submap, Pose, bool]]  # (submap row, initial local → map pose, free)
    fingerprint: str
    submaps: list[SubmapInput] = field(default_factory=list)
    border_pins: dict[str, Any] = field(default_factory=dict)
    pending: int = 0  # submaps of the tile still waiting for their alignment (left out)
    # the field blob the reconstruction starts from: the tile's last reconstruction's (a re-fusion after an
    # incremental alignment: ``refusion_warm_fraction`` of the steps), else its last alignment's
    warm_sha256: str | None = None
    warm_kind: WarmKind = "alignment"  # or "reconstruction", "carried" (``reconstruct_tile``)
    warm: bytes | None = None  # its bytes (a serialised state dict), read by load_meshes


@dataclass
class RegionInputs:
    """What an align job needs: the region's tiles and every submap touching them (unaligned ones free,
    the others held at their refined poses: the map they are aligned against)."""

    tiles: list[TileSpec]
    config: FusionConfig
    rows: list[tuple[Submap, Pose, bool]]  # (submap row, initial local → map pose, free)
    fields: dict[tuple[int, int], str] = field(default_factory=dict)  # tile → the map's field blob (frozen)
    submaps: list[SubmapInput] = field(default_factory=list)

    @property
    def free(self) -> list[str]:
        return [s.id for s, _, free in self.rows if free]

    @property
    def held(self) -> int:
        """How many submaps are held (the map the free ones are aligned against)."""
        return sum(not free for _, _, free in self.rows)


def _pose_init(submap: Submap) -> Pose:
    return Pose.from_json(submap.pose_refined or submap.pose_gps)


def fingerprint(tile: TileSpec, config: FusionConfig, submaps: list[tuple[Submap, Pose, bool]],
                warm_sha256: str | None = None) -> str:
    """sha256 over the tile, the fusion config, the sorted submap ids, mesh hashes, initial poses and
    the field the reconstruction starts from (if any)."""
    doc = {
        "tile": [tile.i, tile.j, tile.size_m],
        "config": config.to_dict(),
        # a held submap's drift correction shapes it too (listed only where there is one: the fingerprints of
        # tiles fused before it existed are unchanged)
        "submaps": sorted([s.id, s.mesh_sha256, pose.to_json(), free, *_held_drift(s, free)] for s, pose, free in submaps),
    }
    if warm_sha256 is not None:
        doc["warm"] = warm_sha256
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def pack_border(border: dict[str, Any]) -> bytes:
    """``FusionResult.border`` (side → array, or side → {name: array}) as ``.npz`` bytes."""
    flat: dict[str, np.ndarray] = {}
    for side, value in border.items():
        if isinstance(value, dict):
            for name, array in value.items():
                flat[f"{side}/{name}"] = np.asarray(array)
        else:
            flat[side] = np.asarray(value)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **flat)  # type: ignore[arg-type]  # the attribute planes are mostly NaN
    return buffer.getvalue()


def unpack_border(data: bytes) -> dict[str, Any]:
    """Inverse of :func:`pack_border`."""
    border: dict[str, Any] = {}
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        for key in npz.files:
            value = npz[key]
            plain = value.item() if value.ndim == 0 else value
            if "/" in key:
                side, name = key.split("/", 1)
                border.setdefault(side, {})[name] = plain
            else:
                border[key] = plain
    return border


def _border_pins(db: Session, blobs: BlobStore, i: int, j: int) -> dict[str, Any]:
    """Border samples of fused neighbours, keyed by our side (their opposite side's samples)."""

    def border_of(key: tuple[int, int]) -> dict[str, Any] | None:
        border_sha = db.execute(
            select(TileVersion.border_sha256)
            .where(TileVersion.tile_i == key[0], TileVersion.tile_j == key[1])
            .order_by(TileVersion.version.desc())
            .limit(1)
        ).scalar_one_or_none()
        return unpack_border(blobs.get(border_sha)) if border_sha else None

    return border_pins(i, j, border_of)


def _submaps_touching(db: Session, keys: list[tuple[int, int]]) -> list[Submap]:
    found: dict[str, Submap] = {}
    for i, j in keys:
        rows = db.execute(
            select(Submap).join(SubmapTile, SubmapTile.submap_id == Submap.id).where(SubmapTile.i == i, SubmapTile.j == j)
        ).scalars()
        found.update((s.id, s) for s in rows)
    return sorted(found.values(), key=lambda s: (s.session_id, s.seq))


def shapes_tile(submap: Submap, i: int, j: int) -> bool:
    """Whether the aligned ``submap``'s surface reaches tile (i, j) at its refined pose (within
    ``refusion_band_m``; ``Submap.surface_tiles``); one aligned before those were recorded counts."""
    return submap.surface_tiles is None or [i, j] in submap.surface_tiles


def plan_tile(db: Session, settings: Settings, i: int, j: int) -> TileInputs:
    """The aligned submaps of tile (i, j), every one held at its refined pose (the alignment owns the
    poses); those still waiting for an alignment are counted in ``pending`` and left out. The warm start:
    the tile's last reconstruction field (its held submaps have not moved since, or moved by cm to dm: an
    incremental alignment only adds submaps, a re-alignment by registration only trains no field) with
    ``refusion_warm_fraction`` of the steps (``refusion_carried_fraction`` where a re-alignment carried it
    and brought the tile no new submap: ``Tile.recon_field_carried``), else its last alignment field (none
    when the fraction is 0). The fingerprint names the alignment field (where warm starts are on), never the
    reconstruction's (every version changes it), and only the submaps whose surface reaches the tile
    (:func:`shapes_tile`): a tile whose submaps and poses are unchanged, or that a new submap only grazes,
    is not fused again (the grazing submap is in the tile's next fusion, whatever brings it)."""
    tile = TileSpec(i, j, settings.tile_size)
    config = fusion_config(settings)
    submaps = _submaps_touching(db, [(i, j)])
    rows = [(s, _pose_init(s), False) for s in submaps if s.pose_refined]
    row = db.get(Tile, (i, j))
    aligned = row.align_field_sha256 if row is not None else None
    warm: str | None = None
    kind: WarmKind = "alignment"
    if row is not None and row.recon_field_sha256 and config.refusion_warm_fraction > 0:
        warm, kind = row.recon_field_sha256, "carried" if row.recon_field_carried else "reconstruction"
    elif aligned and config.recon_warm_fraction > 0:
        warm = aligned
    shaping = [r for r in rows if shapes_tile(r[0], i, j)]
    return TileInputs(tile=tile, config=config, rows=rows,
                      fingerprint=fingerprint(tile, config, shaping, aligned if config.recon_warm_fraction > 0 else None),
                      pending=len(submaps) - len(rows), warm_sha256=warm, warm_kind=kind)


def plan_alignment(db: Session, settings: Settings, keys: list[tuple[int, int]], realign: bool = False) -> RegionInputs:
    """Every submap touching the region's tiles: the unaligned ones free (at their GPS poses), the
    aligned ones held at their refined poses; and the map's fields in those tiles, the new submaps are
    tracked against: each tile's last reconstruction field (``align_track_reconstruction``), else its
    alignment field. ``realign`` (a joint re-alignment): free too, from its refined pose, is every aligned
    submap whose tiles all lie in ``keys`` (the others, reaching tiles outside, hold the region's border);
    no field is frozen."""
    config = fusion_config(settings)
    submaps = _submaps_touching(db, keys)
    inside: set[str] = set()
    if realign:
        outside = set(db.execute(
            select(SubmapTile.submap_id)
            .where(SubmapTile.submap_id.in_([s.id for s in submaps]), tuple_(SubmapTile.i, SubmapTile.j).not_in(keys))
        ).scalars())
        inside = {s.id for s in submaps} - outside
    rows = [(s, _pose_init(s), s.pose_refined is None or s.id in inside) for s in submaps]
    fields = {}
    for i, j in keys if not realign else []:
        tile = db.get(Tile, (i, j))
        if tile is None:
            continue
        blob = (config.align_track_reconstruction and tile.recon_field_sha256) or tile.align_field_sha256
        if blob:
            fields[(i, j)] = blob
    return RegionInputs([TileSpec(i, j, settings.tile_size) for i, j in keys],
                        config.for_realignment() if realign else config, rows, fields)


def _held_drift(submap: Submap, free: bool) -> list[dict[str, Any]]:
    """The stored drift correction a held submap is fused with (``fusion.drift``), as a 0- or 1-item list: a
    free submap's is found anew by its alignment."""
    return [submap.drift_refined] if submap.drift_refined and not free else []


def load_submaps(
    blobs: BlobStore, settings: Settings, rows: list[tuple[Submap, Pose, bool]]
) -> list[SubmapInput]:
    """The fusion inputs of ``rows``: mesh blobs read and validated, poses and sigmas; a held submap
    corrected by its stored drift (the refined pose is the corrected submap's)."""
    limits = MeshLimits(max_faces=settings.max_faces, max_coordinate_m=settings.max_coordinate_m)
    return [
        corrected_input(SubmapInput(
            id=s.id,
            session_id=s.session_id,
            seq=s.seq,
            mesh=read_submap_ply(blobs.get(s.mesh_sha256), limits),
            pose_init=pose,
            odometry=Pose.from_json(s.odometry),
            gps_sigma=Sigma(s.gps_sigma_trans_m, s.gps_sigma_rot_deg),
            odometry_sigma=Sigma(s.odometry_sigma_trans_m, s.odometry_sigma_rot_deg),
            free=free,
            pose_gps=Pose.from_json(s.pose_gps),
        ), next((Drift.from_json(d) for d in _held_drift(s, free)), None))
        for s, pose, free in rows
    ]


def load_meshes(db: Session, blobs: BlobStore, settings: Settings, inputs: TileInputs) -> None:
    """Read the submap meshes, the neighbours' border pins and the warm-start field into ``inputs``."""
    inputs.submaps = load_submaps(blobs, settings, inputs.rows)
    inputs.border_pins = _border_pins(db, blobs, inputs.tile.i, inputs.tile.j)
    inputs.warm = blobs.get(inputs.warm_sha256) if inputs.warm_sha256 else None


def pose_change(a: Pose, b: Pose) -> tuple[float, float]:
    """Translation (metres) and rotation angle (degrees) between two local → map poses."""
    trans = float(np.linalg.norm(np.asarray(a.t) - np.asarray(b.t)))
    return trans, float(rotation_angle_deg(quat_to_matrix(a.q).T @ quat_to_matrix(b.q)))
