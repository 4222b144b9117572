"""Scheduler behaviour: debounce / max wait, one alignment and one reconstruction per burst,
re-dirtying, lease, sweeper.

Uploads go through the real app (httpx TestClient, SQLite); the scheduler is ticked with an injected
``now``; jobs run in-process with a fake fusion (tests/worker_support.py) so no torch training runs.
"""

from __future__ import annotations

import subprocess
import sys
from datetime import timedelta
from typing import Any

import pytest
from sqlalchemy import select, update

from fusion.errors import FusionError
from fusion.field import unpack_state
from service import schedule as scheduler
from service.store.models import FusionJob, JobState, Tile, TileVersion, utcnow
from tests.worker_support import (
    FakeAlign,
    FakeFusion,
    api,
    in_process,
    make_settings,
    session_factory,
    upload,
)
from worker import runner
from worker.lease import claim_job
from worker.runner import run_fusion_job


@pytest.fixture
def fake(monkeypatch: pytest.MonkeyPatch) -> FakeFusion:
    fusion = FakeFusion(shift=0.0)
    monkeypatch.setattr(runner, "_fuse", fusion)
    return fusion


@pytest.fixture
def align(monkeypatch: pytest.MonkeyPatch) -> FakeAlign:
    aligner = FakeAlign(shift=0.0)
    monkeypatch.setattr(runner, "_align", aligner)
    return aligner


@pytest.fixture
def env(tmp_path: Any) -> Any:
    with in_process(tmp_path) as client:
        yield client


def tile_row(client: Any, i: int = 0, j: int = 0) -> Tile:
    with client.db() as db:
        tile = db.get(Tile, (i, j))
        assert tile is not None
        return tile


def run(client: Any, job_id: str) -> str:
    return run_fusion_job(
        job_id, client.settings, session_factory=client.db, blob_store=client.app.state.blobs
    )


def tick(client: Any, after_s: float) -> scheduler.TickReport:
    """Tick at ``after_s`` seconds after tile (0, 0)'s last upload."""
    now = tile_row(client).last_upload_at + timedelta(seconds=after_s)
    with client.db() as db:
        return scheduler.tick(db, now, client.settings)


def current_job(client: Any, i: int = 0, j: int = 0) -> str:
    """The id of the tile's latest job."""
    job_id = tile_row(client, i, j).job_id
    assert job_id is not None
    return job_id


def kind(client: Any, job_id: str) -> str:
    return str(client.get(f"/v1/jobs/{job_id}").json()["kind"])


def align_then_reconstruct(client: Any, *keys: tuple[int, int]) -> None:
    """Run the region's align job (the current job of the first tile), then each tile's reconstruct job."""
    job_id = current_job(client, *keys[0])
    assert kind(client, job_id) == "align"
    assert run(client, job_id) == "succeeded"
    for key in keys:
        assert client.get(f"/v1/tiles/{key[0]}/{key[1]}").json()["state"] == "queued"
        job_id = current_job(client, *key)
        assert kind(client, job_id) == "reconstruct"
        assert run(client, job_id) == "succeeded"


def jobs_of(client: Any, i: int = 0, j: int = 0) -> list[FusionJob]:
    with client.db() as db:
        query = select(FusionJob).where(FusionJob.tile_i == i, FusionJob.tile_j == j)
        return list(db.execute(query.order_by(FusionJob.created_at)).scalars())


def test_debounce_then_one_alignment_and_one_reconstruction_per_burst(
    env: Any, fake: FakeFusion, align: FakeAlign
) -> None:
    for seq in range(5):
        upload(env, "veh-1/a", seq, [10.0 + seq, 10.0, 0.0])
    assert env.get("/v1/tiles/0/0").json()["state"] == "dirty"
    assert tick(env, 10).scheduled == []  # not quiet for 30 s yet
    assert tick(env, 31).scheduled == [(0, 0)]
    assert tick(env, 32).scheduled == []  # already queued: no second job
    (job,) = jobs_of(env)
    assert env.get("/v1/tiles/0/0").json()["state"] == "queued"
    align.shift = 0.2
    align_then_reconstruct(env, (0, 0))
    assert len(align.calls) == 1 and [s.free for s in align.calls[0][1]] == [True] * 5
    assert len(fake.calls) == 1 and [s.free for s in fake.calls[0][1]] == [False] * 5  # poses held
    assert [s.pose_init.t[0] for s in fake.calls[0][1]] == pytest.approx([10.2, 11.2, 12.2, 13.2, 14.2])
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"], body["progress"]) == ("fused", 1, 1.0)
    assert tick(env, 1000).scheduled == []
    assert env.get(f"/v1/jobs/{job.id}").json()["state"] == "succeeded"


