"""Recording a finished fusion: blobs first, then ONE transaction for version, poses, tile and job.

Every tile write is conditional on our lease (``lease_owner = <us>``): a worker whose lease was taken
away writes nothing. The tile becomes ``fused`` only if no upload arrived since the job started
(its ``dirty_generation`` is unchanged), else ``dirty`` again so the new submaps get fused later.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from dataclasses import dataclass
from datetime import datetime
from enum import StrEnum
from typing import Any

import numpy as np
from sqlalchemy import func, literal, select, update
from sqlalchemy.orm import Session, sessionmaker

from fusion.drift import Drift
from fusion.meshio import write_fused_ply, write_glb
from fusion.types import FusionResult, Pose
from service.store import tiles
from service.store.blobs import BlobStore
from service.store.db import insert_ignore
from service.store.models import (
    FusionJob,
    JobKind,
    JobState,
    JobTrigger,
    Submap,
    SubmapTile,
    TileVersion,
    UTCDateTime,
    new_id,
    utcnow,
)
from worker.inputs import TileInputs, pack_border
from worker.lease import Claim

log = logging.getLogger(__name__)



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
    field_sha256: str | None = None


def store_blobs(blobs: BlobStore, result: FusionResult) -> StoredBlobs:
    """Write the fused mesh as PLY and GLB, the border samples as ``.npz`` and the trained field (the
    next re-fusion's warm start) before any row names them."""
    from fusion.field import pack_state

    border = blobs.put(pack_border(result.border)) if result.border else None
    field = blobs.put(pack_state(result.field_state)) if result.field_state is not None else None
    return StoredBlobs(blobs.put(write_fused_ply(result.mesh)), blobs.put(write_glb(result.mesh)), border, field)


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


def _finish(
    db: Session, claim: Claim, now: datetime, *, new_version: bool, pending: bool, field_sha256: str | None = None
) -> tuple[int, str] | None:
    return tiles.finish(db, claim.i, claim.j, owner=claim.owner, generation=claim.generation,
                        started_at=claim.started_at, now=now, new_version=new_version, pending=pending,
                        field_sha256=field_sha256)


def commit_success(
    factory: sessionmaker[Session],
    claim: Claim,
    inputs: TileInputs,
    result: FusionResult,
    stored: StoredBlobs,
    duration_s: float,
) -> Outcome:
    """ONE transaction: tile version, tile state, job. ``succeeded``/``lost``. The poses were written
    by the alignment; a reconstruction never moves one, so it never makes another tile dirty."""
    now = utcnow()
    with factory() as db:
        finished = _finish(db, claim, now, new_version=True, pending=inputs.pending > 0,
                           field_sha256=stored.field_sha256)
        if finished is None:
            db.rollback()
            log.warning("job %s: lease lost before commit; results discarded", claim.job_id)
            return Outcome.lost
        version, state = finished
        metrics = jsonable(dict(result.metrics))
        metrics.update(
            submaps=len(inputs.rows),
            pending_submaps=inputs.pending,
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
        _job_succeeded(db, claim, now, inputs.fingerprint, {**metrics, "version": version})
        db.commit()
    log.info("tile (%d, %d) fused: version %d, state %s", claim.i, claim.j, version, state)
    return Outcome.succeeded


def _job_succeeded(
    db: Session, claim: Claim, now: datetime, fingerprint: str | None, metrics: dict[str, Any]
) -> None:
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
        finished = _finish(db, claim, now, new_version=False, pending=inputs.pending > 0)
        if finished is None:
            db.rollback()
            return Outcome.lost
        version, _ = finished
        _job_succeeded(db, claim, now, inputs.fingerprint,
                       {"reused_version": version, "submaps": len(inputs.rows)})
        db.commit()
    log.info("tile (%d, %d): inputs unchanged since version %d; no new version", claim.i, claim.j, version)
    return Outcome.reused


def _join_surface_tiles(
    db: Session, surface: dict[str, list[tuple[int, int]]], leased: set[tuple[int, int]], now: datetime
) -> list[tuple[int, int]]:
    """A submap whose aligned surface reaches a tile its GPS-padded box did not (a GPS error beyond its
    sigma) joins that tile: a membership row, and the tile, where this job does not hold it, marked dirty
    (created if new) so the scheduler fuses it with the submap. Returns those tiles."""
    ids = sorted(surface)
    have = {(sid, int(i), int(j)) for sid, i, j in db.execute(
        select(SubmapTile.submap_id, SubmapTile.i, SubmapTile.j).where(SubmapTile.submap_id.in_(ids)))}
    new = [(sid, int(i), int(j)) for sid in ids for i, j in surface[sid] if (sid, int(i), int(j)) not in have]
    if not new:
        return []
    insert_ignore(db, SubmapTile, [{"submap_id": sid, "i": i, "j": j} for sid, i, j in new])
    reached = {(i, j) for _, i, j in new}
    outside = sorted(reached - leased)
    tiles.mark_dirty(db, outside, now, upload=True)
    log.info("%d aligned submaps reach %d tiles their GPS did not; tiles %s marked dirty",
             len({sid for sid, _, _ in new}), len(reached), outside)
    return outside


def commit_alignment(
    factory: sessionmaker[Session],
    claim: Claim,
    poses: dict[str, Pose],
    fields: dict[tuple[int, int], str],
    metrics: dict[str, Any],
    surface: dict[str, list[tuple[int, int]]] | None = None,
    *,
    incremental: bool = False,
    drifts: dict[str, Drift] | None = None,
    kept: list[tuple[int, int]] | None = None,
    carried: dict[tuple[int, int], str] | None = None,
    quiet: Collection[tuple[int, int]] = (),
) -> tuple[Outcome, list[str]]:
    """ONE transaction: the refined pose of every aligned submap (written once: only where none was; a
    joint re-alignment, ``claim.realign``, rewrites them) with the tiles its surface reaches there
    (``surface``, by submap id; ``Submap.surface_tiles``) and whether it was aligned against a held map
    (``incremental``) and its drift correction (``drifts``, by submap id; none: NULL), a reconstruct job for each of the region's tiles (each tile handed from this lease to
    its job, ``queued``, with the blob of the field trained there, if any, which replaces the tile's
    reconstruction field as its warm start), the align job ``succeeded``. A tile in ``kept`` (a re-alignment
    left its surface where its mesh has it: ``fusion.placement.settle_realignment``) goes back to ``fused``
    instead where nothing marked it since its last fusion (``tiles.settle``). A tile in ``carried`` (tile → blob:
    its last reconstruction field carried along with its surface, ``FusionConfig.refusion_carry``) takes that
    blob as its reconstruction field, its re-fusion's start (with fewer steps where the tile is in ``quiet``: no
    new submap reaches it, ``Tile.recon_field_carried``). Returns the outcome and the new jobs to enqueue."""
    now = utcnow()
    with factory() as db:
        for submap_id, pose in sorted(poses.items()):
            db.execute(
                update(Submap)
                .where(Submap.id == submap_id, *(() if claim.realign else (Submap.pose_refined.is_(None),)))
                .values(pose_refined=pose.to_json(),
                        drift_refined=drifts[submap_id].to_json() if drifts and submap_id in drifts else None,
                        refined_at=func.coalesce(Submap.refined_at, literal(now, UTCDateTime())),
                        aligned_incrementally=incremental,
                        surface_tiles=[list(t) for t in surface[submap_id]] if surface and submap_id in surface else None)
            )
        joined = _join_surface_tiles(db, surface or {}, set(claim.tiles), now)
        jobs, settled, keep = [], [], set(kept or ())
        for i, j in claim.tiles:
            if (i, j) in keep and tiles.settle(db, i, j, owner=claim.owner, now=now):
                settled.append([i, j])
                continue
            job = FusionJob(id=new_id(), tile_i=i, tile_j=j, kind=JobKind.reconstruct.value, state=JobState.queued.value,
                            trigger=JobTrigger.auto.value, created_at=now, enqueued_at=now)
            if not tiles.hand_over(db, i, j, owner=claim.owner, job_id=job.id, now=now, field_sha256=fields.get((i, j)),
                                   recon_field_sha256=(carried or {}).get((i, j)), quiet=(i, j) in quiet):
                db.rollback()
                log.warning("job %s: lease lost before commit; alignment discarded", claim.job_id)
                return Outcome.lost, []
            db.add(job)
            jobs.append(job.id)
        _job_succeeded(db, claim, now, None, jsonable({**metrics, "aligned_submaps": len(poses),
                                                       "reconstruct_jobs": jobs, "joined_tiles": joined,
                                                       "kept_tiles": settled}))
        db.commit()
    log.info("region %s aligned: %d submap poses, %d tiles to reconstruct, %d kept", claim.tiles, len(poses), len(jobs),
             len(settled))
    return Outcome.succeeded, jobs
