#!/usr/bin/env python3
"""Load benchmark of the production deployment: many vehicles uploading submaps at once, then tile
reads while a fusion runs.

By default it starts the deployment itself on loopback (a fresh PostgreSQL database on the given
server, a private Redis database number and queue, a file blob store under a temporary folder,
``fleetmap serve --workers N`` and ``fleetmap worker``) and removes it afterwards. With ``--url`` it
targets a running deployment instead (``--token``: an operator token).

Phases (each bounded in count and time):
1. upload: ``--clients`` simulated vehicles (httpx, asyncio) POST real synthetic submaps of about
   ``--submap-kb`` KB until ``--count`` are sent or ``--duration`` seconds pass;
2. upload → map (from the start of phase 1 until every stored submap is in the map, or
   ``--fusion-seconds`` after phase 1 ended): the automatic scheduler and ``--fusion-workers`` workers
   fuse the uploaded tiles while an operator client polls ``GET /v1/tiles`` every ``--poll-seconds``;
3. fusion: an operator triggers ``POST /v1/tiles/{i}/{j}/fuse`` on the busiest tile, and readers poll
   ``GET /v1/tiles`` while the job is queued/running (at most ``--fusion-seconds``).

Upload → map latency of a submap S (uploaded with a ``201``; retries answered ``200`` are not counted):
``fused_at(T) - t201(S)``, where ``t201(S)`` is the client's wall-clock time when the 201 response
arrived and ``T`` is the first of S's tiles that a poll *started after* t201(S) finds in state ``fused``,
``fused_at(T)`` being the commit time of that tile version (server wall clock: the same host on
loopback). A tile is ``fused`` only when its latest version used every submap it holds, so that version
contains S; it is the first version containing S unless the tile became ``dirty`` and was fused again
between two polls (then the figure is an upper bound). It includes the scheduler's debounce
(``--fuse-debounce``, default the deployment's ``FLEETMAP_FUSE_DEBOUNCE_S``), the queue waits, the
alignment and the tile reconstruction. Submaps not in the map when the phase ends are counted apart.

Prints submaps/s, MB/s, latency percentiles, errors by status, upload → map p50/p90/p99, and GET
/v1/tiles percentiles. A locally started deployment's workers serve their own metrics
(``--metrics-port``); the script prints each worker's job counts and mean upload → fused from them.

    .venv/bin/python scripts/loadbench.py --clients 16 --count 4000 --duration 30
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys
import time
import uuid
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from loadbench_deploy import local_deployment  # noqa: E402  (scripts/ is sys.path[0] when run as a script)

from fusion.meshio import write_submap_ply  # noqa: E402
from fusion.types import SemanticMesh  # noqa: E402

# Submaps are square terrain patches; ~52 bytes per grid vertex in binary PLY (vertex + 2 faces).
BYTES_PER_GRID_VERTEX = 52
SUBMAP_SIZE_M = 30.0
STEP_M = 12.0  # distance between consecutive submaps of one vehicle


# ---------------------------------------------------------------------------------------- submaps


def terrain_submap(n: int, rng: np.random.Generator) -> SemanticMesh:
    """An n×n-vertex terrain patch, SUBMAP_SIZE_M wide, centred on the local origin (metres):
    a road strip (label 1) through terrain (4), with random height noise so every upload is unique."""
    xs = np.linspace(-SUBMAP_SIZE_M / 2, SUBMAP_SIZE_M / 2, n)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    gz = 0.3 * np.sin(gx / 5.0) + 0.2 * np.cos(gy / 7.0) + rng.normal(0.0, 0.02, gx.shape)
    vertices = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    on_road = np.abs(vertices[faces[:, 0], 1]) < 4.0
    labels = np.where(on_road, 1, 4).astype(np.int64)
    return SemanticMesh(vertices=vertices, faces=faces.astype(np.int64), face_labels=labels)


@dataclass
class Upload:
    """One prepared request: the meta JSON and the mesh bytes."""

    agent_id: str
    meta: str
    mesh: bytes


def vehicle_uploads(vehicle: int, count: int, grid_n: int, run_id: str) -> list[Upload]:
    """``count`` consecutive submaps of one vehicle driving east along its own lane (map frame)."""
    rng = np.random.default_rng(vehicle)
    agent = f"bench-{run_id}-veh-{vehicle:03d}"
    session = f"{agent}/{time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}"
    y = 40.0 * vehicle
    uploads = []
    for seq in range(count):
        x = STEP_M * seq
        meta = {
            "agent_id": agent,
            "session_id": session,
            "seq": seq,
            "captured_at": "2026-11-24T08:00:00Z",
            "gps": {"pose": {"t": [x, y, 0.0], "q": [1.0, 0.0, 0.0, 0.0]}},
            "gps_sigma": {"trans_m": 1.0, "rot_deg": 1.0},
            "odometry": {"t": [x, 0.0, 0.0], "q": [1.0, 0.0, 0.0, 0.0]},
        }
        mesh = write_submap_ply(terrain_submap(grid_n, rng))
        uploads.append(Upload(agent, json.dumps(meta), mesh))
    return uploads


# -------------------------------------------------------------------------------------- statistics


def cpu_snapshot(api_pid: int | None) -> dict[str, float]:
    """CPU seconds used so far by this client, the API process tree and PostgreSQL (needs psutil)."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    snap = {"client": usage.ru_utime + usage.ru_stime}
    try:
        import psutil
    except ImportError:
        return snap
    if api_pid is not None:
        with contextlib.suppress(psutil.Error):
            root = psutil.Process(api_pid)
            snap["api"] = sum(sum(p.cpu_times()[:2]) for p in [root, *root.children(recursive=True)])
    pg = 0.0
    for proc in psutil.process_iter(["name"]):
        if proc.info["name"] in {"postgres", "postmaster"}:
            with contextlib.suppress(psutil.Error):
                pg += sum(proc.cpu_times()[:2])
    snap["postgres"] = pg
    return snap


