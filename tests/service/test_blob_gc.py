"""Blob garbage collection: superseded fields and unfinished writes go, everything a row names stays."""

from __future__ import annotations

import os
import time
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest

from service import cli, schedule
from service.settings import get_settings
from service.store.blobs import FileBlobStore
from service.store.gc import collect, referenced
from service.store.models import Tile
from tests.worker_support import FakeAlign, FakeFusion, in_process, upload
from worker import runner
from worker.runner import run_fusion_job

TWO_DAYS_S = 2 * 24 * 3600.0


def _age(store: FileBlobStore, seconds: float) -> None:
    """Every blob of ``store`` last written ``seconds`` ago."""
    then = time.time() - seconds
    for blob in store.list_blobs():
        path = store.path(blob.sha256)
        assert path is not None
        os.utime(path, (then, then))


def _fuse_region(client: Any) -> str | None:
    """Align the region of tile (0, 0), then run each of its tiles' reconstruct jobs; returns tile (0, 0)'s
    reconstruction field between the two (a re-alignment's carried field: ``FusionConfig.refusion_carry``)."""
    with client.db() as db:
        job = schedule.request_fusion(db, 0, 0, settings=client.settings).id
    run_fusion_job(job, client.settings, session_factory=client.db, blob_store=client.app.state.blobs)
    with client.db() as db:
        jobs = [t.job_id for t in db.query(Tile).all() if t.state == "queued"]
        between = db.get(Tile, (0, 0)).recon_field_sha256
    for job in jobs:
        run_fusion_job(job, client.settings, session_factory=client.db, blob_store=client.app.state.blobs)
    return between


def test_gc_removes_superseded_fields_and_unfinished_writes_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from fusion.config import FusionConfig
    from worker import inputs

    monkeypatch.setattr(inputs, "fusion_config",  # re-fusions from the tile's own field, as in the cpu preset
                        lambda settings: FusionConfig.preset(settings.fusion_preset).with_(recon_warm_fraction=1 / 3))
    monkeypatch.setattr(runner, "_align", FakeAlign())
    monkeypatch.setattr(runner, "_fuse", FakeFusion())
    with in_process(tmp_path) as client:
        store = client.app.state.blobs
        assert isinstance(store, FileBlobStore)
        upload(client, "veh-1/a", 0, [10.0, 10.0, 0.0])
        _fuse_region(client)
        with client.db() as db:
            first = db.get(Tile, (0, 0)).recon_field_sha256
        # the tile is fused again (its region re-aligned: half its sessions came incrementally), from its field
        # carried along with its surface: a new field replaces both
        upload(client, "veh-2/b", 0, [12.0, 10.0, 0.0])
        carried = _fuse_region(client)
        superseded = [first, carried]
        with client.db() as db:
            tile = db.get(Tile, (0, 0))
            assert tile.version == 2 and tile.recon_field_sha256 not in (None, first, carried)
            assert carried not in (None, first)
            named = referenced(db)
        assert not set(superseded) & named and all(store.exists(sha) for sha in superseded)
        unfinished = store.put(b"a blob whose row never committed")
        retried = store.put(b"an upload whose first try failed before its row")
        _age(store, TWO_DAYS_S)
        young = store.put(b"a blob a job is about to name")
        assert store.put(b"an upload whose first try failed before its row") == retried  # written again: young

        with client.db() as db:
            dry = collect(store, referenced(db), dry_run=True)
            assert sorted(dry.removed) == sorted([*superseded, unfinished])
            assert dry.young == 2 and dry.referenced == len(named)
            assert store.exists(first) and store.exists(unfinished)
            report = collect(store, referenced(db))
        assert sorted(report.removed) == sorted([*superseded, unfinished])
        assert not any(store.exists(sha) for sha in [*superseded, unfinished])
        assert store.exists(young) and store.exists(retried) and all(store.exists(sha) for sha in named)
        assert client.get("/v1/tiles/0/0/mesh").status_code == 200
        for version in (1, 2):  # the history stays downloadable
            assert client.get(f"/v1/tiles/0/0/mesh?version={version}").status_code == 200
        with client.db() as db:
            assert sorted(collect(store, referenced(db), min_age=timedelta(0)).removed) == sorted([young, retried])
        with pytest.raises(ValueError, match="negative"):
            collect(store, set(), min_age=timedelta(hours=-1))
        settings = client.settings

    # the operator's command, on the same embedded data directory
    monkeypatch.setenv("FLEETMAP_DATA_DIR", str(settings.data_dir))
    for name in ("FLEETMAP_DATABASE_URL", "FLEETMAP_BROKER_URL", "FLEETMAP_BLOB_URL"):
        monkeypatch.delenv(name, raising=False)
    get_settings.cache_clear()
    try:
        leftover = store.put(b"another unfinished write")
        _age(store, TWO_DAYS_S)
        assert cli.main(["blobs", "gc", "--dry-run", "--verbose"]) == 0
        out = capsys.readouterr().out
        assert leftover in out and "would remove 1 unreferenced blobs" in out and store.exists(leftover)
        assert cli.main(["blobs", "gc", "--min-age-hours", "1"]) == 0
        assert "removed 1 unreferenced blobs" in capsys.readouterr().out and not store.exists(leftover)
        assert cli.main(["blobs", "gc", "--min-age-hours", "-1"]) == 2
        assert "min-age-hours" in capsys.readouterr().err
    finally:
        get_settings.cache_clear()


def test_gc_removes_dead_writers_partial_files_once_old(tmp_path: Path) -> None:
    """A writer killed between creating its ``.tmp-*`` file and renaming it leaves the file behind: the
    collection removes it once older than the grace period (a young one may be a write in progress), and
    never lists it as a blob."""
    store = FileBlobStore(tmp_path / "blobs")
    sha = store.put(b"a blob")
    folder = store.path(sha).parent  # type: ignore[union-attr]
    dead, live = folder / ".tmp-dead", folder / ".tmp-live"
    dead.write_bytes(b"x" * 1000)
    live.write_bytes(b"y" * 10)
    then = time.time() - TWO_DAYS_S
    os.utime(dead, (then, then))
    assert [b.sha256 for b in store.list_blobs()] == [sha]
    dry = collect(store, {sha}, dry_run=True)
    assert (dry.partial, dry.partial_bytes) == (1, 1000) and dead.exists()
    report = collect(store, {sha})
    assert (report.partial, report.partial_bytes, report.removed) == (1, 1000, [])
    assert not dead.exists() and live.exists() and store.exists(sha)
    assert "1 partial writes" in report.summary()