def test_max_wait_schedules_a_tile_that_never_goes_quiet(env: Any) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    dirty_since = tile_row(env).dirty_since
    assert dirty_since is not None
    for after_s in (100.0, 599.0):  # uploads keep coming every few seconds
        now = dirty_since + timedelta(seconds=after_s)
        with env.db() as db:
            db.execute(update(Tile).values(last_upload_at=now - timedelta(seconds=2)))
            db.commit()
            assert scheduler.tick(db, now, env.settings).scheduled == []
    now = dirty_since + timedelta(seconds=601)
    with env.db() as db:
        db.execute(update(Tile).values(last_upload_at=now - timedelta(seconds=2)))
        db.commit()
        assert scheduler.tick(db, now, env.settings).scheduled == [(0, 0)]


def test_uploads_during_fusion_are_aligned_then_fused_again(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    assert run(env, current_job(env)) == "succeeded"  # the alignment
    fake.during = lambda: upload(env, "veh-1/a", 1, [12.0, 10.0, 0.0])
    assert run(env, current_job(env)) == "succeeded"
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"], body["submaps"]) == ("dirty", 1, 2)
    fake.during = None
    assert tick(env, 31).scheduled == [(0, 0)]
    align_then_reconstruct(env, (0, 0))
    assert [s.free for s in align.calls[-1][1]] == [False, True]  # the map is held, the new submap aligned
    # ... tracked against the field the tile's first reconstruction left (the fake's first call)
    assert set(align.frozen) == {(0, 0)} and unpack_state(align.frozen[(0, 0)])["w"].item() == 1.0
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"]) == ("fused", 2)
    assert len(fake.calls[-1][1]) == 2


def test_a_submap_uploaded_during_reconstruction_keeps_the_tile_dirty(
    env: Any, fake: FakeFusion, align: FakeAlign
) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    assert run(env, current_job(env)) == "succeeded"
    upload(env, "veh-1/a", 1, [12.0, 10.0, 0.0])  # after the alignment, before the reconstruction started
    assert run(env, current_job(env)) == "succeeded"
    assert [s.seq for s in fake.calls[-1][1]] == [0]  # the unaligned submap is left out ...
    assert env.get("/v1/tiles/0/0").json()["state"] == "dirty"  # ... and still pending


def test_one_fusion_per_tile_and_one_active_job(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    first = env.post("/v1/tiles/0/0/fuse")
    second = env.post("/v1/tiles/0/0/fuse")
    assert first.status_code == second.status_code == 202
    assert first.json()["job_id"] == second.json()["job_id"]
    job_id = first.json()["job_id"]
    assert kind(env, job_id) == "align"  # an unaligned submap: its region is aligned first
    with env.db() as db:
        assert claim_job(db, job_id, "other-worker", env.settings) is not None
    assert env.get("/v1/tiles/0/0").json()["state"] == "fusing"
    assert run(env, job_id) == "skipped"  # the lease is held elsewhere
    assert align.calls == [] and fake.calls == []
    with env.db() as db:
        assert claim_job(db, job_id, "third-worker", env.settings) is None
    assert env.post("/v1/tiles/0/0/fuse").json()["job_id"] == job_id  # still the running job


def test_failed_fusion_keeps_serving_the_previous_version(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    align_then_reconstruct(env, (0, 0))
    etag = env.get("/v1/tiles/0/0/mesh").headers["etag"]
    upload(env, "veh-1/a", 1, [12.0, 10.0, 0.0])
    tick(env, 31)
    assert run(env, current_job(env)) == "succeeded"
    fake.error = FusionError("the optimisation diverged")
    failed_id = current_job(env)
    assert run(env, failed_id) == "failed"
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"]) == ("failed", 1)
    assert "diverged" in body["last_error"]
    job = env.get(f"/v1/jobs/{failed_id}").json()
    assert job["state"] == "failed" and "diverged" in job["error"]
    mesh = env.get("/v1/tiles/0/0/mesh")
    assert mesh.status_code == 200 and mesh.headers["etag"] == etag
    assert tick(env, 1000).scheduled == []  # no new upload: no automatic retry loop
    fake.error = None
    upload(env, "veh-1/a", 2, [14.0, 10.0, 0.0])
    assert tick(env, 31).scheduled == [(0, 0)]
    align_then_reconstruct(env, (0, 0))
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"], body["last_error"]) == ("fused", 2, None)


def test_one_alignment_writes_each_pose_once_for_all_its_tiles(
    env: Any, fake: FakeFusion, align: FakeAlign
) -> None:
    # x ∈ [48, 68] with the GPS margin: touches tiles (0, 0) and (1, 0), linked into one region.
    created = upload(env, "veh-1/a", 0, [50.0, 10.0, 0.0])
    assert sorted(map(tuple, created["tiles"])) == [(0, 0), (1, 0)]
    upload(env, "veh-1/a", 1, [10.0, 10.0, 0.0])
    upload(env, "veh-9/far", 0, [1000.0, 10.0, 0.0])  # another region: aligned on its own
    report = tick(env, 31)
    assert sorted(report.scheduled) == [(0, 0), (1, 0), (15, 0)]
    align_job = current_job(env)
    assert current_job(env, 1, 0) == align_job
    assert env.get(f"/v1/jobs/{align_job}").json()["tiles"] == [[0, 0], [1, 0]]
    align.shift = 0.3
    align_then_reconstruct(env, (0, 0), (1, 0))
    refined = env.get(f"/v1/submaps/{created['id']}").json()["pose_refined"]
    assert refined["t"] == pytest.approx([50.3, 10.0, 0.0])
    poses = env.get("/v1/sessions/veh-1%2Fa/poses").json()
    assert [p["seq"] for p in poses] == [0, 1]
    assert poses[0]["pose_refined"]["t"] == pytest.approx([50.3, 10.0, 0.0])
    held = fake.calls[-1][1]  # tile (1, 0) holds the submap at its refined pose
    assert [s.pose_init.t[0] for s in held] == pytest.approx([50.3])
    assert tick(env, 31).scheduled == []  # no cascade: the reconstructions moved nothing
    assert [env.get(f"/v1/tiles/{i}/0").json()["version"] for i in (0, 1)] == [1, 1]


def test_rerunning_a_job_is_idempotent(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    align_id = current_job(env)
    align_then_reconstruct(env, (0, 0))
    job_id = current_job(env)
    assert run(env, align_id) == "skipped"  # a duplicate delivery of a finished alignment
    assert run(env, job_id) == "skipped"  # ... and of a finished reconstruction
    again = env.post("/v1/tiles/0/0/fuse").json()["job_id"]
    assert kind(env, again) == "reconstruct"  # everything aligned: the tile alone
    assert run(env, again) == "reused"  # same inputs and config as version 1
    with env.db() as db:
        versions = db.execute(select(TileVersion.version)).scalars().all()
    assert versions == [1]
    assert env.get(f"/v1/jobs/{again}").json()["metrics"]["reused_version"] == 1
    assert env.get("/v1/tiles/0/0").json()["state"] == "fused"
    assert len(fake.calls) == 1 and len(align.calls) == 1


def test_sweeper_reclaims_expired_leases_then_gives_up(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    job_id = current_job(env)
    for attempt in range(1, scheduler.MAX_ATTEMPTS + 1):
        with env.db() as db:
            claim = claim_job(db, job_id, f"dead-worker-{attempt}", env.settings)
            assert claim is not None  # the worker "dies" holding the lease
        expired = utcnow() + timedelta(seconds=env.settings.lease_s + 1)
        with env.db() as db:
            report = scheduler.tick(db, expired, env.settings)
        assert report.reclaimed_tiles == [(0, 0)]
        state = env.get("/v1/tiles/0/0").json()["state"]
        assert state == ("queued" if attempt < scheduler.MAX_ATTEMPTS else "failed")
    job = env.get(f"/v1/jobs/{job_id}").json()
    assert job["state"] == "failed" and "worker lost" in job["error"]
    assert fake.calls == [] and align.calls == []


def test_sweeper_resends_jobs_whose_broker_message_was_lost(tmp_path: Any, monkeypatch: Any) -> None:
    settings = make_settings(tmp_path, broker_url="redis://127.0.0.1:1/0")
    sent: list[str] = []
    monkeypatch.setattr(scheduler, "enqueue", lambda job_id, *_: sent.append(job_id) or True)
    with api(settings) as client:
        upload(client, "veh-1/a", 0, [10.0, 10.0, 0.0])
        factory = session_factory(client.app)
        with factory() as db:
            last = db.get(Tile, (0, 0)).last_upload_at
            assert scheduler.tick(db, last + timedelta(seconds=31), settings).scheduled == [(0, 0)]
        assert len(sent) == 1
        with factory() as db:
            later = last + timedelta(seconds=31 + settings.fuse_requeue_s / 2)
            assert scheduler.tick(db, later, settings).requeued_jobs == []
            later = last + timedelta(seconds=32 + settings.fuse_requeue_s)
            assert scheduler.tick(db, later, settings).requeued_jobs == sent[:1]
        assert sent == [sent[0], sent[0]]
        with factory() as db:
            assert db.get(FusionJob, sent[0]).state == JobState.queued.value


def test_the_api_process_does_not_import_torch(tmp_path: Any) -> None:
    code = f"""
import sys
from fastapi.testclient import TestClient
from service.api.app import create_app
from service import schedule as scheduler
from tests.worker_support import make_settings, session_factory
from pathlib import Path
settings = make_settings(Path({str(tmp_path)!r}), broker_url="memory://")
with TestClient(create_app(settings, migrate=True, background=False)) as client:
    assert client.get("/healthz").status_code == 200
    with session_factory(client.app)() as db:
        scheduler.tick(db, None, settings)
    scheduler.enqueue("some-job", settings)
assert "torch" not in sys.modules, "the API process imported torch"
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.integration
def test_concurrent_ticks_queue_each_tile_once_on_postgresql(tmp_path: Any) -> None:
    """Several API processes tick at once: the conditional UPDATE admits exactly one of them."""
    import threading

    from tests.production_support import fresh_database, pg_reachable

    if (why := pg_reachable()) is not None:
        pytest.skip(why)
    with fresh_database() as url:
        settings = make_settings(tmp_path, database_url=url)
        with api(settings) as client:
            for seq in range(3):
                upload(client, "veh-1/pg", seq, [10.0 + 20 * seq, 10.0 + 20 * seq, 0.0])
            factory = session_factory(client.app)
            with factory() as db:
                last = max(t.last_upload_at for t in db.execute(select(Tile)).scalars())
            now = last + timedelta(seconds=31)
            reports: list[scheduler.TickReport] = []
            barrier = threading.Barrier(4)

            def tick_once() -> None:
                barrier.wait()
                with factory() as db:
                    reports.append(scheduler.tick(db, now, settings))

            threads = [threading.Thread(target=tick_once) for _ in range(4)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join(60)
            scheduled = sorted(t for r in reports for t in r.scheduled)
            with factory() as db:
                tiles = sorted((t.i, t.j) for t in db.execute(select(Tile)).scalars())
                jobs = db.execute(select(FusionJob)).scalars().all()
            assert scheduled == tiles  # every tile once, by exactly one ticker
            assert len(jobs) == 1 and jobs[0].kind == "align"  # one session: one region, one alignment
            assert sorted(tuple(t) for t in jobs[0].tiles) == tiles
            client.app.state.engine.dispose()


def test_an_alignment_whose_worker_died_is_run_again_and_loses_nothing(
    env: Any, fake: FakeFusion, align: FakeAlign
) -> None:
    created = upload(env, "veh-1/a", 0, [50.0, 10.0, 0.0])  # a region of two tiles
    upload(env, "veh-1/a", 1, [10.0, 10.0, 0.0])
    tick(env, 31)
    job_id = current_job(env)
    with env.db() as db:
        assert claim_job(db, job_id, "dead-worker", env.settings) is not None  # dies holding both leases
    assert [env.get(f"/v1/tiles/{i}/0").json()["state"] for i in (0, 1)] == ["fusing", "fusing"]
    expired = utcnow() + timedelta(seconds=env.settings.lease_s + 1)
    with env.db() as db:
        report = scheduler.tick(db, expired, env.settings)
    assert sorted(report.reclaimed_tiles) == [(0, 0), (1, 0)] and set(report.requeued_jobs) == {job_id}
    assert env.get(f"/v1/submaps/{created['id']}").json()["pose_refined"] is None  # nothing half-written
    align.shift = 0.1
    align_then_reconstruct(env, (0, 0), (1, 0))
    assert env.get(f"/v1/submaps/{created['id']}").json()["pose_refined"]["t"] == pytest.approx([50.1, 10.0, 0.0])
    assert env.get(f"/v1/jobs/{job_id}").json()["state"] == "succeeded"


def test_a_tile_with_no_surface_is_fused_empty(env: Any, fake: FakeFusion, align: FakeAlign) -> None:
    upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])
    tick(env, 31)
    assert run(env, current_job(env)) == "succeeded"
    fake.error = FusionError("the submaps near tile (0, 0) have no surface inside it", code="empty_tile")
    assert run(env, current_job(env)) == "succeeded"
    body = env.get("/v1/tiles/0/0").json()
    assert (body["state"], body["version"]) == ("fused", 1)
    assert env.get("/v1/tiles/0/0/mesh").status_code == 200