@dataclass
class Samples:
    """Latencies (seconds) and status counts of one kind of request."""

    latencies: list[float] = field(default_factory=list)
    statuses: Counter[str] = field(default_factory=Counter)
    bytes_sent: int = 0

    def add(self, status: str, latency_s: float, nbytes: int = 0) -> None:
        self.statuses[status] += 1
        self.latencies.append(latency_s)
        self.bytes_sent += nbytes

    def pct(self, q: float) -> float:
        """Percentile ``q`` in milliseconds (nan without samples)."""
        return float(np.percentile(self.latencies, q) * 1e3) if self.latencies else float("nan")


def _ok(status: str) -> bool:
    return status in {"200", "201", "202", "304"}


# --------------------------------------------------------------------------------------- phases


@dataclass
class Stored:
    """A submap the server stored (201): its tiles and the client's wall-clock time of the response."""

    id: str
    tiles: list[tuple[int, int]]
    at: float  # time.time() when the 201 arrived
    in_map_s: float | None = None  # upload → map latency, once known


async def upload_phase(
    url: str,
    tokens: dict[str, str],
    queues: list[list[Upload]],
    duration_s: float,
    timeout_s: float,
    stored: list[Stored] | None = None,
) -> tuple[Samples, float, Counter[tuple[int, int]]]:
    """Every vehicle uploads its queue in order; returns samples, elapsed seconds and tile hit counts.
    Every 201 is appended to ``stored``."""
    samples = Samples()
    tiles: Counter[tuple[int, int]] = Counter()
    deadline = time.monotonic() + duration_s
    limits = httpx.Limits(max_connections=len(queues) + 4, max_keepalive_connections=len(queues) + 4)

    async with httpx.AsyncClient(base_url=url, timeout=timeout_s, limits=limits) as client:

        async def vehicle(queue: list[Upload]) -> None:
            for item in queue:
                if time.monotonic() >= deadline:
                    return
                headers = {"Authorization": f"Bearer {tokens[item.agent_id]}"}
                files: dict[str, tuple[str | None, bytes | str] | tuple[str | None, bytes | str, str]] = {
                    "meta": (None, item.meta, "application/json"), "mesh": ("submap.ply", item.mesh)}
                start = time.perf_counter()
                try:
                    response = await client.post("/v1/submaps", files=files, headers=headers)
                    status = str(response.status_code)
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                arrived = time.time()
                samples.add(status, time.perf_counter() - start, len(item.mesh))
                if status in {"200", "201"}:
                    body = response.json()
                    for i, j in body["tiles"]:
                        tiles[(i, j)] += 1
                    if status == "201" and stored is not None:
                        stored.append(Stored(body["id"], [(i, j) for i, j in body["tiles"]], arrived))

        began = time.perf_counter()
        await asyncio.gather(*(vehicle(q) for q in queues))
        return samples, time.perf_counter() - began, tiles


