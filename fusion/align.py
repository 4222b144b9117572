"""Joint alignment of a region: one pose per submap across all of the region's tiles (DESIGN.md,
"Multi-tile consistency").

Why: fusing tiles one by one refines each pose against one tile's share of its data and never aligns
sessions that meet in another tile. Here every submap of the region has ONE pose (a single
``PoseSet``), every session's odometry chain is whole, a weak GPS prior anchors the gauge, and each
tile has its own field (feature grid; the geometry/semantic heads are shared by the trained tiles, as
in the paper). Every step draws one tile (probability ∝ the surface area its submaps have inside it, at
least a quarter of an even share), a batch there, and the paper's field terms (SDF, normal, semantic,
confidence, eikonal) on that tile's field, plus odometry and GPS prior on all the region's poses.
(Splitting each step's batch over all tiles was measured ~n× slower per sample on CPU: per-call overhead.)

Progressive LOD runs up to ``align_max_levels`` (by default every level: capped at 8 of 12 levels the
one-tile bench's poses stayed ~0.2 m worse, see ``FusionConfig``).
Iterations: ``align_iterations_per_tile`` × the region's content in full tiles (``fusion.schedule``:
each full tile sees about ``align_iterations_per_tile`` batches, a grazed one adds ~nothing): linear in
the region's data.

Frames: poses live in the *region frame* (map frame shifted by the region's lower tile corner, for
float32 precision); each tile's field lives in its own *tile frame* (map frame shifted by the tile's
lower corner, as ``reconstruct_tile``), so field states are independent of the region they were trained in.

Incremental alignment (``frozen``): previous per-tile field states; submaps with ``free=False`` keep
their poses. Tiles with a state are loaded and held (no field gradient; only the free submaps'
surface samples are drawn there: tracking against the map), tiles without one are trained as usual.
With ``align_incremental_iterations_per_tile`` 0 (the default) nothing is tracked or trained: the free
submaps are placed by the coarse and fine registrations against the held ones, and a tile the map had no
field for is reconstructed cold. Likewise ``align_iterations_per_tile`` 0 without a held map (a re-alignment
with ``realign_iterations_fraction`` 0): the registrations alone, no field returned.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from fusion.coarse import coarse_register
from fusion.config import FusionConfig
from fusion.drift import Drift, corrected_input
from fusion.errors import FusionError
from fusion.field import SemanticSDFField, field_from_state, field_state
from fusion.losses import field_losses, total_loss
from fusion.poses import PoseSet, odometry_consistent_start
from fusion.reconstruct import TileProblem, build_problem, overlapping, set_consensus
from fusion.register import fine_register
from fusion.runtime import cpu_threads, reproducible, resolve_device
from fusion.sampling import SurfacePool, face_geometry, sample_batch
from fusion.schedule import content_iterations, tile_content
from fusion.training import Optimiser, PoseTerms, Reporter, consensus_iterations, loss_values, map_poses
from fusion.types import Pose, ProgressCallback, SubmapInput, TileSpec

TileKey = tuple[int, int]


@dataclass
class AlignResult:
    """``poses``: refined local → map pose per free submap; ``fields``: per-tile field state (tile
    frame, CPU tensors; ``field_from_state`` rebuilds it); ``metrics``: losses, iterations, timing,
    counts, per-tile sample shares."""

    poses: dict[str, Pose]
    fields: dict[TileKey, dict[str, torch.Tensor]]
    metrics: dict[str, Any] = field(default_factory=dict)
    drifts: dict[str, Drift] = field(default_factory=dict)  # per free submap whose drift was corrected


@dataclass
class _Tile:
    key: TileKey
    problem: TileProblem
    index: torch.Tensor  # (m,) region index of each of the problem's submaps
    shift: torch.Tensor  # (4, 4) float64 region frame → tile frame
    field: SemanticSDFField
    frozen: bool
    share: float = 0.0


def align_levels(it: int, iterations: int, config: FusionConfig) -> int:
    """Progressive LOD for alignment: ``lod_start_levels`` → ``align_max_levels`` over
    ``align_lod_full_fraction`` of the iterations."""
    cap = max(config.lod_start_levels, min(config.align_max_levels, config.num_levels))
    span = max(1, int(config.align_lod_full_fraction * iterations))
    return min(cap, config.lod_start_levels + (cap - config.lod_start_levels + 1) * it // span)


def _tile_area(submaps: list[SubmapInput], tile: TileSpec, margin: float) -> float:
    """Surface area (m²) of the submaps' faces whose GPS-posed centroid lies in the tile (+ margin)."""
    lo, hi = np.asarray(tile.xy_min) - margin, np.asarray(tile.xy_max) + margin
    total = 0.0
    for sm in submaps:
        area, _ = face_geometry(sm.mesh.vertices, sm.mesh.faces)
        c = sm.pose_init.apply(sm.mesh.vertices[sm.mesh.faces].mean(axis=1))[:, :2]
        total += float(area[np.all((c >= lo) & (c <= hi), axis=1)].sum())
    return total


