"""``fleetmap demo``: the whole system on one machine, in a few minutes on a 2-core CPU.

1. simulates a fleet driving through a synthetic labelled world (``fusion.eval.synth``; ``WORLDS``:
   ``demo`` four tiles around a corner, ``bench`` the 3×3-tile core of ``fleetmap bench``),
2. starts the service (``fleetmap serve`` on a free loopback port, SQLite and blobs under ``OUT/data``
   or ``--database-url``, auth off, 2 s debounce) with its embedded fusion worker, or with ``--broker``
   as production runs it: ``--workers`` Celery workers (``fleetmap worker``) on a queue of its own,
3. uploads every submap over HTTP as vehicles would (multipart ``meta`` + ``mesh``),
4. shows the tiles' states while they fuse, downloads the fused meshes (PLY + GLB) and refined poses,
5. draws ``map.png`` from what it downloaded (``service.client.mapimage``: the fused tiles top-down by
   label, the GPS and refined trajectories),
6. prints an evaluation against the simulator's ground truth (``fusion.eval.scoring``): per tile, and for
   the whole core the figures ``fleetmap bench`` prints for its fused row, with how many times each tile
   was fused; then the viewer's URL (``--serve`` keeps the service running for it until Ctrl-C).

It waits for every tile: the fleet's region is aligned once, then each tile is reconstructed, each in
steps proportional to its content (``fusion.schedule``; a tile its submaps only graze through their GPS
uncertainty is fused empty). Leftover jobs resume with ``FLEETMAP_DATA_DIR=OUT/data fleetmap serve``.
This process never imports torch: fusion runs in the server's worker child.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import httpx

from fusion.config import PRESETS
from fusion.eval.cli import fleet_overrides_error

MARKER = ".fleetmap-demo"
SERVER_START_S = 90.0
# The driven streets (map frame x/y, metres): 40 m around the corner where tiles (0,0), (1,0), (0,1) and
# (1,1) of 64 m meet. The sensors see ~25 m beyond them, so the four tiles share the data and no tile is
# only grazed: a region of four tiles aligned jointly, four reconstructions, seams in both directions, in
# about 3 minutes on 2 cores (the bench's world, one 64 m tile driven through, touches nine tiles, five
# of them only along their edges).
DEMO_CORE = ((44.0, 44.0), (84.0, 84.0))
# ``bench``: the world of ``fleetmap bench`` (3×3 tiles of 64 m, a loop, a junction, a slope), to measure
# through the service what the bench measures offline
WORLDS = {"demo": DEMO_CORE, "bench": ((0.0, 0.0), (192.0, 192.0))}
DEFAULT_SESSIONS = {"demo": 3, "bench": 5}


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _prepare_out(out: Path) -> None:
    """Create ``out``; wipe a previous demo run there, refuse to touch any other non-empty folder."""
    if out.exists() and any(out.iterdir()):
        if not (out / MARKER).exists():
            raise SystemExit(f"{out} is not empty and not a fleetmap demo folder; choose another --out")
        for name in ("data", "sim", "meshes"):
            shutil.rmtree(out / name, ignore_errors=True)
        for name in ("map.png", "poses.json"):  # a failed run must not leave the previous run's results
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by `fleetmap demo`; safe to delete\n")


def service_env(out: Path, preset: str, debounce_s: float, broker: str | None = None,
                database_url: str | None = None) -> dict[str, str]:
    """The environment of the demo's ``fleetmap serve`` (and, with ``broker``, its workers): data under
    ``out/data``, auth off, this run's own Celery queue (a shared broker may hold other queues)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FLEETMAP_")}
    env.update(
        FLEETMAP_DATA_DIR=str(out / "data"),
        FLEETMAP_AUTH="off",
        FLEETMAP_FUSE_DEBOUNCE_S=str(debounce_s),
        FLEETMAP_SCHEDULER_INTERVAL_S="1",
        FLEETMAP_FUSION_PRESET=preset,
        FLEETMAP_LEASE_S="600",
        FLEETMAP_LOG_LEVEL=os.environ.get("FLEETMAP_LOG_LEVEL", "INFO"),
    )
    if broker:
        env.update(FLEETMAP_BROKER_URL=broker, FLEETMAP_FUSION_QUEUE=f"fleetmap-demo-{uuid.uuid4().hex[:12]}")
    if database_url:
        env["FLEETMAP_DATABASE_URL"] = database_url
    return env