def _epoch(stamp: str) -> float:
    """An API timestamp (ISO 8601, UTC) as seconds since the epoch."""
    parsed = datetime.fromisoformat(stamp)
    return (parsed if parsed.tzinfo else parsed.replace(tzinfo=UTC)).timestamp()


async def _all_tiles(client: httpx.AsyncClient) -> list[dict[str, Any]]:
    items: list[dict[str, Any]] = []
    cursor: str | None = None
    for _ in range(1000):  # at most 1000 pages of 1000 tiles
        params: dict[str, str | int] = {"limit": 1000, **({"cursor": cursor} if cursor else {})}
        response = await client.get("/v1/tiles", params=params)
        response.raise_for_status()
        page = response.json()
        items += page["items"]
        cursor = page["next_cursor"]
        if not cursor:
            break
    return items


async def map_latency_phase(
    url: str, operator: str, stored: list[Stored], uploading: asyncio.Event, max_s: float, poll_s: float,
    timeout_s: float,
) -> int:
    """Poll ``GET /v1/tiles`` until every submap in ``stored`` is in the map (see the module docstring),
    or ``max_s`` after ``uploading`` was cleared. Sets ``Stored.in_map_s``; returns the number of polls."""
    headers = {"Authorization": f"Bearer {operator}"}
    polls = 0
    deadline = float("inf")
    async with httpx.AsyncClient(base_url=url, timeout=timeout_s, headers=headers) as client:
        while time.monotonic() < deadline:
            if not uploading.is_set() and deadline == float("inf"):
                deadline = time.monotonic() + max_s
            began = time.time()
            pending = [s for s in stored if s.in_map_s is None and s.at < began]
            try:
                tiles = await _all_tiles(client)
            except httpx.HTTPError as exc:
                print(f"map poll failed: {exc}", flush=True)
                await asyncio.sleep(poll_s)
                continue
            polls += 1
            fused = {
                (int(t["i"]), int(t["j"])): _epoch(str(t["fused_at"]))
                for t in tiles
                if t["state"] == "fused" and t["fused_at"]
            }
            for submap in pending:
                times = [fused[t] for t in submap.tiles if t in fused]
                if times:
                    submap.in_map_s = max(0.0, min(times) - submap.at)
            if not uploading.is_set() and all(s.in_map_s is not None for s in stored):
                break
            await asyncio.sleep(poll_s)
    return polls