def align_region(
    submaps: list[SubmapInput],
    tiles: list[TileSpec],
    config: FusionConfig,
    progress: ProgressCallback | None = None,
    device: str | None = None,
    frozen: dict[TileKey, dict[str, torch.Tensor]] | None = None,
) -> AlignResult:
    """Align the poses of ``submaps`` (map frame ``pose_init``; ``pose_gps`` the prior's anchor) jointly
    over ``tiles`` (one region). Returns one refined map-frame pose per free submap.

    Tiles no submap overlaps are left out (``metrics["skipped"]``); raises ``FusionError`` if none is
    left or no submap is free.
    """
    t_start = time.perf_counter()
    dev = resolve_device(device or config.device)
    with reproducible(dev):
        torch.manual_seed(config.seed)
        gen = torch.Generator().manual_seed(config.seed)
        frozen = frozen or {}
        subs = sorted(submaps, key=lambda s: s.id)  # independent of the input order
        tiles = sorted(tiles, key=lambda t: (t.i, t.j))
        if not tiles:
            raise FusionError("align_region: no tiles", code="empty_tile")
        if not any(s.free for s in subs):
            raise FusionError("align_region: no free submap to align", code="empty_tile")
        size = tiles[0].size_m
        origin = np.array([min(t.i for t in tiles) * size, min(t.j for t in tiles) * size, 0.0])
        poses, gps, coarse, drifts = _region_poses(subs, origin, config, dev)
        subs = [corrected_input(s, drifts.get(s.id)) for s in subs]  # the field sees each submap as corrected
        held = any((t.i, t.j) in frozen for t in tiles)  # a map is there: new submaps are added to it
        per_tile = config.align_incremental_iterations_per_tile if held else config.align_iterations_per_tile
        polish = config.fine_register and config.fine_polish_rounds > 0
        gain = (coarse.get("fine", {}).get("rounds") or [{}])[-1].get("gain", 1.0)
        if per_tile == 0:  # registration only: no field is trained (nor tracked against)
            if polish and _polish_weight(gain, config) > config.fine_weight:
                poses, coarse["polish"] = _polish(subs, poses, gps, config, dev, gain)  # tight matches: trusted more
            return AlignResult(map_poses(poses, origin, subs), {}, drifts=drifts, metrics={
                "losses": {}, "iterations": 0, "incremental": held, "registration_only": True,
                "duration_s": time.perf_counter() - t_start, "duration_train_s": 0.0, "device": str(dev),
                "num_submaps": len(subs), "num_free": int(sum(s.free for s in subs)), "num_tiles": len(tiles),
                "frozen_tiles": [], "skipped": {}, "coarse": coarse})
        built, skipped = _build_tiles(subs, tiles, config, dev, poses, origin, frozen)
        incremental = any(t.frozen for t in built)
        if not incremental:  # no frozen field among the region's tiles: a first alignment after all
            per_tile = config.align_iterations_per_tile
        contents = [tile_content(_posed(t, poses()), t.problem.lo, t.problem.hi, config) for t in built]
        iterations = content_iterations(per_tile, contents, config)  # a grazed tile adds ~nothing
        t_train = time.perf_counter()
        losses = _train(built, subs, poses, gps, config, iterations, gen, progress)
        train_s = time.perf_counter() - t_train
        if polish:
            poses, coarse["polish"] = _polish(subs, poses, gps, config, dev, gain)
        fields = {t.key: field_state(t.field) for t in built}
        metrics = {
            "losses": losses,
            "iterations": iterations,
            "incremental": incremental,
            "duration_s": time.perf_counter() - t_start,
            "duration_train_s": train_s,
            "device": str(dev),
            "num_submaps": len(subs),
            "num_free": int(sum(s.free for s in subs)),
            "num_tiles": len(built),
            "frozen_tiles": [list(t.key) for t in built if t.frozen],
            "tile_pool_points": {f"{t.key[0]}_{t.key[1]}": int(t.problem.pool.points.shape[0]) for t in built},
            "tile_share": {f"{t.key[0]}_{t.key[1]}": round(t.share, 4) for t in built},
            "tile_content": {f"{t.key[0]}_{t.key[1]}": round(c, 4) for t, c in zip(built, contents, strict=True)},
            "skipped": skipped,
            "coarse": coarse,
        }
        return AlignResult(map_poses(poses, origin, subs), fields, metrics, drifts)