def _fleetmap(*args: str) -> list[str]:
    return [sys.executable, "-m", "service.cli", *args]


def start_server(out: Path, env: dict[str, str], port: int = 0) -> tuple[subprocess.Popen[bytes], str]:
    """``fleetmap serve`` on ``port`` (0: a free one) with ``env`` (``service_env``), started: returns the
    process and its base URL at once (``wait_until_up`` waits for it: it starts while the fleet is
    simulated). With a broker the database is upgraded first (the embedded mode does it on start)."""
    port = port or _free_port()
    if env.get("FLEETMAP_BROKER_URL"):
        done = subprocess.run(_fleetmap("db", "upgrade"), env=env, capture_output=True, text=True)
        if done.returncode != 0:
            last = ((done.stderr or done.stdout).strip().splitlines() or ["no output"])[-1]
            raise SystemExit(f"fleetmap db upgrade failed: {last}")
    with open(out / "serve.log", "wb") as log:
        proc = subprocess.Popen(
            _fleetmap("serve", "--host", "127.0.0.1", "--port", str(port)),
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    return proc, f"http://127.0.0.1:{port}"


def start_workers(out: Path, env: dict[str, str], count: int) -> list[subprocess.Popen[bytes]]:
    """``count`` Celery fusion workers (``fleetmap worker``, one job at a time each) on the run's queue,
    the host's cores shared among them; logs ``out/worker-N.log``."""
    threads = max(1, (os.cpu_count() or 1) // count)
    procs = []
    for n in range(1, count + 1):
        with open(out / f"worker-{n}.log", "wb") as log:
            procs.append(subprocess.Popen(
                _fleetmap("worker", "--concurrency", "1", "--loglevel", "info"),
                env=env | {"FLEETMAP_TORCH_THREADS": str(threads)},
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            ))
    return procs


def wait_until_up(proc: subprocess.Popen[bytes], base: str, out: Path) -> None:
    """Wait for ``GET /healthz``; a one-line error if the server exits or does not answer in time."""
    deadline = time.monotonic() + SERVER_START_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"fleetmap serve exited ({proc.returncode}); see {out / 'serve.log'}")
        try:
            if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    raise SystemExit(f"fleetmap serve did not start within {SERVER_START_S:.0f} s; see {out / 'serve.log'}")


def stop_server(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM the server (it stops its worker; a running job goes back to queued), SIGKILL if stuck."""
    if proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def upload_all(client: httpx.Client, sim_dir: Path, records: list[Any]) -> dict[str, str]:
    """POST every simulated submap like a vehicle; returns submap name → server id."""
    ids = {}
    for k, record in enumerate(records, 1):
        files: dict[str, Any] = {
            "meta": (None, json.dumps(record.meta()), "application/json"),
            "mesh": (
                f"{record.name}.ply",
                (sim_dir / f"{record.name}.ply").read_bytes(),
                "application/octet-stream",
            ),
        }
        response = client.post("/v1/submaps", files=files)
        if response.status_code not in (200, 201):
            raise SystemExit(f"upload of {record.name} failed: {response.status_code} {response.text}")
        ids[record.name] = response.json()["id"]
        print(f"\r  uploaded {k}/{len(records)} submaps", end="", flush=True)
    print()
    return ids


def all_tiles(client: httpx.Client) -> list[dict[str, Any]]:
    items, cursor = [], None
    while True:
        page = client.get(
            "/v1/tiles", params={"limit": 1000, **({"cursor": cursor} if cursor else {})}
        ).json()
        items += page["items"]
        cursor = page.get("next_cursor")
        if not cursor:
            return items


def wait_for_tiles(
    client: httpx.Client, wanted: set[tuple[int, int]], timeout_s: float
) -> list[dict[str, Any]]:
    """Poll ``GET /v1/tiles`` until every wanted tile is fused or failed; prints the states as they change."""
    deadline = time.monotonic() + timeout_s
    last = ""
    started = time.monotonic()
    while True:
        tiles = all_tiles(client)
        counts: dict[str, int] = {}
        for t in tiles:
            counts[t["state"]] = counts.get(t["state"], 0) + 1
        busy = _busy(tiles)
        line = "  " + ", ".join(f"{n} {state}" for state, n in sorted(counts.items()))
        line += f"  [{'; '.join(busy)}]" if busy else ""
        if line != last:
            print(f"[{time.monotonic() - started:6.1f} s]{line}", flush=True)
            last = line
        done = {(t["i"], t["j"]) for t in tiles if t["state"] in ("fused", "failed")}
        if wanted <= done:
            return tiles
        if time.monotonic() > deadline:
            raise SystemExit(f"tiles not fused within {timeout_s:.0f} s; see the serve log")
        time.sleep(1.0)


def wait_settled(client: httpx.Client, wanted: set[tuple[int, int]], tiles: list[dict[str, Any]],
                 settle_s: float, timeout_s: float) -> list[dict[str, Any]]:
    """Once every wanted tile is fused: watch ``settle_s`` more seconds; a tile queued again (a re-fusion the
    fused poses called for) is waited for too. Returns the tiles as they settled (``version``: how many
    times each was fused)."""
    quiet_since = time.monotonic()
    while time.monotonic() - quiet_since < settle_s:
        time.sleep(1.0)
        tiles = all_tiles(client)
        if any(t["state"] not in ("fused", "failed") for t in tiles):
            print("  a tile was queued again; waiting for it", flush=True)
            tiles = wait_for_tiles(client, wanted | {(t["i"], t["j"]) for t in tiles}, timeout_s)
            quiet_since = time.monotonic()
    return tiles


def _busy(tiles: list[dict[str, Any]]) -> list[str]:
    """The running jobs: ``aligning N tiles P%`` for a region's alignment (one job leases all its
    tiles), ``fusing (i,j) P%`` for a tile's reconstruction."""
    jobs: dict[str, list[dict[str, Any]]] = {}
    for t in tiles:
        if t["state"] == "fusing":
            jobs.setdefault(t["job_id"] or f"{t['i']},{t['j']}", []).append(t)
    out = []
    for held in jobs.values():
        percent = f"{100 * held[0]['progress']:.0f}%"
        out.append(f"aligning {len(held)} tiles {percent}" if len(held) > 1 else
                   f"fusing ({held[0]['i']},{held[0]['j']}) {percent}")
    return out


def download(client: httpx.Client, tiles: list[dict[str, Any]], meshes: Path) -> dict[tuple[int, int], bytes]:
    """Fused meshes (PLY and GLB) of every fused tile into ``meshes/``; returns the PLY bytes by tile."""
    meshes.mkdir(parents=True, exist_ok=True)
    plys = {}
    for t in tiles:
        if not t["version"]:
            continue
        i, j = t["i"], t["j"]
        ply = client.get(f"/v1/tiles/{i}/{j}/mesh").content
        (meshes / f"tile_{i}_{j}.ply").write_bytes(ply)
        (meshes / f"tile_{i}_{j}.glb").write_bytes(
            client.get(f"/v1/tiles/{i}/{j}/mesh", params={"format": "glb"}).content
        )
        plys[(i, j)] = ply
    return plys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fleetmap demo", description=__doc__.splitlines()[0])
    parser.add_argument("--world", choices=tuple(WORLDS), default="demo",
                        help="demo: four tiles around a corner (default); bench: the 3×3 tiles of fleetmap bench")
    parser.add_argument("--sessions", type=_positive, default=None,
                        help="vehicles driving through the world (default 3; 5 in the bench world)")
    parser.add_argument("--seed", type=int, default=0, help="world and fleet seed")
    parser.add_argument("--sensor", choices=("camera", "exact"), default="camera",
                        help="the fleet's sensor model (fusion.eval.synth.camera; default camera)")
    parser.add_argument("--camera", action="append", default=[], metavar="KEY=VALUE",
                        help="override a field of the camera model (repeatable; as for fleetmap bench)")
    parser.add_argument("--out", type=Path, default=Path("./fleetmap-demo"), help="output folder")
    parser.add_argument(
        "--preset", default="cpu", choices=PRESETS, help="fusion preset: cpu, paper (GPU) or tiny (smoke test)"
    )
    parser.add_argument("--debounce", type=float, default=2.0, help="seconds of quiet before a tile is fused")
    parser.add_argument("--timeout", type=float, default=1800.0, help="give up after this many seconds")
    parser.add_argument(
        "--serve", action="store_true", help="keep the service running for the viewer afterwards (Ctrl-C stops it)"
    )
    parser.add_argument("--port", type=int, default=0, help="the service's port (default: a free one)")
    parser.add_argument("--broker", metavar="URL", default=None,
                        help="fuse with Celery workers on this broker (e.g. redis://127.0.0.1:6379/0) instead of "
                             "the embedded worker")
    parser.add_argument("--workers", type=_positive, default=None, help="Celery workers with --broker (default 2)")
    parser.add_argument("--database-url", metavar="URL", default=None,
                        help="an empty database for the service (default: SQLite under OUT/data)")
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        parser.error(f"--port {args.port} is not a TCP port")
    if args.workers and not args.broker:
        parser.error("--workers needs --broker (the embedded worker is one process)")
    if (error := fleet_overrides_error(args.sensor, args.camera)) is not None:
        parser.error(error)
    sessions = args.sessions or DEFAULT_SESSIONS[args.world]

    out = args.out.resolve()
    _prepare_out(out)
    t0 = time.monotonic()
    env = service_env(out, args.preset, args.debounce, args.broker, args.database_url)
    proc, base = start_server(out, env, args.port)  # starts while the fleet drives
    workers = start_workers(out, env, args.workers or 2) if args.broker else []
    try:
        print(f"1/6 simulating {sessions} sessions ({args.world} world, seed {args.seed}, {args.sensor} sensor) ...",
              flush=True)
        records, truth = _simulate(out / "sim", args.seed, sessions, args.sensor, WORLDS[args.world], args.camera)
        print(f"    {len(records)} submaps, {sum(len(r.mesh.faces) for r in records):,} faces")
        fusing = f"{len(workers)} Celery workers on {args.broker}" if workers else "embedded worker"
        print(f"2/6 starting the service (fleetmap serve + {fusing}) ...", flush=True)
        wait_until_up(proc, base, out)
        started = time.monotonic() - t0
        with httpx.Client(base_url=base, timeout=60) as client:
            if all_tiles(client):
                raise SystemExit("the service's database already holds tiles: give --database-url an empty database")
            print(f"    {base} (auth off, preset {args.preset}, debounce {args.debounce:g} s)")
            report = _run(client, out, records, truth, args.timeout, WORLDS[args.world])
        report["timings"] = {"simulation and start": started} | report["timings"]
        report["resume"] = _resume_command(env, bool(workers))
        print_report(report, out, time.monotonic() - t0)
        if args.serve:
            return serve_until_stopped(proc, base)
        print(f"\nviewer: {base}/ (stopped with the demo; `fleetmap demo --serve` keeps it running)")
        return 0
    finally:
        stop_server(proc)
        for worker in workers:
            stop_server(worker)


def _resume_command(env: dict[str, str], celery: bool) -> str:
    """How to pick the run's service up again: its settings, then ``fleetmap serve`` (and workers)."""
    keys = ("FLEETMAP_DATA_DIR", "FLEETMAP_DATABASE_URL", "FLEETMAP_BROKER_URL", "FLEETMAP_FUSION_QUEUE")
    settings = " ".join(f"{k}={env[k]}" for k in keys if k in env) + " FLEETMAP_AUTH=off"
    return f"{settings} fleetmap serve" + (" and fleetmap worker" if celery else "")


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _simulate(sim: Path, seed: int, sessions: int, sensor: str = "camera",
              core: tuple[tuple[float, float], tuple[float, float]] = DEMO_CORE,
              camera: list[str] | None = None) -> tuple[list[Any], Any]:
    """The simulated fleet's uploads (written under ``sim``) and its ground truth, driven through ``core``
    (``camera``: overrides of the camera model, ``--camera``)."""
    from fusion.eval.synth.simulate import load_ground_truth, simulate
    from fusion.eval.synth.world import WorldParams

    world = WorldParams(core_min=core[0], core_max=core[1])
    records = simulate(sim, seed=seed, sessions=sessions, world_params=world, sensor=sensor, camera=camera or ())
    return records, load_ground_truth(sim)


def _run(client: httpx.Client, out: Path, records: list[Any], truth: Any, timeout_s: float,
         core: tuple[tuple[float, float], tuple[float, float]] = DEMO_CORE, settle_s: float = 10.0) -> dict[str, Any]:
    """Steps 3-6 against the running service: upload, wait for every tile (and ``settle_s`` more without a
    tile leaving ``fused``), download, draw, evaluate (the whole map over ``core``)."""
    timings: dict[str, float] = {}
    t = time.monotonic()
    print("3/6 uploading submaps over HTTP ...", flush=True)
    ids = upload_all(client, out / "sim", records)
    tiles = all_tiles(client)
    tile_size = float(client.get("/v1/capabilities").json()["tile_size_m"])
    wanted = {(t["i"], t["j"]) for t in tiles}  # alignment, then every tile's reconstruction
    timings["upload"], t = time.monotonic() - t, time.monotonic()
    print(f"4/6 aligning and fusing {len(wanted)} tiles ...", flush=True)
    tiles = wait_for_tiles(client, wanted, timeout_s)
    timings["fusion"], t = time.monotonic() - t, time.monotonic()
    tiles = wait_settled(client, wanted, tiles, settle_s, timeout_s)
    timings["settling"], t = time.monotonic() - t, time.monotonic()
    plys = download(client, tiles, out / "meshes")
    sessions = sorted({r.session_id for r in records})
    poses = {s: client.get(f"/v1/sessions/{_quote(s)}/poses").json() for s in sessions}
    jobs = {(t["i"], t["j"]): client.get(f"/v1/jobs/{t['job_id']}").json() for t in tiles if t["job_id"]}
    (out / "poses.json").write_text(json.dumps(poses, indent=1))
    print("5/6 drawing map.png (fused tiles, GPS and refined trajectories) ...", flush=True)
    draw_map(out / "map.png", client.get("/v1/labels").json(), tile_size, plys, poses)
    timings["download, map.png"], t = time.monotonic() - t, time.monotonic()
    print("6/6 evaluating against the ground truth ...", flush=True)
    report = evaluate(truth, records, ids, tiles, plys, poses, jobs, tile_size, core)
    timings["evaluation"] = time.monotonic() - t
    return report | {"timings": timings}


def draw_map(
    path: Path, labels: list[dict[str, Any]], tile_size: float, plys: dict[tuple[int, int], bytes],
    poses: dict[str, list[dict[str, Any]]],
) -> None:
    """``map.png`` from what the demo downloaded: the fused tiles' PLYs, the label set, the poses."""
    from fusion.meshio import read_fused_ply
    from service.client import mapimage

    meshes = {key: read_fused_ply(data) for key, data in plys.items()}
    mapimage.render(mapimage.MapData(tile_size, mapimage.labels_from_json(labels), meshes, poses), path)


def serve_until_stopped(proc: subprocess.Popen[bytes], base: str) -> int:
    """Keep the service running until Ctrl-C or SIGTERM (0; the caller stops it), or until it exits (1)."""

    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    # both handled explicitly: a process started in the background of a non-interactive shell inherits
    # SIGINT *ignored*, and Python then never raises KeyboardInterrupt for it
    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"\nviewer: {base}/ (serving; Ctrl-C stops it)", flush=True)
        code = proc.wait()
        print(f"fleetmap serve exited ({code}); see its log", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("stopping the service ...", flush=True)
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def evaluate(
    truth: Any,
    records: list[Any],
    ids: dict[str, str],
    tiles: list[dict[str, Any]],
    plys: dict[tuple[int, int], bytes],
    poses: dict[str, list[dict[str, Any]]],
    jobs: dict[tuple[int, int], dict[str, Any]],
    tile_size: float,
    core: tuple[tuple[float, float], tuple[float, float]] = DEMO_CORE,
) -> dict[str, Any]:
    """Per fused tile: geometric P/R/F and mean semantic F at d = 0.2 m (the tile's square), gauge-aligned
    (``geo``, ``sem_f``: the meshes moved by the rigid fit of every submap's current pose, refined else
    GPS, onto its true pose, over a sample of its vertices; GPS fixes the map's absolute placement only
    to a few decimetres) and in the absolute map frame (``abs_geo``, ``abs_sem_f``); ``map``: the tiles'
    meshes together over the world's ``core``, scored as ``fleetmap bench`` scores its fused row
    (``scoring.score_aligned_and_absolute``: per class F, surviving share of single-session objects);
    poses: RMSE of GPS and refined poses against the truth (after rigid alignment). Scoring:
    ``fusion.eval.scoring``."""
    from fusion.eval import scoring
    from fusion.meshio import read_fused_ply

    gauge = _gauge(truth, records, ids, poses)
    world = scoring.sample_truth(truth, None)
    rows = [_tile_row(t, plys, jobs, world, gauge, tile_size) for t in tiles]
    core_truth = scoring.sample_truth(truth, core, uploads={r.name: r.mesh.vertices for r in records})
    whole = scoring.merge_meshes([read_fused_ply(data) for data in plys.values()])
    figures = scoring.score_aligned_and_absolute(core_truth, whole, gauge)
    versions = [t["version"] for t in tiles]
    return {"tiles": rows, "poses": _pose_report(truth, records, ids, poses),
            "map": figures | {"core": core, "max_fusions": max(versions, default=0)}}


def _gauge(
    truth: Any, records: list[Any], ids: dict[str, str], poses: dict[str, list[dict[str, Any]]]
) -> Any:
    """The rigid gauge (R, t) of the served map: every submap's current pose (refined, else GPS) fitted
    onto its true pose (``scoring.gauge_fit``); None when the server knows no submap's pose."""
    from fusion.eval import scoring
    from fusion.types import Pose

    current = {p["id"]: p.get("pose_refined") or p["pose_gps"] for s in poses.values() for p in s}
    used = [r for r in records if ids.get(r.name) in current]
    if not used:
        return None
    return scoring.gauge_fit(
        [Pose.from_json(current[ids[r.name]]) for r in used],
        [truth.poses[r.name] for r in used],
        [r.mesh.vertices for r in used],
    )


def _tile_row(
    t: dict[str, Any],
    plys: dict[tuple[int, int], bytes],
    jobs: dict[tuple[int, int], dict[str, Any]],
    world: Any,
    gauge: Any,
    tile_size: float,
) -> dict[str, Any]:
    """One tile's table row: state, fusion seconds and, when it has a mesh, its figures (absolute and
    gauge-aligned) against ``world`` (``scoring.TruthPoints``) cropped to the tile."""
    from fusion.eval import scoring
    from fusion.meshio import read_fused_ply
    from fusion.tiles import tile_bounds

    key = (t["i"], t["j"])
    row: dict[str, Any] = {"tile": key, "state": t["state"], "version": t["version"], "submaps": t["submaps"]}
    row["fuse_s"] = ((jobs.get(key) or {}).get("metrics") or {}).get("duration_s")
    if key not in plys:
        return row
    mesh = read_fused_ply(plys[key])
    row["faces"] = int(len(mesh.faces))
    if len(mesh.faces):
        truth = world.cropped(tile_bounds(*key, tile_size))
        absolute = scoring.score_mesh(truth, mesh)
        aligned = scoring.score_mesh(truth, mesh, gauge) if gauge is not None else absolute
        row["abs_geo"] = (absolute["geo_p"], absolute["geo_r"], absolute["geo_f"])
        row["abs_sem_f"] = absolute["sem_f"]
        row["geo"] = (aligned["geo_p"], aligned["geo_r"], aligned["geo_f"])
        row["sem_f"] = aligned["sem_f"]
    return row


def _pose_report(
    truth: Any, records: list[Any], ids: dict[str, str], poses: dict[str, list[dict[str, Any]]]
) -> dict[str, Any]:
    """RMSE (m, deg) of the GPS and the refined poses of the refined submaps against the truth."""
    from fusion.eval import metrics
    from fusion.types import Pose

    refined = {p["id"]: p for session in poses.values() for p in session if p.get("pose_refined")}
    names = [r.name for r in records if ids[r.name] in refined]
    pose_report: dict[str, Any] = {"refined": len(names), "submaps": len(records)}
    if names:
        true = [truth.poses[n] for n in names]
        pose_report["gps"] = metrics.pose_rmse(
            [Pose.from_json(refined[ids[n]]["pose_gps"]) for n in names], true
        )
        pose_report["fused"] = metrics.pose_rmse(
            [Pose.from_json(refined[ids[n]]["pose_refined"]) for n in names], true
        )
    return pose_report


def _f(value: Any, fmt: str = "{:.3f}") -> str:
    return "-" if value is None else fmt.format(value)


def print_report(report: dict[str, Any], out: Path, wall_s: float) -> None:
    """The evaluation table and where the outputs are."""
    print()
    print(
        f"{'tile':>9}  {'state':7} {'ver':>3} {'submaps':>7} {'faces':>8}  {'geo P':>6} {'geo R':>6} "
        f"{'geo F':>6} {'sem F':>6} {'abs geoF':>8} {'abs semF':>8} {'fuse s':>7}"
    )
    for row in report["tiles"]:
        p, r, f = row.get("geo") or (None, None, None)
        tile = f"({row['tile'][0]},{row['tile'][1]})"
        print(
            f"{tile:>9}  {row['state']:7} {row['version']:>3} {row['submaps']:>7} {_f(row.get('faces'), '{:d}'):>8}  "
            f"{_f(p):>6} {_f(r):>6} {_f(f):>6} {_f(row.get('sem_f')):>6} {_f((row.get('abs_geo') or [None] * 3)[2]):>8} "
            f"{_f(row.get('abs_sem_f')):>8} {_f(row.get('fuse_s'), '{:.1f}'):>7}"
        )
    print("geo P/R/F, sem F: gauge-aligned (meshes moved by the rigid fit of the submaps' poses onto their true "
          "poses); abs: absolute map frame")
    if "map" in report:
        _print_map(report["map"])
    poses = report["poses"]
    if "gps" in poses:
        (gt, gr), (ft, fr) = poses["gps"], poses["fused"]
        print(
            f"\nposes ({poses['refined']} of {poses['submaps']} submaps refined; RMSE after rigid alignment):"
            f"\n  GPS      {gt:.3f} m  {gr:.3f} deg\n  refined  {ft:.3f} m  {fr:.3f} deg"
        )
    else:
        print(f"\nposes: none of {poses['submaps']} submaps refined yet")
    timings = ", ".join(f"{name} {seconds:.0f} s" for name, seconds in report.get("timings", {}).items())
    print(
        f"\nmap picture: {out / 'map.png'}\nfused meshes (PLY, GLB): {out / 'meshes'}"
        f"\nrefined poses: {out / 'poses.json'}"
        f"\nsimulated uploads and ground truth: {out / 'sim'}\nservice data: {out / 'data'} "
        f"(resume: {report['resume']})"
        f"\nserver log: {out / 'serve.log'}\ndone in {wall_s:.0f} s ({timings})"
    )


def _print_map(figures: dict[str, Any]) -> None:
    """The whole core's line: what ``fleetmap bench`` prints for its fused row."""
    (x0, y0), (x1, y1) = figures["core"]
    survival = figures.get("transient_survival")
    print(
        f"\nwhole map ({x1 - x0:g} × {y1 - y0:g} m core, gauge-aligned): geo P/R/F {figures['geo_p']:.3f} / "
        f"{figures['geo_r']:.3f} / {figures['geo_f']:.3f}, sem F {figures['sem_f']:.3f}, abs geo F "
        f"{figures['abs_geo_f']:.3f}, single-session objects kept {_f(survival, '{:.1%}')}; "
        f"fusions per tile at most {figures['max_fusions']}"
    )
    print("  per class F: " + "  ".join(f"{name} {f:.2f}" for name, f in figures["per_class_f"].items()))


def _quote(session_id: str) -> str:
    from urllib.parse import quote

    return quote(session_id, safe="")


if __name__ == "__main__":
    sys.exit(main())
