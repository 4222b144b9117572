"""Fusion workers under faults, on the production stack: PostgreSQL, Redis (Celery), `fleetmap serve`
with its scheduler, real `fleetmap worker` processes.

One scenario (worker start-up and fusions are the expensive part): a burst of uploads to three
tiles; the first worker is SIGKILLed in the middle of a fusion; two fresh workers then share the
queue. Afterwards every tile is ``fused`` with exactly one version, no tile was ever fused by two
jobs at once, the killed job was re-run to success, and every submap got its refined pose.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from service.store.models import FusionJob, JobState, Submap, Tile, TileState, TileVersion
from tests.production_support import Deployment, deployment, post_submap, small_mesh, submap_meta, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.slow]

# Map-frame x of each tile's submaps: tiles (0, 0), (2, 0) and (4, 0) with 64 m tiles; a 16 m scene
# at x0 + [0, 16] stays inside its tile.
TILE_X = {(0, 0): 20.0, (2, 0): 148.0, (4, 0): 276.0}


def _upload_burst(dep: Deployment, base: str) -> set[tuple[str, int]]:
    """Two vehicles upload two submaps into each tile; returns the (session, seq) acknowledged."""
    sent = set()
    seeds = itertools.count()
    with httpx.Client(base_url=base, timeout=30) as client:
        for vehicle in ("veh-a", "veh-b"):
            session = f"{vehicle}/burst"
            for seq, ((_, _), x) in enumerate(
                (tile, x + dx) for tile, x in TILE_X.items() for dx in (0.0, 4.0)
            ):
                meta = submap_meta(session, seq, [x, 20.0 + (8.0 if vehicle == "veh-b" else 0.0), 0.0])
                response = post_submap(client, dep.headers, meta, small_mesh(next(seeds)))
                assert response.status_code == 201, response.text
                sent.add((session, seq))
    return sent


def _running_job(dep: Deployment) -> FusionJob | None:
    with dep.session() as db:
        return db.scalars(select(FusionJob).where(FusionJob.state == JobState.running.value)).first()


def _all_fused(dep: Deployment) -> bool:
    with dep.session() as db:
        tiles = db.scalars(select(Tile)).all()
        failed = [t for t in tiles if t.state == TileState.failed.value]
        assert not failed, [(t.i, t.j, t.last_error) for t in failed]
        return len(tiles) == len(TILE_X) and all(
            t.state == TileState.fused.value and t.fused_generation == t.dirty_generation for t in tiles
        )


def test_killed_worker_is_replaced_and_two_workers_never_fuse_one_tile_twice(tmp_path: Path) -> None:
    with deployment(tmp_path, lease_s="4", fuse_requeue_s="3") as dep:
        try:
            _, base = dep.api()
            # The first worker runs the full CPU schedule, so it is surely still fusing when killed.
            doomed = dep.worker("worker-doomed", FLEETMAP_FUSION_PRESET="cpu")
            sent = _upload_burst(dep, base)

            victim = wait_until(lambda: _running_job(dep), 180, "a fusion job running on the first worker")
            doomed.kill()
            with dep.session() as db:
                job = db.get(FusionJob, victim.id)
                assert job is not None and job.state == JobState.running.value, "killed too late"

            # Two fresh workers take over: the expired lease is reclaimed and the job re-sent.
            dep.worker("worker-1")
            dep.worker("worker-2")
            wait_until(lambda: _all_fused(dep), 240, "all tiles fused", interval_s=0.5)
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{dep.logs()}") from None

        with dep.session() as db:
            for tile in db.scalars(select(Tile)):
                versions = db.scalar(
                    select(func.count()).where(TileVersion.tile_i == tile.i, TileVersion.tile_j == tile.j)
                )
                assert (tile.version, versions) == (1, 1), f"tile ({tile.i}, {tile.j})"
            # No two fusions of one tile overlapped in time.
            jobs = db.scalars(select(FusionJob).where(FusionJob.started_at.is_not(None))).all()
            for (i, j), group in itertools.groupby(
                sorted(jobs, key=lambda job: (job.tile_i, job.tile_j, job.started_at)),
                key=lambda job: (job.tile_i, job.tile_j),
            ):
                ordered = list(group)
                for earlier, later in itertools.pairwise(ordered):
                    assert earlier.finished_at is not None and earlier.finished_at <= later.started_at, (
                        f"tile ({i}, {j}): jobs {earlier.id} and {later.id} overlap"
                    )
            killed = db.get(FusionJob, victim.id)
            assert killed is not None and killed.state == JobState.succeeded.value
            assert killed.attempts >= 2
            # Every acknowledged submap is stored and was used: its home tile's fusion refined it.
            submaps = db.scalars(select(Submap)).all()
            assert {(s.session_id, s.seq) for s in submaps} == sent
            assert all(s.pose_refined is not None for s in submaps)
