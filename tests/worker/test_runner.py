"""The job runner's outcomes and attempt counting (in-process, SQLite, a fake fusion).

``fusion_jobs.attempts`` counts runs that failed or whose worker died (the sweeper gives up after
``MAX_ATTEMPTS``); a graceful stop hands the job back without burning one.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from fusion.errors import FusionError
from service import schedule
from service.store import tiles
from service.store.models import FusionJob, JobState, Tile, TileState, utcnow
from tests.worker_support import FakeAlign, FakeFusion, in_process, never_realign, upload
from worker import runner
from worker.results import Outcome
from worker.runner import WorkerShutdown, run_fusion_job


@pytest.fixture
def env(tmp_path: Any) -> Any:
    with in_process(tmp_path) as client:
        upload(client, "veh-1/a", 0, [10.0, 10.0, 0.0])
        with client.db() as db:
            client.job_id = schedule.request_fusion(db, 0, 0, settings=client.settings).id  # type: ignore[attr-defined]
        yield client


def _run(env: Any) -> Outcome:
    return run_fusion_job(env.job_id, env.settings, session_factory=env.db, blob_store=env.app.state.blobs)


def _job_and_tile(env: Any) -> tuple[FusionJob, Tile]:
    with env.db() as db:
        return db.get(FusionJob, env.job_id), db.get(Tile, (0, 0))


def _stop_three_times(env: Any, monkeypatch: pytest.MonkeyPatch, hook: str, fake: Any) -> None:
    for _ in range(3):  # more graceful stops than MAX_ATTEMPTS: the job must stay runnable
        monkeypatch.setattr(runner, hook, fake)
        with pytest.raises(WorkerShutdown):
            _run(env)
        job, tile = _job_and_tile(env)
        assert (job.state, job.attempts, tile.state) == (JobState.queued.value, 0, TileState.queued.value)
        assert tile.lease_owner is None


def test_a_stopped_worker_hands_its_job_back_without_burning_an_attempt(
    env: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    _stop_three_times(env, monkeypatch, "_align", FakeAlign(error=WorkerShutdown()))
    monkeypatch.setattr(runner, "_align", FakeAlign())
    assert _run(env) is Outcome.succeeded  # the alignment; the tile goes to its reconstruct job
    job, tile = _job_and_tile(env)
    assert (job.state, job.attempts, job.kind, tile.state) == ("succeeded", 1, "align", TileState.queued.value)
    env.job_id = tile.job_id
    _stop_three_times(env, monkeypatch, "_fuse", FakeFusion(error=WorkerShutdown()))
    monkeypatch.setattr(runner, "_fuse", FakeFusion())
    assert _run(env) is Outcome.succeeded
    job, tile = _job_and_tile(env)
    assert (job.state, job.attempts, tile.state) == (JobState.succeeded.value, 1, TileState.fused.value)


def test_a_failed_fusion_counts_its_attempt(env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(runner, "_align", FakeAlign())
    assert _run(env) is Outcome.succeeded
    env.job_id = _job_and_tile(env)[1].job_id
    monkeypatch.setattr(runner, "_fuse", FakeFusion(error=FusionError("the optimisation diverged", code="diverged")))
    assert _run(env) is Outcome.failed
    job, tile = _job_and_tile(env)
    assert (job.state, job.attempts, tile.state) == (JobState.failed.value, 1, TileState.failed.value)
    assert tile.last_error == "diverged: the optimisation diverged"
    assert _run(env) is Outcome.skipped  # a finished job is not run again


def test_the_reconstruction_starts_from_its_tiles_alignment_field(env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """The reconstruct job is given the field its region's alignment left in the tile (the warm start),
    and that field is part of the job's fingerprint: a new field is a new input."""
    from fusion.config import FusionConfig
    from worker import inputs
    from worker.inputs import plan_tile

    # the tiny preset the tests run reconstructs cold; the cpu and paper presets start warm
    monkeypatch.setattr(inputs, "fusion_config",
                        lambda settings: FusionConfig.preset(settings.fusion_preset).with_(recon_warm_fraction=1 / 3))
    monkeypatch.setattr(runner, "_align", FakeAlign())
    assert _run(env) is Outcome.succeeded
    with env.db() as db:
        warm = plan_tile(db, env.settings, 0, 0)
        tile = db.get(Tile, (0, 0))
        env.job_id, field_sha = tile.job_id, tile.align_field_sha256
        tile.align_field_sha256 = None
        cold = plan_tile(db, env.settings, 0, 0)
        db.rollback()
    assert warm.warm_sha256 == field_sha and cold.warm_sha256 is None and warm.fingerprint != cold.fingerprint
    fusion = FakeFusion()
    monkeypatch.setattr(runner, "_fuse", fusion)
    assert _run(env) is Outcome.succeeded
    assert fusion.warm == b"field of 0,0"