def start_poses(submaps: list[SubmapInput], config: FusionConfig, device: str | None = None
                ) -> tuple[dict[str, Pose], dict[str, Any]]:
    """Where the alignment starts, without training: each session's odometry chain on its GPS poses
    (``odom_init``), moved onto the other sessions (``coarse_register``), every submap registered onto the
    others (``fine_register``). Map-frame pose per free submap, and the coarse registration's per-session
    figures plus, under ``"fine"``, the fine registration's rounds (the bench's ``init``/``coarse`` rows)."""
    subs = sorted(submaps, key=lambda s: s.id)
    cents = np.stack([s.pose_init.apply(s.mesh.vertices.mean(0)[None])[0] for s in subs])
    origin = np.array([*np.floor(cents[:, :2].min(0)), 0.0])
    poses, _, coarse, _ = _region_poses(subs, origin, config, resolve_device(device or config.device))
    return map_poses(poses, origin, subs), coarse


def _region_poses(
    subs: list[SubmapInput], origin: np.ndarray, config: FusionConfig, dev: torch.device
) -> tuple[PoseSet, torch.Tensor, dict[str, Any], dict[str, Drift]]:
    """The region's poses (region frame: map frame shifted by ``-origin``): each session's odometry
    chain placed on its GPS poses (fixed submaps dominate), then moved rigidly onto the other sessions
    (``fusion.coarse``), then every submap registered onto the others (``fusion.register``); the GPS anchors
    of the prior; the coarse registration's per-session figures (+ ``"fine"``: the fine registration's); the
    drift corrections the fine registration found (``fine_drift``; the poses are the corrected submaps')."""
    to_region = np.eye(4)
    to_region[:3, 3] = -origin
    init = [to_region @ s.pose_init.matrix() for s in subs]
    gps = torch.tensor(np.stack([to_region @ (s.pose_gps or s.pose_init).matrix() for s in subs]), device=dev)
    cents = [s.mesh.vertices.mean(0) for s in subs]
    start = odometry_consistent_start(subs, init, cents) if config.odom_init else init
    coarse: dict[str, Any] = {}
    if config.coarse_register:
        registered = coarse_register(subs, start, config, dev)
        start, coarse = registered.poses, registered.metrics
    drifts: dict[str, Drift] = {}
    if config.fine_register:
        fine = fine_register(subs, start, gps, config, dev)
        start = fine.poses
        coarse = coarse | {"fine": fine.metrics}
        drifts = {s.id: d for s, d in zip(subs, fine.drifts, strict=False) if s.free and not d.is_identity()}
    poses = _pose_set([corrected_input(s, drifts.get(s.id)) for s in subs], start, dev)
    return poses, gps, coarse, drifts


def _pose_set(subs: list[SubmapInput], mats: list[np.ndarray], dev: torch.device) -> PoseSet:
    """Poses ``mats`` (region frame) of ``subs`` as the centroid-relative ``PoseSet`` the alignment optimises."""
    cents = [s.mesh.vertices.mean(0) for s in subs]
    centroids = np.stack([m[:3, :3] @ c + m[:3, 3] for m, c in zip(mats, cents, strict=True)])
    return PoseSet(torch.tensor(np.stack(mats)), torch.tensor(centroids), torch.tensor([s.free for s in subs])).to(dev)


