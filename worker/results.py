"""Recording a finished fusion: blobs first, then ONE transaction for version, poses, tile and job.

Every tile write is conditional on our lease (``lease_owner = <us>``): a worker whose lease was taken
away writes nothing. The tile becomes ``fused`` only if no upload arrived since the job started
(its ``dirty_generation`` is unchanged), else ``dirty`` again so the new submaps get fused later.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Any

import numpy as np
from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from fusion.meshio import write_fused_ply, write_glb
from fusion.types import FusionResult
from service.store import tiles
from service.store.blobs import BlobStore
from service.store.models import FusionJob, JobState, Submap, SubmapTile, TileVersion, utcnow
from worker.inputs import TileInputs, pack_border, pose_change
from worker.lease import Claim

log = logging.getLogger(__name__)

# A free submap that moved more than this marks the other tiles it touches dirty (multi-tile consistency).
MOVE_THRESHOLD_M = 0.05
MOVE_THRESHOLD_DEG = 0.1


class Outcome(StrEnum):
    """How :func:`run_fusion_job` ended."""

    succeeded = "succeeded"  # a new tile version
    reused = "reused"  # inputs unchanged since the latest version: no new version
    failed = "failed"  # job and tile failed; the previous version is still served
    skipped = "skipped"  # finished already, or the tile is leased by another worker
    lost = "lost"  # the lease was taken away; another worker re-runs the job



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


def _finish(db: Session, claim: Claim, now: datetime, *, new_version: bool) -> tuple[int, str] | None:
    return tiles.finish(db, claim.i, claim.j, owner=claim.owner, generation=claim.generation,
                        started_at=claim.started_at, now=now, new_version=new_version)


def _mark_tiles_dirty(
    db: Session, claim: Claim, submap_ids: list[str], now: datetime
) -> list[tuple[int, int]]:
    """The other tiles touched by ``submap_ids`` need a re-fusion: their held poses changed."""
    touched = db.execute(
        select(SubmapTile.i, SubmapTile.j).where(SubmapTile.submap_id.in_(submap_ids)).distinct()
    ).all()
    others = sorted((int(i), int(j)) for i, j in touched if (i, j) != (claim.i, claim.j))
    tiles.mark_dirty(db, others, now, upload=False)
    return others


def commit_success(
    factory: sessionmaker[Session],
    claim: Claim,
    inputs: TileInputs,
    result: FusionResult,
    stored: StoredBlobs,
    duration_s: float,
) -> Outcome:
    """ONE transaction: tile version, refined poses, tile state, job, neighbours. ``succeeded``/``lost``."""
    now = utcnow()
    with factory() as db:
        previous = db.execute(
            select(TileVersion.metrics)
            .where(TileVersion.tile_i == claim.i, TileVersion.tile_j == claim.j)
            .order_by(TileVersion.version.desc())
            .limit(1)
        ).first()
        finished = _finish(db, claim, now, new_version=True)
        if finished is None:
            db.rollback()
            log.warning("job %s: lease lost before commit; results discarded", claim.job_id)
            return Outcome.lost
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
    return Outcome.succeeded


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


def commit_reused(factory: sessionmaker[Session], claim: Claim, inputs: TileInputs) -> Outcome:
    """The latest version already used exactly these inputs: finish without a new version."""
    now = utcnow()
    with factory() as db:
        finished = _finish(db, claim, now, new_version=False)
        if finished is None:
            db.rollback()
            return Outcome.lost
        version, _ = finished
        _job_succeeded(db, claim, now, inputs.fingerprint,
                       {"reused_version": version, "submaps": len(inputs.rows)})
        db.commit()
    log.info("tile (%d, %d): inputs unchanged since version %d; no new version", claim.i, claim.j, version)
    return Outcome.reused