def test_a_refusion_after_a_session_was_added_starts_from_the_tiles_last_reconstruction(
    env: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The reconstruction keeps its field; a session added later is tracked against it (the frozen map,
    ``align_track_reconstruction``) and the tile's re-fusion starts from it (``warm_kind`` "reconstruction"). The field is
    not part of the fingerprint (an unchanged tile is reused); an alignment that trains the tile again
    makes its own field the warm start."""
    from fusion.config import FusionConfig
    from fusion.field import unpack_state
    from worker import inputs
    from worker.inputs import plan_alignment, plan_tile

    monkeypatch.setattr(inputs, "fusion_config",  # warm starts on, as in the cpu and paper presets
                        lambda settings: FusionConfig.preset(settings.fusion_preset).with_(recon_warm_fraction=1 / 3))
    never_realign(monkeypatch)  # two sessions: the second would re-align the map jointly
    monkeypatch.setattr(runner, "_align", FakeAlign())
    monkeypatch.setattr(runner, "_fuse", fusion := FakeFusion())
    assert _run(env) is Outcome.succeeded  # alignment
    env.job_id = _job_and_tile(env)[1].job_id
    assert _run(env) is Outcome.succeeded  # reconstruction: from the alignment's field, no other yet
    assert (fusion.warm, fusion.warm_kind) == (b"field of 0,0", "alignment")
    tile = _job_and_tile(env)[1]
    kept = tile.recon_field_sha256
    assert kept and unpack_state(env.app.state.blobs.get(kept))["w"].item() == 1.0

    with env.db() as db:  # nothing changed: the same fingerprint as the version, so the job reuses it
        env.job_id = schedule.request_fusion(db, 0, 0, settings=env.settings).id
    assert _run(env) is Outcome.reused

    upload(env, "veh-2/b", 0, [12.0, 10.0, 0.0])
    with env.db() as db:
        env.job_id = schedule.request_fusion(db, 0, 0, settings=env.settings).id
    align = FakeAlign()
    monkeypatch.setattr(runner, "_align", align)
    assert _run(env) is Outcome.succeeded  # the new session tracked against the map's reconstruction field
    assert set(align.frozen) == {(0, 0)} and unpack_state(align.frozen[(0, 0)])["w"].item() == 1.0
    env.job_id = _job_and_tile(env)[1].job_id
    with env.db() as db:
        planned = plan_tile(db, env.settings, 0, 0)
    assert (planned.warm_sha256, planned.warm_kind) == (kept, "reconstruction")
    assert _run(env) is Outcome.succeeded
    assert unpack_state(fusion.warm)["w"].item() == 1.0 and fusion.warm_kind == "reconstruction"
    tile = _job_and_tile(env)[1]
    assert tile.recon_field_sha256 not in (None, kept)  # the re-fusion's field is next
    monkeypatch.setattr(inputs, "fusion_config",  # the switch off: new sessions track the alignment's field
                        lambda settings: FusionConfig.preset(settings.fusion_preset).with_(
                            recon_warm_fraction=1 / 3, align_track_reconstruction=False))
    with env.db() as db:
        assert plan_alignment(db, env.settings, [(0, 0)]).fields == {(0, 0): tile.align_field_sha256}

    with env.db() as db:  # an alignment trains the tile again: its field, not the stale one, is the start
        assert tiles.hand_over(db, 0, 0, owner="nobody", job_id=env.job_id, now=utcnow(), field_sha256="f") is False
        db.get(Tile, (0, 0)).lease_owner = "w"
        db.commit()
        assert tiles.hand_over(db, 0, 0, owner="w", job_id=env.job_id, now=utcnow(), field_sha256="f")
        db.commit()
        planned = plan_tile(db, env.settings, 0, 0)
    assert (planned.warm_sha256, planned.warm_kind) == ("f", "alignment")


def test_a_tile_a_new_session_only_grazes_is_reused_not_fused_again(env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A submap dirties every tile its GPS uncertainty reaches; the alignment records where its surface
    lies at the refined pose (``Submap.surface_tiles``, within ``refusion_band_m``), and only those tiles
    change their fingerprint: a tile the new surface stays away from keeps its version."""
    from service.store.models import Submap, SubmapTile

    never_realign(monkeypatch)
    monkeypatch.setattr(runner, "_align", FakeAlign())
    monkeypatch.setattr(runner, "_fuse", fusion := FakeFusion())
    assert _run(env) is Outcome.succeeded
    env.job_id = _job_and_tile(env)[1].job_id
    assert _run(env) is Outcome.succeeded and _job_and_tile(env)[1].version == 1

    def add(session: str, x: float) -> dict[str, Outcome]:
        """Upload a 16 m street at x, align its region, run each tile's reconstruct job."""
        sid = upload(env, session, 0, [x, 10.0, 0.0])["id"]
        with env.db() as db:
            assert {(t.i, t.j) for t in db.query(SubmapTile).filter_by(submap_id=sid)} == {(-1, 0), (0, 0)}
            env.job_id = schedule.request_fusion(db, 0, 0, settings=env.settings).id
        assert _run(env) is Outcome.succeeded  # the alignment
        outcomes = {}
        for key in [(-1, 0), (0, 0)]:
            with env.db() as db:
                env.job_id = db.get(Tile, key).job_id
            outcomes[f"{key[0]}_{key[1]}"] = _run(env)
        with env.db() as db:
            outcomes["surface"] = db.get(Submap, sid).surface_tiles
        return outcomes

    # surface x ∈ [-18.5, -2.5]: 2.5 m west of tile (0, 0), beyond the tiny preset's 2 m band; its GPS
    # uncertainty (2 m, 2°: +2.8 m) reaches the tile
    assert add("veh-2/grazes", -18.5) == {"-1_0": Outcome.succeeded, "0_0": Outcome.reused, "surface": [[-1, 0]]}
    assert _job_and_tile(env)[1].version == 1
    # surface to x = -1.5: within the band, the tile is fused again, with both new submaps
    assert add("veh-3/reaches", -17.5) == {"-1_0": Outcome.succeeded, "0_0": Outcome.succeeded,
                                           "surface": [[-1, 0], [0, 0]]}
    assert _job_and_tile(env)[1].version == 2
    assert {s.session_id for s in fusion.calls[-1][1]} == {"veh-1/a", "veh-2/grazes", "veh-3/reaches"}


def _sample(name: str, **labels: str) -> float:
    from worker import metrics

    return metrics._get().registry.get_sample_value(name, labels) or 0.0


def test_the_runner_records_worker_metrics(env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Durations by kind and outcome, queue waits, failures by code, in progress back to 0, and one
    upload → fused sample per submap a new version includes for the first time."""
    before = {
        "align": _sample("fleetmap_worker_job_duration_seconds_count", kind="align", outcome="succeeded"),
        "interrupted": _sample("fleetmap_worker_job_duration_seconds_count", kind="reconstruct",
                               outcome="interrupted"),
        "failed": _sample("fleetmap_worker_job_failures_total", kind="reconstruct", code="diverged"),
        "wait": _sample("fleetmap_worker_queue_wait_seconds_count", kind="reconstruct"),
        "fused": _sample("fleetmap_worker_upload_to_fused_seconds_count"),
    }
    monkeypatch.setattr(runner, "_align", FakeAlign())
    assert _run(env) is Outcome.succeeded
    env.job_id = _job_and_tile(env)[1].job_id
    monkeypatch.setattr(runner, "_fuse", FakeFusion(error=WorkerShutdown()))
    with pytest.raises(WorkerShutdown):
        _run(env)
    monkeypatch.setattr(runner, "_fuse", FakeFusion())
    assert _run(env) is Outcome.succeeded
    assert _sample("fleetmap_worker_job_duration_seconds_count", kind="align", outcome="succeeded") == (
        before["align"] + 1
    )
    assert _sample("fleetmap_worker_job_duration_seconds_count", kind="reconstruct", outcome="interrupted") == (
        before["interrupted"] + 1
    )
    assert _sample("fleetmap_worker_queue_wait_seconds_count", kind="reconstruct") == before["wait"] + 2
    assert _sample("fleetmap_worker_upload_to_fused_seconds_count") == before["fused"] + 1
    assert _sample("fleetmap_worker_jobs_in_progress", kind="reconstruct") == 0
    assert _sample("fleetmap_worker_jobs_in_progress", kind="align") == 0

    upload(env, "veh-1/a", 1, [14.0, 10.0, 0.0])  # a failing re-fusion: counted under its code
    with env.db() as db:
        env.job_id = schedule.request_fusion(db, 0, 0, settings=env.settings).id
    monkeypatch.setattr(runner, "_fuse", FakeFusion(error=FusionError("the optimisation diverged", code="diverged")))
    while (outcome := _run(env)) is Outcome.succeeded:  # the new submap's alignment first
        env.job_id = _job_and_tile(env)[1].job_id
    assert outcome is Outcome.failed
    assert _sample("fleetmap_worker_job_failures_total", kind="reconstruct", code="diverged") == (
        before["failed"] + 1
    )


def _drain(env: Any) -> list[FusionJob]:
    """Run every queued job (alignments hand their tiles to reconstruct jobs) until none is left; returns
    the jobs run, in order."""
    done: list[FusionJob] = []
    for _ in range(20):
        with env.db() as db:
            queued = db.query(FusionJob).filter_by(state=JobState.queued.value).order_by(FusionJob.created_at).first()
        if queued is None:
            return done
        assert run_fusion_job(queued.id, env.settings, session_factory=env.db, blob_store=env.app.state.blobs) in (
            Outcome.succeeded, Outcome.reused)
        with env.db() as db:
            done.append(db.get(FusionJob, queued.id))
    raise AssertionError("jobs keep coming")


def _growing(env: Any, ids: dict[str, str]) -> tuple[Any, Any]:
    """``add(session, x)``: upload one submap of a new session at (x, 10) (its id into ``ids``), ask for tile
    (0, 0)'s fusion and run every job that follows (returned); ``pose_x()``: each submap's refined x."""
    from service.store.models import Submap

    def add(session: str, x: float) -> list[FusionJob]:
        ids[session] = upload(env, session, 0, [x, 10.0, 0.0])["id"]
        with env.db() as db:
            schedule.request_fusion(db, 0, 0, settings=env.settings)
        return _drain(env)

    def pose_x() -> dict[str, float]:
        with env.db() as db:
            return {k: db.get(Submap, v).pose_refined["t"][0] for k, v in ids.items()}

    return add, pose_x


@pytest.mark.parametrize("fraction", [0.5, 0.0])
def test_a_region_grown_incrementally_is_realigned_jointly(tmp_path: Any, monkeypatch: pytest.MonkeyPatch,
                                                           fraction: float) -> None:
    """Sessions added to a fused map are aligned against it, held where it is; once a third of the sessions
    with a submap in the new session's tiles came that way (``realign_share``), the alignment re-aligns
    them jointly instead: every submap whose tiles all lie in the job's tiles free from its refined pose
    (one reaching farther holds the border), every pose rewritten, every tile reconstructed from the new
    alignment field, or, by registration only (``realign_iterations_fraction`` 0: no field trained), from
    its own last reconstruction."""
    from fusion.config import FusionConfig
    from service.store.models import Submap, SubmapTile
    from worker import inputs
    from worker.inputs import plan_tile

    tiny = FusionConfig.preset("tiny").with_(realign_iterations_fraction=fraction)
    monkeypatch.setattr(inputs, "fusion_config", lambda settings: tiny)
    monkeypatch.setattr(runner, "_align", align := FakeAlign(shift=0.5))  # a free pose moves 0.5 m along x
    monkeypatch.setattr(runner, "_fuse", fusion := FakeFusion())
    with in_process(tmp_path) as env:
        ids: dict[str, str] = {}
        add, pose_x = _growing(env, ids)

        for session, x in [("a", 10.0), ("b", 12.0), ("c", 55.0)]:
            ids[session] = upload(env, session, 0, [x, 10.0, 0.0])["id"]
        ids["f"] = upload(env, "f", 0, [120.0, 10.0, 0.0])["id"]  # reaches tiles (1, 0) and (2, 0)
        with env.db() as db:
            tiles_of = {k: sorted((t.i, t.j) for t in db.query(SubmapTile).filter_by(submap_id=v)) for k, v in ids.items()}
        assert tiles_of == {"a": [(0, 0)], "b": [(0, 0)], "c": [(0, 0), (1, 0)], "f": [(1, 0), (2, 0)]}
        first = add("base", 14.0)  # one joint alignment of five sessions over the three tiles
        assert [(j.kind, j.realign) for j in first][0] == ("align", False)
        assert pose_x() == {"a": 10.5, "b": 12.5, "c": 55.5, "f": 120.5, "base": 14.5}

        second = add("d", 16.0)  # 1 of 6 sessions in tile (0, 0) incremental: tracked against the map
        assert (second[0].kind, second[0].realign, second[0].tiles) == ("align", False, [[0, 0]])
        assert set(align.frozen) == {(0, 0)} and align.config == tiny
        assert pose_x() == {"a": 10.5, "b": 12.5, "c": 55.5, "f": 120.5, "base": 14.5, "d": 16.5}
        with env.db() as db:
            assert db.get(Submap, ids["d"]).aligned_incrementally is True
            assert db.get(Submap, ids["a"]).aligned_incrementally is False
            assert db.get(Tile, (0, 0)).recon_field_sha256 is not None
            first_aligned = db.get(Submap, ids["a"]).refined_at

        third = add("e", 18.0)  # 2 of 7: the region is re-aligned jointly, over every tile its submaps reach
        job = third[0]
        assert (job.kind, job.realign, job.tiles, job.metrics["realign"]) == ("align", True, [[0, 0], [1, 0]], True)
        assert env.get(f"/v1/jobs/{job.id}").json()["realign"] is True
        assert align.frozen == {}  # no field held: every tile trained again, from the refined poses: half the steps
        assert align.config.align_iterations_per_tile == round(tiny.align_iterations_per_tile * fraction)
        free = {s.session_id for s in align.calls[-1][1] if s.free}
        assert free == {"a", "b", "c", "base", "d", "e"}  # f reaches tile (2, 0), outside: it holds the border
        assert pose_x() == {"a": 11.0, "b": 13.0, "c": 56.0, "f": 120.5, "base": 15.0, "d": 16.5 + 0.5, "e": 18.5}
        with env.db() as db:
            assert not any(db.get(Submap, v).aligned_incrementally for v in ids.values())
            assert db.get(Submap, ids["a"]).refined_at == first_aligned  # when it was first aligned
            assert db.get(Tile, (0, 0)).align_field_sha256 is not None
        recon = {(j.tile_i, j.tile_j): j for j in third[1:]}
        assert set(recon) == {(0, 0), (1, 0)} and all(j.kind == "reconstruct" for j in recon.values())
        # each started from the new alignment's field, or without one from its own last reconstruction (carried
        # along with its surface: with fewer steps where the new session is not)
        kinds = {key: fusion.warms[key][1] for key in recon}
        assert kinds == ({(0, 0): "alignment", (1, 0): "alignment"} if fraction else
                         {(0, 0): "reconstruction", (1, 0): "carried"})

        fourth = add("g", 20.0)  # the re-aligned map is joint again: the next session is tracked against it
        assert fourth[0].realign is False and set(align.frozen) == {(0, 0)}
        with env.db() as db:
            assert plan_tile(db, env.settings, 0, 0).warm_kind == "reconstruction"


def test_a_submap_aligned_into_a_tile_its_gps_missed_joins_it(tmp_path: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A GPS error beyond the submap's sigma: its box marks only tile (0, 0), the alignment moves it 45 m east
    into tile (1, 0). The submap joins that tile (membership, the tile created dirty), and the tile's
    reconstruction fuses it; the tile it already was in is not marked again."""
    from service.store.models import Submap

    monkeypatch.setattr(runner, "_align", FakeAlign(shift=45.0))
    monkeypatch.setattr(runner, "_fuse", fusion := FakeFusion())
    with in_process(tmp_path) as env:
        sid = upload(env, "veh-1/a", 0, [10.0, 10.0, 0.0])["id"]
        assert env.get(f"/v1/submaps/{sid}").json()["tiles"] == [[0, 0]]
        with env.db() as db:
            schedule.request_fusion(db, 0, 0, settings=env.settings)
        jobs = _drain(env)
        assert jobs[0].metrics["joined_tiles"] == [[1, 0]]
        assert env.get(f"/v1/submaps/{sid}").json()["tiles"] == [[0, 0], [1, 0]]
        assert env.get("/v1/tiles/0/0").json()["state"] == "fused"
        assert env.get("/v1/tiles/1/0").json()["state"] == "dirty"
        with env.db() as db:
            assert db.get(Submap, sid).surface_tiles == [[0, 0], [1, 0]]
            job = schedule.request_fusion(db, 1, 0, settings=env.settings)
        assert job.kind == "reconstruct"  # the submap is aligned: the tile is only reconstructed
        _drain(env)
        tile, submaps = fusion.calls[-1]
        assert (tile.i, tile.j) == (1, 0) and [s.id for s in submaps] == [sid]
        assert env.get("/v1/tiles/1/0").json()["state"] == "fused"


def test_the_drift_an_alignment_found_is_stored_with_the_pose_and_corrects_the_submap_in_its_tiles(
    env: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``fine_drift``: the alignment's drift correction of each submap (``fusion.drift``) is written with its refined
    pose, shown on ``GET /v1/submaps/{id}``, and the tile's reconstruction holds the corrected mesh; it is part of
    the tile's inputs (fingerprint)."""
    import math

    import numpy as np

    from fusion.drift import Drift
    from fusion.meshio import MeshLimits, read_submap_ply
    from service.store.models import Submap
    from worker.inputs import plan_tile

    monkeypatch.setattr(runner, "_align", FakeAlign(drift=Drift(math.log(1.02), 1e-4, -1e-4, (0.0, 1.0))))
    monkeypatch.setattr(runner, "_fuse", fusion := FakeFusion())
    assert _run(env) is Outcome.succeeded
    with env.db() as db:
        row = db.query(Submap).one()
        sid, stored, uploaded = row.id, row.drift_refined, row.mesh_sha256
        env.job_id = db.get(Tile, (0, 0)).job_id
        with_drift = plan_tile(db, env.settings, 0, 0).fingerprint
        row.drift_refined = None
        without = plan_tile(db, env.settings, 0, 0).fingerprint
        db.rollback()
    assert stored["scale"] == pytest.approx(1.02) and stored["axis"] == [0.0, 1.0]
    assert with_drift != without
    shown = env.get(f"/v1/submaps/{sid}").json()["drift_refined"]
    assert shown["scale"] == pytest.approx(1.02) and shown["bend_yaw_rad_per_m"] == pytest.approx(1e-4)
    assert _run(env) is Outcome.succeeded
    held = fusion.calls[-1][1][0]
    raw = read_submap_ply(env.app.state.blobs.get(uploaded), MeshLimits())
    np.testing.assert_allclose(held.mesh.vertices, Drift.from_json(stored).apply(raw.vertices))
    assert not np.allclose(held.mesh.vertices, raw.vertices)


def test_a_submap_aligned_without_a_drift_correction_has_none(env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    from service.store.models import Submap

    monkeypatch.setattr(runner, "_align", FakeAlign())
    assert _run(env) is Outcome.succeeded
    with env.db() as db:
        row = db.query(Submap).one()
        assert row.pose_refined is not None and row.drift_refined is None
        sid = row.id
    assert env.get(f"/v1/submaps/{sid}").json()["drift_refined"] is None


@pytest.mark.parametrize("hold", [True, False])
def test_a_realignment_holds_the_map_where_it_stood_and_keeps_the_tiles_it_did_not_move(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch, hold: bool
) -> None:
    """A joint re-alignment by registration alone with every submap free moves the whole map by whatever the
    GPS prior lets it (here the fake's 0.5 m): held, the refined poses stand where they stood (the new
    session's moves with them), and tile (1, 0), which the new session does not reach and whose surface did
    not move, goes back to ``fused`` with its mesh (no reconstruct job, same version); tile (0, 0), with the
    new session, is reconstructed. Not held (``realign_hold`` off), every tile moved: both reconstructed.
    A tile marked since its fusion (a pose changed elsewhere) is reconstructed though its surface stood still.
    With ``refusion_carry`` a tile reconstructed again starts from its last field carried along with its surface:
    moved 0.5 m along x where the map moved, where it was where the map was held; as a "carried" warm start
    (``refusion_carried_fraction`` of the steps) where no new submap reaches the tile, once."""
    from fusion.config import FusionConfig
    from fusion.field import unpack_state
    from worker import inputs

    tiny = FusionConfig.preset("tiny").with_(realign_iterations_fraction=0.0, realign_hold=hold, refusion_carry=True)
    monkeypatch.setattr(inputs, "fusion_config", lambda settings: tiny)
    monkeypatch.setattr(runner, "_align", FakeAlign(shift=0.5))
    fusion = FakeFusion()
    monkeypatch.setattr(runner, "_fuse", fusion)
    with in_process(tmp_path) as env:
        ids: dict[str, str] = {}
        add, pose_x = _growing(env, ids)

        for session, x in [("a", 10.0), ("b", 12.0), ("link", 50.0), ("c", 80.0)]:  # link reaches both tiles
            ids[session] = upload(env, session, 0, [x, 10.0, 0.0])["id"]
        add("base", 14.0)
        add("d", 16.0)  # tracked against the map
        assert pose_x() == {"a": 10.5, "b": 12.5, "link": 50.5, "c": 80.5, "base": 14.5, "d": 16.5}
        version = env.get("/v1/tiles/1/0").json()["version"]

        third = add("e", 18.0)  # 2 of 6 sessions incremental: re-aligned jointly, every submap free
        job = third[0]
        assert (job.kind, job.realign, job.tiles) == ("align", True, [[0, 0], [1, 0]])
        recon = sorted((j.tile_i, j.tile_j) for j in third[1:])
        tile = env.get("/v1/tiles/1/0").json()
        warm, kind = fusion.warms[(0, 0)]
        assert kind == "reconstruction" and warm is not None
        state = unpack_state(warm)
        assert set(state) == {"w", "norm.frame"} and job.metrics["carried_tiles"] == [list(t) for t in recon]
        # the field at x + motion is the old one at x: its frame takes a point back by the motion
        assert state["norm.frame"][:3, 3].tolist() == pytest.approx([0.0 if hold else -0.5, 0.0, 0.0], abs=1e-5)
        assert state["norm.frame"][:3, :3].numpy() == pytest.approx(np.eye(3), abs=1e-6)
        if hold:
            assert pose_x() == pytest.approx({"a": 10.5, "b": 12.5, "link": 50.5, "c": 80.5, "base": 14.5, "d": 16.5,
                                              "e": 18.0})
            assert job.metrics["tile_moved_m"]["0_0"] is None  # the new session is there
            assert job.metrics["tile_moved_m"]["1_0"] == pytest.approx(0.0, abs=1e-6)
            assert job.metrics["kept_tiles"] == [[1, 0]] and recon == [(0, 0)] and job.metrics["quiet_tiles"] == []
            assert (tile["state"], tile["version"]) == ("fused", version)
        else:
            assert pose_x()["a"] == 11.0 and job.metrics["tile_moved_m"]["1_0"] == pytest.approx(0.5)
            assert job.metrics["kept_tiles"] == [] and recon == [(0, 0), (1, 0)]
            assert (tile["state"], tile["version"]) == ("fused", version + 1)
            assert job.metrics["quiet_tiles"] == [[1, 0]] and fusion.warms[(1, 0)][1] == "carried"
        with env.db() as db:  # the carried field's re-fusion done: the tile's next one is a plain re-fusion
            assert not any(t.recon_field_carried for t in db.query(Tile))

        with env.db() as db:  # poses changed elsewhere: tile (1, 0) is owed a fusion, it cannot be settled
            tiles.mark_dirty(db, [(1, 0)], utcnow(), upload=False)
            db.commit()
        for n in range(6):  # sessions tracked against the map until a third of them were: re-aligned again
            later = add(f"s{n}", 20.0 + n)
            if later[0].realign:
                break
        assert later[0].realign and later[0].metrics["kept_tiles"] == []
        assert sorted((j.tile_i, j.tile_j) for j in later[1:]) == [(0, 0), (1, 0)]
        # held, tile (1, 0)'s surface stood still (its field needs no carry) but something marked it: how far that
        # moved its surface this alignment does not know, so its re-fusion is a plain one
        assert later[0].metrics["quiet_tiles"] == ([] if hold else [[1, 0]])
        assert fusion.warms[(1, 0)][1] == ("reconstruction" if hold else "carried")
        assert env.get("/v1/tiles/1/0").json()["state"] == "fused"