def _polish(subs: list[SubmapInput], poses: PoseSet, gps: torch.Tensor, config: FusionConfig, dev: torch.device,
            gain: float) -> tuple[PoseSet, dict[str, Any]]:
    """The fine registration once more from the field alignment's poses, over ``fine_polish_rounds`` radii
    from ``fine_polish_max_m`` down to ``fine_min_dist_m`` (or where the surfaces disagree:
    ``fusion.match_weights.spread_floor``): the field's stochastic pose steps (Adam, one
    tile per step) leave each pose a few cm to dm off the optimum of the surfaces it was trained on, and
    on an exact fleet they took the map from 0.07 m (the fine registration) to 0.20 m (3×3 bench, seed 0).

    ``gain``: the first registration's data gain in its last round; the polish's matches count ``fine_weight`` ×
    that (within [1, ``fine_polish_gain_max``]) against the priors: as much more as they proved tight. An
    alignment without field steps (an addition, a re-alignment) is polished too where that weight exceeds the
    registration's: its poses are the registration's optimum at ``fine_weight``, the bend the priors left there
    the same (registration alone from GPS, exact seeds 0 / 1 / 2: 0.094 / 0.053 / 0.071 -> 0.085 / 0.042 / 0.064 m)."""
    with torch.no_grad():
        current = [m for m in poses().cpu().numpy()]
    radii = np.geomspace(max(config.fine_polish_max_m, config.fine_min_dist_m), config.fine_min_dist_m,
                         config.fine_polish_rounds)
    # the drift stays as the first registration found it (``subs`` are already corrected)
    weight = _polish_weight(gain, config)
    fine = fine_register(subs, current, gps, replace(config, fine_drift=False, fine_weight=weight), dev, radii)
    return _pose_set(subs, fine.poses, dev), fine.metrics | {"weight": weight}


def _polish_weight(gain: float, config: FusionConfig) -> float:
    """The polish's match weight: ``fine_weight`` × the registration's data ``gain`` within [1, ``fine_polish_gain_max``]."""
    return config.fine_weight * float(np.clip(gain, 1.0, config.fine_polish_gain_max))


def _build_tiles(
    subs: list[SubmapInput], tiles: list[TileSpec], config: FusionConfig, dev: torch.device, poses: PoseSet,
    origin: np.ndarray, frozen: dict[TileKey, dict[str, torch.Tensor]],
) -> tuple[list[_Tile], dict[str, str]]:
    """Every tile with data: its problem (surface pool, boxes), its field (held when ``frozen`` has one;
    else new, sharing the heads of the other trained tiles) and its sampling share."""
    index_of = {s.id: k for k, s in enumerate(subs)}
    heads: SemanticSDFField | None = None
    built: list[_Tile] = []
    skipped: dict[str, str] = {}
    for tile in tiles:
        key = (tile.i, tile.j)
        state = frozen.get(key)
        chosen = overlapping(subs, tile, config.tile_margin_m)
        if state is not None and not any(s.free for s in chosen):
            continue  # held map, no new data: nothing to track here
        try:
            problem = build_problem(subs, tile, config, dev)
        except FusionError as exc:
            skipped[f"{tile.i}_{tile.j}"] = exc.message
            continue
        index = torch.tensor([index_of[s.id] for s in problem.submaps], device=dev)
        shift = torch.eye(4, dtype=torch.float64, device=dev)
        shift[:3, 3] = torch.tensor(origin - problem.origin, device=dev)
        if state is not None:
            fld = _held_field(problem, state, config, dev)
            if len(problem.pool.points) == 0:  # the new submaps only graze this tile: nothing to track
                continue
        else:
            fld = SemanticSDFField(config, problem.lo, problem.hi).to(dev)
            if heads is None:
                heads = fld
            else:  # heads shared by the trained tiles (the paper): one decoder, per-tile grids
                fld.geo, fld.sem = heads.geo, heads.sem
        t = _Tile(key, problem, index, shift, fld, state is not None)
        t.share = _tile_area([s for s in problem.submaps if s.free] if t.frozen else problem.submaps,
                             tile, config.tile_margin_m)
        allocate = getattr(fld.grid, "allocate", None)
        if callable(allocate) and not t.frozen:
            with torch.no_grad():
                allocate(fld.norm(_posed(t, poses())))
        built.append(t)
    if not built:
        raise FusionError("align_region: no tile has data to align against", code="empty_tile")
    _normalise_shares(built)
    return built, skipped


