"""The one fusion job runner, used by the Celery task and by the embedded worker.

A job runs under a *lease* on its tile (``worker.lease``), so at most one fusion of a tile runs at a
time and a dead worker's tile is reclaimed by the sweeper (``service.schedule``). Every write after
the fusion checks that the lease is still ours.

It is idempotent: a job that already finished is ignored, and a job whose inputs (submaps, their
initial poses, the fusion config) equal the latest version's finishes without a new version.
Results land in ONE transaction: the new tile version, the refined poses of the tile's home submaps,
the tile state (``fused``, or ``dirty`` when uploads arrived during the fusion) and the job.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from functools import lru_cache
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from fusion.drift import Drift, corrected_input
from fusion.errors import FusionError, FusionLibraryError
from fusion.field import moved_state, pack_state, unpack_state
from fusion.placement import motion_report, quiet_tiles, settle_realignment, tile_carry
from fusion.tiles import surface_tiles
from fusion.types import FusedMesh, FusionResult, Pose
from service.broker import enqueue
from service.settings import Settings, get_settings
from service.store.blobs import BlobStore, blob_store_from_url
from service.store.db import engine_from_settings, make_sessionmaker
from service.store.models import JobKind, Tile, TileVersion, utcnow
from worker import metrics, results
from worker.inputs import RegionInputs, TileInputs, load_meshes, load_submaps, plan_alignment, plan_tile
from worker.lease import Claim, LeaseKeeper, LeaseLost, claim_job, release
from worker.results import Outcome

log = logging.getLogger(__name__)


class WorkerShutdown(BaseException):
    """Raised in a worker that was asked to stop: the job goes back to ``queued``."""


class TransientJobError(Exception):
    """A database, broker or storage hiccup: the job was put back to ``queued`` and may be retried."""


def is_transient(exc: BaseException) -> bool:
    """Errors worth a retry with backoff (connections), as opposed to fusion errors (not retried)."""
    from sqlalchemy.exc import InterfaceError, OperationalError

    if isinstance(exc, OperationalError | InterfaceError | ConnectionError | TimeoutError):
        return True
    try:
        from redis.exceptions import ConnectionError as RedisConnectionError
        from redis.exceptions import TimeoutError as RedisTimeoutError
    except ImportError:
        return False
    return isinstance(exc, RedisConnectionError | RedisTimeoutError)


def worker_identity() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


@lru_cache(maxsize=4)
def factory_for(database_url: str) -> sessionmaker[Session]:
    settings = get_settings().model_copy(update={"database_url": database_url})
    return make_sessionmaker(engine_from_settings(settings))


def _error_message(exc: BaseException) -> str:
    from celery.exceptions import SoftTimeLimitExceeded

    if isinstance(exc, SoftTimeLimitExceeded):
        return "fusion exceeded its time limit"
    if isinstance(exc, FusionLibraryError):
        return f"{exc.code}: {exc.message}"
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _torch_threads() -> None:
    threads = get_settings().torch_threads  # FLEETMAP_TORCH_THREADS: leave cores to a co-located API
    if threads:
        import torch

        torch.set_num_threads(threads)


def _fuse(inputs: TileInputs, keeper: LeaseKeeper) -> FusionResult:
    """Reconstruct one tile with every pose held, from its last reconstruction's or alignment's field
    where it has one (torch: imported in the worker process only)."""
    from fusion.field import unpack_state
    from fusion.reconstruct import reconstruct_tile

    _torch_threads()
    warm = unpack_state(inputs.warm) if inputs.warm else None
    return reconstruct_tile(
        inputs.submaps, inputs.tile, inputs.config, progress=keeper, border_pins=inputs.border_pins or None,
        warm=warm, warm_kind=inputs.warm_kind,
    )


def _align(
    inputs: RegionInputs, keeper: LeaseKeeper, frozen: dict[tuple[int, int], bytes]
) -> tuple[dict[str, Pose], dict[str, Any], dict[tuple[int, int], bytes], dict[str, Drift]]:
    """Align the region's free submaps against the rest, tracking them against the ``frozen`` fields of
    earlier alignments (serialised state dicts) where a tile has one. Returns the refined poses (map
    frame), metrics, the fields trained here (serialised), by tile, and the drift corrections found
    (``fine_drift``), by submap."""
    from fusion.align import align_region
    from fusion.field import pack_state, unpack_state

    _torch_threads()
    states = {key: unpack_state(data) for key, data in frozen.items()}
    result = align_region(inputs.submaps, inputs.tiles, inputs.config, progress=keeper, frozen=states or None)
    trained = {key: pack_state(state) for key, state in result.fields.items() if key not in frozen}
    return result.poses, result.metrics, trained, result.drifts


def _settle(inputs: RegionInputs, poses: dict[str, Pose], drifts: dict[str, Drift], keys: list[tuple[int, int]],
            tile_size: float) -> tuple[dict[str, Pose], list[tuple[int, int]], dict[tuple[int, int], float],
                                       dict[tuple[int, int], np.ndarray]]:
    """A re-alignment by registration alone (``fusion.placement.settle_realignment``): its poses (with
    ``realign_hold``, the map held where the refined poses had it), the tiles whose surface did not move,
    each tile's motion, and the rigid motion each other tile's field is carried by (``refusion_carry``;
    ``fusion.placement.tile_carry``)."""
    config = inputs.config
    before = {row.id: Pose.from_json(row.pose_refined) for row, _, free in inputs.rows if free and row.pose_refined}
    shaped = {row.id: Drift.from_json(row.drift_refined) for row, _, free in inputs.rows
              if free and row.pose_refined and row.drift_refined}
    settled, kept, moved = settle_realignment(
        inputs.submaps, before, poses, keys, tile_size=tile_size, band_m=config.refusion_band_m,
        hold=config.realign_hold, keep_m=config.realign_keep_m, drifts_before=shaped, drifts_after=drifts)
    carry = tile_carry(inputs.submaps, before, settled, [k for k in keys if k not in kept], tile_size,
                       config.refusion_band_m, shaped, drifts) if config.refusion_carry else {}
    return settled, kept, moved, carry


def _carried_fields(factory: sessionmaker[Session], blobs: BlobStore,
                    carry: dict[tuple[int, int], np.ndarray]) -> dict[tuple[int, int], str]:
    """Each tile's last reconstruction field carried by its motion (``fusion.field.moved_state``), stored
    as a new blob (durable before a row names it): tile → blob. Tiles without such a field are absent."""
    with factory() as db:
        stored = {key: tile.recon_field_sha256 for key in carry
                  if (tile := db.get(Tile, key)) is not None and tile.recon_field_sha256}
    return {key: blobs.put(pack_state(moved_state(unpack_state(blobs.get(sha)), carry[key])))
            for key, sha in stored.items()}


def _run_alignment(
    factory: sessionmaker[Session], blobs: BlobStore, settings: Settings, claim: Claim, keeper: LeaseKeeper
) -> Outcome:
    with factory() as db:
        inputs = plan_alignment(db, settings, claim.tiles, claim.realign)
    poses: dict[str, Pose] = {}
    drifts: dict[str, Drift] = {}
    kept: list[tuple[int, int]] = []
    carried: dict[tuple[int, int], str] = {}
    quiet: list[tuple[int, int]] = []
    surface: dict[str, list[tuple[int, int]]] = {}
    fields: dict[tuple[int, int], str] = {}
    metrics: dict[str, Any] = {"submaps": len(inputs.rows), "free_submaps": len(inputs.free), "realign": claim.realign}
    if inputs.free:  # none: a re-run after the poses were committed; only the hand-over is left
        inputs.submaps = load_submaps(blobs, settings, inputs.rows)
        log.info("aligning region %s: %d submaps, %d free, %d tiles with a field, job %s", claim.tiles,
                 len(inputs.rows), len(inputs.free), len(inputs.fields), claim.job_id)
        frozen = {key: blobs.get(sha) for key, sha in inputs.fields.items()}
        poses, align_metrics, trained, drifts = _align(inputs, keeper, frozen)
        metrics.update(align_metrics)
        if claim.realign and not trained:  # by registration alone: tiles it did not move keep their mesh
            poses, kept, moved, carry = _settle(inputs, poses, drifts, claim.tiles, settings.tile_size)
            metrics["tile_moved_m"] = motion_report(moved)
            carried = _carried_fields(factory, blobs, carry)
            quiet = quiet_tiles(carried, moved)
            metrics["carried_tiles"] = [list(key) for key in sorted(carried)]
            metrics["quiet_tiles"] = [list(key) for key in quiet]
        posed = [corrected_input(s, drifts.get(s.id)) for s in inputs.submaps if s.id in poses]
        surface = {s.id: surface_tiles(s.mesh.vertices, s.mesh.faces, poses[s.id], settings.tile_size,
                                       inputs.config.refusion_band_m) for s in posed}
        fields = {key: blobs.put(data) for key, data in trained.items()}  # durable before rows name them
    if keeper.lost.is_set():
        raise LeaseLost(f"lease of job {claim.job_id} lost")
    outcome, jobs = results.commit_alignment(factory, claim, poses, fields, metrics, surface,
                                             incremental=inputs.held > 0 and not claim.realign, drifts=drifts,
                                             kept=kept, carried=carried, quiet=quiet)
    for job_id in jobs:
        enqueue(job_id, settings, JobKind.reconstruct.value)
    return outcome


def _run_reconstruction(
    factory: sessionmaker[Session], blobs: BlobStore, settings: Settings, claim: Claim, keeper: LeaseKeeper
) -> Outcome:
    started = time.monotonic()
    with factory() as db:
        inputs = plan_tile(db, settings, claim.i, claim.j)
        latest = db.execute(
            select(TileVersion.input_fingerprint, TileVersion.created_at)
            .where(TileVersion.tile_i == claim.i, TileVersion.tile_j == claim.j)
            .order_by(TileVersion.version.desc())
            .limit(1)
        ).one_or_none()
        unchanged = latest is not None and latest[0] == inputs.fingerprint
        if not unchanged:
            if not inputs.rows:
                raise ValueError("the tile holds no aligned submap")
            load_meshes(db, blobs, settings, inputs)
    if unchanged:
        return results.commit_reused(factory, claim, inputs)
    log.info("fusing tile (%d, %d): %d submaps, job %s", claim.i, claim.j, len(inputs.rows), claim.job_id)
    try:
        result = _fuse(inputs, keeper)
    except FusionError as exc:
        if exc.code != "empty_tile":
            raise
        # The tile's submaps only graze it (their GPS uncertainty reaches it, their surface does not):
        # it is fused, with nothing in it, rather than failed.
        result = FusionResult(FusedMesh.empty(), {}, {"empty": exc.message}, inputs.config.to_dict(), {})
    if keeper.lost.is_set():
        raise LeaseLost(f"lease of tile ({claim.i}, {claim.j}) lost")
    blob_ids = results.store_blobs(blobs, result)
    outcome = results.commit_success(factory, claim, inputs, result, blob_ids, time.monotonic() - started)
    if outcome is Outcome.succeeded:
        previous = latest[1] if latest is not None else None
        metrics.submaps_fused(
            [s.created_at for s, _, _ in inputs.rows
             if previous is None or (s.refined_at is not None and s.refined_at > previous)],
            utcnow(),
        )
    return outcome


def run_fusion_job(
    job_id: str,
    settings: Settings | None = None,
    *,
    session_factory: sessionmaker[Session] | None = None,
    blob_store: BlobStore | None = None,
) -> Outcome:
    """Run fusion job ``job_id`` to its end; returns the :class:`Outcome`.

    Raises :class:`TransientJobError` after putting the job back to ``queued`` on a transient error,
    and re-raises :class:`WorkerShutdown` likewise.
    """
    settings = settings or get_settings()
    factory = session_factory or factory_for(settings.resolved_database_url)
    blobs = blob_store or blob_store_from_url(settings.resolved_blob_url)
    owner = f"{worker_identity()}:{job_id}"
    with factory() as db:
        claim = claim_job(db, job_id, owner, settings)
    if claim is None:
        return Outcome.skipped
    started = time.monotonic()
    metrics.job_started(claim.kind, claim.queued_since, claim.started_at)
    label, code = "failed", None
    try:
        outcome, label = _run_claimed(job_id, factory, blobs, settings, claim)
    except WorkerShutdown:
        label = "interrupted"
        raise
    except TransientJobError:
        label = "transient"
        raise
    except _Failed as failed:
        code = failed.code
        return Outcome.failed
    finally:
        metrics.job_finished(claim.kind, label, time.monotonic() - started, code)
    return outcome


class _Failed(Exception):
    """A job that ended ``failed`` (recorded already), with its error code for the metrics."""

    def __init__(self, code: str) -> None:
        super().__init__(code)
        self.code = code


def _run_claimed(
    job_id: str, factory: sessionmaker[Session], blobs: BlobStore, settings: Settings, claim: Claim
) -> tuple[Outcome, str]:
    """Run a claimed job; returns its outcome and the outcome's metrics label. Raises :class:`_Failed`
    for a job that failed (recorded), :class:`TransientJobError` and :class:`WorkerShutdown`."""
    run = _run_alignment if claim.kind == JobKind.align.value else _run_reconstruction
    try:
        with LeaseKeeper(factory, claim) as keeper:
            outcome = run(factory, blobs, settings, claim, keeper)
    except LeaseLost as exc:
        log.warning("job %s: %s; another worker re-runs it", job_id, exc)
        return Outcome.lost, Outcome.lost.value
    except WorkerShutdown:
        log.warning("job %s interrupted by shutdown; back to queued", job_id)
        release(factory, claim, error=None)
        raise
    except Exception as exc:
        if is_transient(exc):
            log.warning("job %s: transient error %s; back to queued", job_id, exc)
            try:
                release(factory, claim, error=None)
            except Exception as release_exc:  # the sweeper reclaims the lease when it expires
                log.warning("job %s: could not release the lease: %s", job_id, release_exc)
            raise TransientJobError(str(exc)) from exc
        message = _error_message(exc)
        log.error("%s job %s of tile(s) %s failed: %s", claim.kind, job_id, claim.tiles, message, exc_info=exc)
        release(factory, claim, error=message)
        raise _Failed(metrics.error_code(exc)) from exc
    return outcome, outcome.value