async def upload_and_map(
    url: str, operator: str, tokens: dict[str, str], queues: list[list[Upload]], args: argparse.Namespace
) -> tuple[Samples, float, Counter[tuple[int, int]], list[Stored], int]:
    """Phases 1 and 2 together: the map poller runs while the vehicles upload."""
    stored: list[Stored] = []
    uploading = asyncio.Event()
    uploading.set()

    async def uploads() -> tuple[Samples, float, Counter[tuple[int, int]]]:
        try:
            return await upload_phase(url, tokens, queues, args.duration, args.timeout, stored)
        finally:
            uploading.clear()

    if args.no_map_latency:
        samples, elapsed, tiles = await uploads()
        return samples, elapsed, tiles, stored, 0
    (samples, elapsed, tiles), polls = await asyncio.gather(
        uploads(),
        map_latency_phase(url, operator, stored, uploading, args.fusion_seconds, args.poll_seconds, args.timeout),
    )
    return samples, elapsed, tiles, stored, polls


def report_map_latency(stored: list[Stored], polls: int, max_s: float) -> None:
    """Upload → map percentiles (seconds) over the submaps that made it; the rest counted apart."""
    done = [s.in_map_s for s in stored if s.in_map_s is not None]
    line = (
        f"upload -> map: stored={len(stored)} in_map={len(done)} "
        f"not_in_map_{max_s:.0f}s_after_uploads={len(stored) - len(done)} polls={polls}"
    )
    if done:
        p50, p90, p99, top = np.percentile(done, [50, 90, 99, 100])
        line += f" | p50 {p50:.1f} s, p90 {p90:.1f} s, p99 {p99:.1f} s, max {top:.1f} s"
    print(line, flush=True)


def report_workers(ports: list[int]) -> None:
    """Each local worker's own metrics: jobs by kind and outcome, mean queue wait, mean upload → fused."""
    from prometheus_client.parser import text_string_to_metric_families

    for k, port in enumerate(ports):
        try:
            text = httpx.get(f"http://127.0.0.1:{port}/metrics", timeout=5).text
        except httpx.HTTPError as exc:
            print(f"worker {k} metrics: unreachable ({exc})", flush=True)
            continue
        jobs: Counter[str] = Counter()
        sums: dict[str, float] = defaultdict(float)
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                if sample.name == "fleetmap_worker_job_duration_seconds_count":
                    jobs[f"{sample.labels['kind']}/{sample.labels['outcome']}"] += int(sample.value)
                    sums[f"n {sample.labels['kind']}"] += sample.value
                elif sample.name == "fleetmap_worker_job_duration_seconds_sum":
                    sums[f"s {sample.labels['kind']}"] += sample.value
                elif sample.name in {
                    "fleetmap_worker_upload_to_fused_seconds_count", "fleetmap_worker_upload_to_fused_seconds_sum",
                    "fleetmap_worker_queue_wait_seconds_count", "fleetmap_worker_queue_wait_seconds_sum",
                }:
                    sums[sample.name] += sample.value
        fused_n = sums["fleetmap_worker_upload_to_fused_seconds_count"]
        wait_n = sums["fleetmap_worker_queue_wait_seconds_count"]
        fused = sums["fleetmap_worker_upload_to_fused_seconds_sum"] / fused_n if fused_n else float("nan")
        wait = sums["fleetmap_worker_queue_wait_seconds_sum"] / wait_n if wait_n else float("nan")
        durations = ", ".join(
            f"{kind} {sums[f's {kind}'] / sums[f'n {kind}']:.1f} s"
            for kind in ("align", "reconstruct") if sums[f"n {kind}"]
        )
        print(
            f"worker {k} metrics (:{port}): jobs {dict(sorted(jobs.items()))}, mean duration {durations or '-'}, "
            f"mean queue wait {wait:.1f} s, upload -> fused n={int(fused_n)} mean {fused:.1f} s",
            flush=True,
        )