def _held_field(problem: TileProblem, state: dict[str, torch.Tensor], config: FusionConfig,
                dev: torch.device) -> SemanticSDFField:
    """A frozen field of an earlier alignment; the problem's pool keeps the free submaps' samples only, and
    of those only the ones within ``align_track_support_m`` of the held submaps' surface (at the starting
    poses): away from the map's data the frozen field's zero level is whatever its grid extrapolates, and
    tracking a new street against it drags the new session off (3x3 exact bench, seed 0: the added
    session ended 2.6 m off its truth, worse than its GPS)."""
    from scipy.spatial import cKDTree

    fld = field_from_state(state, config).to(dev)
    fld.requires_grad_(False)
    p = problem.pool
    free = torch.tensor([s.free for s in problem.submaps], device=dev)[p.submap]
    keep = free.clone()
    if config.align_track_support_m > 0:
        with torch.no_grad():
            pose = problem.poses()[p.submap].float()
            posed = ((pose[:, :3, :3] @ p.points[:, :, None])[:, :, 0] + pose[:, :3, 3]).cpu().numpy()
        is_free = free.cpu().numpy()
        near = np.zeros(len(posed), bool)
        if not is_free.all():
            dist, _ = cKDTree(posed[~is_free]).query(posed[is_free], distance_upper_bound=config.align_track_support_m,
                                                          workers=cpu_threads())
            near[is_free] = np.isfinite(dist)
        keep &= torch.as_tensor(near, device=dev)
    problem.pool = SurfacePool(p.points[keep], p.normals[keep], p.labels[keep], p.submap[keep], p.conf_target[keep])
    return fld


def _normalise_shares(built: list[_Tile]) -> None:
    """Sampling probability per tile ∝ its surface area, at least a quarter of an even share."""
    total_area = sum(t.share for t in built) or 1.0
    n = len(built)
    for t in built:
        t.share = max(t.share / total_area, 0.25 / n)
    norm = sum(t.share for t in built)
    for t in built:
        t.share /= norm


def _train(
    built: list[_Tile], subs: list[SubmapInput], poses: PoseSet, gps: torch.Tensor, config: FusionConfig,
    iterations: int, gen: torch.Generator, progress: ProgressCallback | None,
) -> dict[str, float]:
    """One tile per step (drawn by share): its field terms, plus odometry and GPS prior on every pose."""
    dev = gps.device
    shares = torch.tensor([t.share for t in built], dtype=torch.float64)
    pose_terms = PoseTerms.of(subs, dev)
    params = list({id(p): p for t in built if not t.frozen for p in t.field.parameters()}.values())
    # the single-tile schedule's warm-up fraction (fields take a rough shape before poses move); none
    # when every tile is a held map
    warmup = round(config.pose_warmup * iterations / max(config.iterations, 1)) if params else 0
    optimiser = Optimiser(params, poses, config, iterations, warmup)
    consensus = consensus_iterations(config, iterations)
    if any(t.frozen for t in built):
        for t in built:
            t.field.set_active_levels(config.num_levels)
    report = Reporter(progress, iterations, "align")
    for it in range(iterations):
        if it in consensus:
            with torch.no_grad():
                current = poses()
            for t in built:
                if not t.frozen:
                    _update_consensus(t, current, config)
        levels = align_levels(it, iterations, config)
        for t in built:
            if not t.frozen:
                t.field.set_active_levels(levels)
        region = poses()
        t = built[int(torch.multinomial(shares, 1, generator=gen))]  # one tile per step (the paper)
        batch = sample_batch(t.problem.pool, t.problem.boxes, (t.shift @ region[t.index]).float(), t.problem.lo,
                             t.problem.hi, config.surface_samples, 0 if t.frozen else config.space_samples,
                             config.sigma_s, gen)
        terms, _ = field_losses(t.field, batch, config, gen)
        terms |= pose_terms.losses(region, gps)
        loss = total_loss(terms, config)
        optimiser.step(it, loss, planar=t.field.finest_active_cell_m() > config.align_planar_cell_m > 0)
        report(it, terms, loss)
    return loss_values(terms, loss)


def _posed(t: _Tile, region: torch.Tensor) -> torch.Tensor:
    """The tile's surface pool (P, 3) at the region poses ``region`` (M, 4, 4), tile frame."""
    pose = (t.shift @ region[t.index])[t.problem.pool.submap].float()
    return (pose[:, :3, :3] @ t.problem.pool.points[:, :, None])[:, :, 0] + pose[:, :3, 3]


def _update_consensus(t: _Tile, region: torch.Tensor, config: FusionConfig) -> None:
    """Cross-session confidence targets of a tile's pool at the current region poses."""
    set_consensus(t.problem, t.shift @ region[t.index], config)
