"""Recording a finished fusion: blobs first, then ONE transaction for version, poses, tile and job.

Every tile write is conditional on our lease (``lease_owner = <us>``): a worker whose lease was taken
away writes nothing. The tile becomes ``fused`` only if no upload arrived since the job started
(its ``dirty_generation`` is unchanged), else ``dirty`` again so the new submaps get fused later.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import case, func, literal, null, select, update
from sqlalchemy.orm import Session, sessionmaker

from fusion.meshio import write_fused_ply, write_glb
from fusion.types import FusionResult
from service.store.blobs import BlobStore
from service.store.models import FusionJob, JobState, Submap, SubmapTile, Tile, TileState, TileVersion, utcnow
from worker.inputs import TileInputs, pack_border, pose_change

if TYPE_CHECKING:
    from worker.runner import Claim

log = logging.getLogger(__name__)

# A free submap that moved more than this marks the other tiles it touches dirty (multi-tile consistency).
MOVE_THRESHOLD_M = 0.05
MOVE_THRESHOLD_DEG = 0.1


@dataclass
class StoredBlobs:
    mesh_sha256: str
    glb_sha256: str
    border_sha256: str | None


def store_blobs(blobs: BlobStore, result: FusionResult) -> StoredBlobs:
    """Write the fused mesh as PLY and GLB and the border samples as ``.npz`` (before any row names them)."""
    border = blobs.put(pack_border(result.border)) if result.border else None
    return StoredBlobs(blobs.put(write_fused_ply(result.mesh)), blobs.put(write_glb(result.mesh)), border)


def jsonable(value: Any) -> Any:
    """``value`` with numpy scalars/arrays turned into plain JSON types."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def _at(value: datetime) -> Any:
    """A datetime literal typed like the tiles' columns (UTC on every backend)."""
    return literal(value, type_=Tile.__table__.c.dirty_since.type)


def finish_tile(db: Session, claim: Claim, now: datetime, *, new_version: bool) -> tuple[int, str] | None:
    """Release our lease and set the tile ``fused`` (or ``dirty`` after concurrent uploads).

    Returns ``(version, state)``, or None when the lease is no longer ours (nothing written).
    """
    unchanged = Tile.dirty_generation == claim.generation
    values: dict[str, Any] = {
        "state": case((unchanged, TileState.fused.value), else_=TileState.dirty.value),
        "dirty_since": case(
            (unchanged, null()), else_=func.coalesce(Tile.dirty_since, _at(claim.started_at))
        ),
        "fused_generation": claim.generation,
        "lease_owner": None,
        "lease_until": None,
        "progress": 1.0,
        "last_error": None,
        "updated_at": now,
    }
    if new_version:
        values.update(version=Tile.version + 1, fused_at=now)
    row = db.execute(
        update(Tile)
        .where(Tile.i == claim.i, Tile.j == claim.j, Tile.lease_owner == claim.owner)
        .values(**values)
        .returning(Tile.version, Tile.state)
        .execution_options(synchronize_session=False)
    ).one_or_none()
    return None if row is None else (int(row[0]), str(row[1]))


def _store_refined_poses(db: Session, inputs: TileInputs, result: FusionResult, now: datetime) -> list[str]:
    """Write the refined poses of the tile's home (free) submaps; returns the ids that moved."""
    free = {s.id for s, _, is_free in inputs.rows if is_free}
    moved = []
    for submap_id, pose in result.poses.items():
        if submap_id not in free:
            continue
        db.execute(
            update(Submap).where(Submap.id == submap_id).values(pose_refined=pose.to_json(), refined_at=now)
        )
        trans_m, rot_deg = pose_change(inputs.pose_init[submap_id], pose)
        if trans_m > MOVE_THRESHOLD_M or rot_deg > MOVE_THRESHOLD_DEG:
            moved.append(submap_id)
    return moved