async def fusion_phase(
    url: str, operator: str, tile: tuple[int, int], readers: int, max_s: float, timeout_s: float
) -> tuple[Samples, Samples, str]:
    """Trigger a fusion of ``tile``; poll GET /v1/tiles from ``readers`` clients until the job ends or
    ``max_s`` passes. Returns (tile-list samples, job-poll samples, final job state)."""
    reads, polls = Samples(), Samples()
    headers = {"Authorization": f"Bearer {operator}"}
    async with httpx.AsyncClient(base_url=url, timeout=timeout_s, headers=headers) as client:
        response = await client.post(f"/v1/tiles/{tile[0]}/{tile[1]}/fuse")
        if response.status_code != 202:
            return reads, polls, f"trigger failed: {response.status_code} {response.text[:200]}"
        job_id = response.json()["job_id"]
        deadline = time.monotonic() + max_s
        state = "queued"
        saw_running = False

        async def reader() -> None:
            while time.monotonic() < deadline and state in {"queued", "running"}:
                start = time.perf_counter()
                try:
                    status = str((await client.get("/v1/tiles", params={"limit": 100})).status_code)
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                # Only reads while the worker is busy count as "during fusion".
                if saw_running:
                    reads.add(status, time.perf_counter() - start)
                await asyncio.sleep(0.01)

        async def watcher() -> None:
            nonlocal state, saw_running
            while time.monotonic() < deadline and state in {"queued", "running"}:
                start = time.perf_counter()
                job = await client.get(f"/v1/jobs/{job_id}")
                polls.add(str(job.status_code), time.perf_counter() - start)
                if job.status_code == 200:
                    state = job.json()["state"]
                    saw_running = saw_running or state == "running"
                await asyncio.sleep(0.5)

        await asyncio.gather(watcher(), *(reader() for _ in range(readers)))
        return reads, polls, state


# ------------------------------------------------------------------------------------------- main


def report(title: str, samples: Samples, elapsed_s: float | None = None) -> None:
    n = len(samples.latencies)
    ok = sum(c for s, c in samples.statuses.items() if _ok(s))
    errors = {s: c for s, c in samples.statuses.items() if not _ok(s)}
    line = f"{title}: n={n} ok={ok} errors={errors or 0}"
    if elapsed_s:
        line += f" | {ok / elapsed_s:.1f} req/s, {samples.bytes_sent / elapsed_s / 1e6:.1f} MB/s over {elapsed_s:.1f} s"
    line += f" | p50 {samples.pct(50):.1f} ms, p90 {samples.pct(90):.1f} ms, p99 {samples.pct(99):.1f} ms, max {samples.pct(100):.1f} ms"
    print(line, flush=True)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--url", help="target a running deployment instead of starting one")
    parser.add_argument("--token", help="operator token for --url (uploads under any agent id)")
    parser.add_argument("--clients", type=int, default=16, help="concurrent simulated vehicles")
    parser.add_argument("--count", type=int, default=3000, help="total submaps to upload at most")
    parser.add_argument("--duration", type=float, default=30.0, help="upload phase limit, seconds")
    parser.add_argument("--submap-kb", type=float, default=200.0, help="approximate submap size, KB")
    parser.add_argument("--readers", type=int, default=4, help="concurrent GET /v1/tiles clients")
    parser.add_argument("--fusion-seconds", type=float, default=60.0, help="fusion phase limit, seconds")
    parser.add_argument("--no-fusion", action="store_true", help="skip the fusion phase")
    parser.add_argument("--timeout", type=float, default=30.0, help="per-request timeout, seconds")
    parser.add_argument("--api-workers", type=int, default=2, help="uvicorn worker processes")
    parser.add_argument("--fusion-workers", type=int, default=1, help="`fleetmap worker` processes")
    parser.add_argument(
        "--fusion-preset", default=None, help="FLEETMAP_FUSION_PRESET of the local deployment (cpu, paper, tiny)"
    )
    parser.add_argument(
        "--fuse-debounce",
        type=float,
        default=None,
        help="FLEETMAP_FUSE_DEBOUNCE_S of the local deployment (default: the deployment's, 30 s)",
    )
    parser.add_argument("--poll-seconds", type=float, default=1.0, help="upload -> map poll interval")
    parser.add_argument("--no-map-latency", action="store_true", help="skip the upload -> map measurement")
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help="FLEETMAP_TORCH_THREADS of the fusion worker (0: torch's default, every core); the worker "
        "shares this host with the API and PostgreSQL",
    )
    parser.add_argument(
        "--pg-url",
        default=os.environ.get(
            "FLEETMAP_TEST_DATABASE_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
        ),
        help="PostgreSQL server (any database on it) where a fresh benchmark database is created",
    )
    parser.add_argument("--redis-url", default="redis://127.0.0.1:6379/14", help="Celery broker")
    parser.add_argument("--blob-url", default="", help="blob store (default: file store in a temp dir)")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (logs, blobs)")
    return parser