def _mark_tiles_dirty(
    db: Session, claim: Claim, submap_ids: list[str], now: datetime
) -> list[tuple[int, int]]:
    """The other tiles touched by ``submap_ids`` need a re-fusion: their held poses changed."""
    tiles = db.execute(
        select(SubmapTile.i, SubmapTile.j).where(SubmapTile.submap_id.in_(submap_ids)).distinct()
    ).all()
    others = [(int(i), int(j)) for i, j in tiles if (i, j) != (claim.i, claim.j)]
    for i, j in others:
        db.execute(
            update(Tile)
            .where(Tile.i == i, Tile.j == j)
            .values(
                dirty_generation=Tile.dirty_generation + 1,
                dirty_since=func.coalesce(Tile.dirty_since, _at(now)),
                state=case((Tile.state == TileState.fused.value, TileState.dirty.value), else_=Tile.state),
                updated_at=now,
            )
            .execution_options(synchronize_session=False)
        )
    return others


def commit_success(
    factory: sessionmaker[Session],
    claim: Claim,
    inputs: TileInputs,
    result: FusionResult,
    stored: StoredBlobs,
    duration_s: float,
) -> str:
    """ONE transaction: tile version, refined poses, tile state, job, neighbours. ``succeeded``/``lost``."""
    now = utcnow()
    with factory() as db:
        previous = db.execute(
            select(TileVersion.metrics)
            .where(TileVersion.tile_i == claim.i, TileVersion.tile_j == claim.j)
            .order_by(TileVersion.version.desc())
            .limit(1)
        ).first()
        finished = finish_tile(db, claim, now, new_version=True)
        if finished is None:
            db.rollback()
            log.warning("job %s: lease lost before commit; results discarded", claim.job_id)
            return "lost"
        version, state = finished
        metrics = jsonable(dict(result.metrics))
        metrics.update(
            submaps=len(inputs.rows),
            free_submaps=sum(1 for _, _, free in inputs.rows if free),
            faces=int(len(result.mesh.faces)),
            vertices=int(len(result.mesh.vertices)),
            wall_s=round(duration_s, 3),
        )
        db.add(
            TileVersion(
                tile_i=claim.i,
                tile_j=claim.j,
                version=version,
                job_id=claim.job_id,
                mesh_sha256=stored.mesh_sha256,
                glb_sha256=stored.glb_sha256,
                border_sha256=stored.border_sha256,
                input_fingerprint=inputs.fingerprint,
                metrics=metrics,
                fusion_config=jsonable(result.config or inputs.config.to_dict()),
                created_at=now,
            )
        )
        moved = _store_refined_poses(db, inputs, result, now)
        # Pose changes propagate when this fusion used new submaps (damping: a re-fusion caused only by
        # a neighbour's pose change does not bounce back, so the map settles tile by tile).
        had = (previous[0] or {}).get("submaps", 0) if previous else 0
        dirtied = _mark_tiles_dirty(db, claim, moved, now) if moved and len(inputs.rows) > had else []
        _job_succeeded(db, claim, now, inputs.fingerprint,
                       {**metrics, "version": version, "moved_submaps": len(moved), "tiles_dirtied": dirtied})
        db.commit()
    log.info(
        "tile (%d, %d) fused: version %d, state %s, %d submaps moved",
        claim.i,
        claim.j,
        version,
        state,
        len(moved),
    )
    return "succeeded"


def _job_succeeded(db: Session, claim: Claim, now: datetime, fingerprint: str, metrics: dict[str, Any]) -> None:
    """Mark the claimed job succeeded with ``metrics`` (inside the caller's transaction)."""
    db.execute(
        update(FusionJob)
        .where(FusionJob.id == claim.job_id)
        .values(
            state=JobState.succeeded.value,
            progress=1.0,
            finished_at=now,
            error=None,
            input_fingerprint=fingerprint,
            metrics=metrics,
        )
    )


def commit_reused(factory: sessionmaker[Session], claim: Claim, inputs: TileInputs) -> str:
    """The latest version already used exactly these inputs: finish without a new version."""
    now = utcnow()
    with factory() as db:
        finished = finish_tile(db, claim, now, new_version=False)
        if finished is None:
            db.rollback()
            return "lost"
        version, _ = finished
        _job_succeeded(db, claim, now, inputs.fingerprint,
                       {"reused_version": version, "submaps": len(inputs.rows)})
        db.commit()
    log.info("tile (%d, %d): inputs unchanged since version %d; no new version", claim.i, claim.j, version)
    return "reused"