def prepare_uploads(args: argparse.Namespace) -> list[list[Upload]]:
    """Exactly ``--count`` submaps (fewer per vehicle for the last ones), one queue per vehicle."""
    run_id = uuid.uuid4().hex[:6]
    per_vehicle = max(1, -(-args.count // args.clients))
    grid_n = max(4, int(round((args.submap_kb * 1024 / BYTES_PER_GRID_VERTEX) ** 0.5)))
    began = time.perf_counter()
    queues = [vehicle_uploads(v, per_vehicle, grid_n, run_id) for v in range(args.clients)]
    remaining = args.count
    for queue in queues:
        del queue[min(len(queue), remaining) :]
        remaining -= len(queue)
    sizes = [len(u.mesh) for q in queues for u in q]
    print(
        f"prepared {len(sizes)} submaps ({np.mean(sizes) / 1024:.0f} KB each, {grid_n}x{grid_n} grid) "
        f"for {args.clients} vehicles in {time.perf_counter() - began:.1f} s",
        flush=True,
    )
    return [q for q in queues if q]


def report_cpu(before: dict[str, float], after: dict[str, float], samples: Samples, elapsed: float) -> None:
    ok = max(1, sum(c for s, c in samples.statuses.items() if _ok(s)))
    used = {name: after[name] - before[name] for name in after if name in before}
    print(
        "CPU during uploads: "
        + ", ".join(f"{name} {cpu:.1f} s ({cpu / ok * 1e3:.1f} ms/submap)" for name, cpu in used.items())
        + f"; {os.cpu_count()} cores, {elapsed:.1f} s wall",
        flush=True,
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.worker_metrics_ports = []
    if args.url and not args.token:
        parser.error("--url needs --token (an operator token)")
    print(
        f"load average {' '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} cores", flush=True
    )
    queues = prepare_uploads(args)
    vehicles = [q[0].agent_id for q in queues]
    deployment: contextlib.AbstractContextManager[tuple[str, str, dict[str, str], int | None]]
    if args.url:
        deployment = contextlib.nullcontext((args.url.rstrip("/"), args.token, {v: args.token for v in vehicles}, None))
    else:
        deployment = local_deployment(args, vehicles)

    with deployment as (url, operator, tokens, api_pid):
        cpu_before = cpu_snapshot(api_pid)
        samples, elapsed, tiles, stored, polls = asyncio.run(upload_and_map(url, operator, tokens, queues, args))
        report("POST /v1/submaps", samples, elapsed)
        report_cpu(cpu_before, cpu_snapshot(api_pid), samples, elapsed)
        if not args.no_map_latency:
            report_map_latency(stored, polls, args.fusion_seconds)
        if not args.no_fusion and tiles:
            tile = tiles.most_common(1)[0][0]
            reads, job_polls, state = asyncio.run(
                fusion_phase(url, operator, tile, args.readers, args.fusion_seconds, args.timeout)
            )
            print(f"fusion of tile {tile}: job state at the end of the phase: {state}", flush=True)
            report("GET /v1/tiles during fusion", reads)
            report("GET /v1/jobs/{id} during fusion", job_polls)
        report_workers(args.worker_metrics_ports)
    errors = sum(c for s, c in samples.statuses.items() if not _ok(s))
    return 0 if errors == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
