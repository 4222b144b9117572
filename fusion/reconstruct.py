"""Joint optimisation of a tile's neural semantic SDF and its submaps' poses (the paper's algorithm).

Frames: inputs and outputs are in the map frame; internally everything lives in the *tile* frame, the
map frame shifted by the tile's lower corner ``(i·S, j·S, 0)`` so float32 keeps precision far from the
map origin.

Per iteration: set the level of detail → pose the submaps → draw a batch (surface + space samples) →
losses (SDF, normal, semantic, eikonal, confidence, odometry, GPS prior) → AdamW step → LR decay.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree

from fusion.config import FusionConfig
from fusion.errors import FusionError
from fusion.extract import extract_mesh
from fusion.field import SemanticSDFField, field_from_state, field_state
from fusion.labels import NUM_CLASSES
from fusion.losses import field_losses, total_loss
from fusion.poses import PoseSet, odometry_consistent_start
from fusion.runtime import cpu_threads, reproducible, resolve_device
from fusion.sampling import (
    SpaceBoxes,
    SurfacePool,
    consensus_targets,
    sample_batch,
    sample_surface_pool,
    space_boxes,
)
from fusion.schedule import content_iterations, tile_content
from fusion.training import Optimiser, PoseTerms, Reporter, consensus_iterations, loss_values, map_poses
from fusion.types import (
    FusedMesh,
    FusionResult,
    ProgressCallback,
    ProgressEvent,
    SubmapInput,
    TileSpec,
    WarmKind,
)


def overlapping(submaps: list[SubmapInput], tile: TileSpec, margin_m: float) -> list[SubmapInput]:
    """Submaps whose initially posed bounding box meets the tile grown by ``margin_m`` (xy)."""
    lo = np.asarray(tile.xy_min) - margin_m
    hi = np.asarray(tile.xy_max) + margin_m
    out = []
    for sm in submaps:
        v = sm.mesh.vertices
        if len(v) == 0 or len(sm.mesh.faces) == 0:
            continue
        corners = np.array([[x, y, z] for x in (v[:, 0].min(), v[:, 0].max())
                            for y in (v[:, 1].min(), v[:, 1].max()) for z in (v[:, 2].min(), v[:, 2].max())])
        xy = sm.pose_init.apply(corners)[:, :2]
        if np.all(xy.max(0) >= lo) and np.all(xy.min(0) <= hi):
            out.append(sm)
    return out


@dataclass
class TileProblem:
    """Everything the optimiser needs for one tile, on the target device (tile frame)."""

    submaps: list[SubmapInput]
    origin: np.ndarray  # (3,) map-frame position of the tile frame's origin, metres
    lo: torch.Tensor  # (3,) tile box, tile frame
    hi: torch.Tensor  # (3,)
    pool: SurfacePool
    boxes: SpaceBoxes
    box_lo_np: np.ndarray  # (M, 3) local space boxes (numpy, for consensus)
    box_hi_np: np.ndarray
    pool_session: np.ndarray  # (P,)
    submap_session: np.ndarray  # (M,)
    poses: PoseSet
    init_tile: torch.Tensor  # (M, 4, 4) GPS poses (the prior's anchor), tile frame (float64)


def build_problem(submaps: list[SubmapInput], tile: TileSpec, config: FusionConfig, dev: torch.device,
                  inflate_thin: bool = False) -> TileProblem:
    """The tile's surface pool, space boxes and poses. ``inflate_thin``: the pool points of
    ``thin_classes`` move ``thin_inflate_m`` out along their normals (``inflate_thin_surfaces``)."""
    chosen = overlapping(submaps, tile, config.tile_margin_m)
    if not chosen:
        raise FusionError(
            f"no submap overlaps tile ({tile.i}, {tile.j}) (size {tile.size_m} m, margin {config.tile_margin_m} m)",
            code="empty_tile",
        )
    origin = np.array([tile.xy_min[0], tile.xy_min[1], 0.0])
    shift = np.eye(4)
    shift[:3, 3] = -origin
    init = [shift @ sm.pose_init.matrix() for sm in chosen]
    gps = [shift @ (sm.pose_gps or sm.pose_init).matrix() for sm in chosen]
    rng = np.random.default_rng(config.seed)
    m = config.tile_margin_m
    xy_lo, xy_hi = np.array([-m, -m]), np.array([tile.size_m + m, tile.size_m + m])
    big = 1e6
    pts, nrm, lab, own = sample_surface_pool(
        chosen, init, np.array([*xy_lo, -big]), np.array([*xy_hi, big]), config.pool_points, rng,
        config.class_balance, config.class_weight_max,
    )
    if len(pts) == 0:
        raise FusionError(f"the submaps near tile ({tile.i}, {tile.j}) have no surface inside it", code="empty_tile")
    mats = np.stack(init)[own]
    z = np.einsum("nj,nj->n", mats[:, 2, :3], pts) + mats[:, 2, 3]
    z_lo, z_hi = np.quantile(z, 0.001) - config.slab_pad_m, np.quantile(z, 0.999) + config.slab_pad_m
    z_hi = min(z_hi, z_lo + config.slab_max_m)
    keep = (z >= z_lo) & (z <= z_hi)
    pts, nrm, lab, own = pts[keep], nrm[keep], lab[keep], own[keep]
    if inflate_thin and config.thin_inflate_m > 0:
        pts = inflate_thin_surfaces(pts, nrm, lab, config.thin_label_ids(), config.thin_inflate_m)

    centroids_local = [sm.mesh.vertices.mean(0) for sm in chosen]
    start = odometry_consistent_start(chosen, init, centroids_local) if config.odom_init else init
    centroids = np.stack([s[:3, :3] @ c + s[:3, 3] for s, c in zip(start, centroids_local, strict=True)])
    blo, bhi = space_boxes(chosen, height_m=4.0, margin_m=1.0)
    lo = torch.tensor([xy_lo[0], xy_lo[1], z_lo], dtype=torch.float32, device=dev)
    hi = torch.tensor([xy_hi[0], xy_hi[1], z_hi], dtype=torch.float32, device=dev)
    # space sampling weight: box footprint (m²) of each submap; a slab fraction is not needed as the
    # samples outside the tile box are rejected
    weight = np.prod(bhi[:, :2] - blo[:, :2], axis=1)
    f32: dict[str, Any] = {"dtype": torch.float32, "device": dev}
    sessions = {s: k for k, s in enumerate(sorted({sm.session_id for sm in chosen}))}
    submap_session = np.array([sessions[sm.session_id] for sm in chosen])
    pool = SurfacePool(
        torch.tensor(pts, **f32), torch.tensor(nrm, **f32),
        torch.tensor(lab, dtype=torch.long, device=dev), torch.tensor(own, dtype=torch.long, device=dev),
        torch.ones(len(pts), **f32),
    )
    boxes = SpaceBoxes(torch.tensor(blo, **f32), torch.tensor(bhi, **f32), torch.tensor(weight, dtype=torch.float32))
    free = torch.tensor([sm.free for sm in chosen])
    poses = PoseSet(torch.tensor(np.stack(start)), torch.tensor(centroids), free).to(dev)
    return TileProblem(chosen, origin, lo, hi, pool, boxes, blo, bhi, submap_session[own], submap_session, poses,
                       torch.tensor(np.stack(gps), dtype=torch.float64, device=dev))


def inflate_thin_surfaces(points: np.ndarray, normals: np.ndarray, labels: np.ndarray, thin: list[int],
                          offset_m: float) -> np.ndarray:
    """``points`` with those labelled one of ``thin`` moved ``offset_m`` out along their (unit) normals.

    A structure thinner than about two of the field's finest cells (a 0.1 m fence, a 0.05 m sign plate, a
    0.24 m pole against 0.16 m cells) has no interior the grid can hold, and a 0.25 m extraction lattice
    steps over what is left: it vanishes or breaks up. Moved out, its surfaces enclose an interior
    ``2 × offset_m`` thicker; with ``offset_m`` under the evaluation distance the surface stays within it."""
    out = np.array(points, copy=True)
    sel = np.isin(labels, thin)
    out[sel] += offset_m * normals[sel]
    return out


def update_consensus(problem: TileProblem, config: FusionConfig) -> float:
    """Recompute the confidence targets of the surface pool from the current poses; returns their mean."""
    with torch.no_grad():
        set_consensus(problem, problem.poses(), config)
    return float(problem.pool.conf_target.mean())


def set_consensus(problem: TileProblem, poses_tile: torch.Tensor, config: FusionConfig) -> None:
    """The pool's confidence targets (``fusion.sampling.consensus_targets``) at ``poses_tile`` (M, 4, 4),
    the tile frame: free-space evidence (``consensus_evidence``) takes the posed normals."""
    pool = problem.pool
    pose = poses_tile[pool.submap].float()
    points = (pose[:, :3, :3] @ pool.points[:, :, None])[:, :, 0] + pose[:, :3, 3]
    normals = (pose[:, :3, :3] @ pool.normals[:, :, None])[:, :, 0] if config.consensus_evidence == "free_space" else None
    session = torch.as_tensor(problem.pool_session, device=points.device)
    movable = torch.isin(pool.labels, torch.tensor(config.movable_label_ids(), dtype=pool.labels.dtype,
                                                   device=pool.labels.device))
    pool.conf_target = consensus_targets(points, session, config.consensus_radius_m, config.consensus_cover_m,
                                         keep_fraction=config.consensus_keep, c_th=config.c_th, normals=normals,
                                         column_m=config.consensus_column_m, movable=movable,
                                         movable_sessions=config.consensus_movable_sessions,
                                         movable_cover_m=config.consensus_movable_cover_m,
                                         overhang_m=config.consensus_overhang_m,
                                         movable_below_m=config.consensus_movable_below_m)


def active_levels(it: int, config: FusionConfig) -> int:
    """Progressive LOD: ``lod_start_levels`` at first, all levels after ``lod_full_fraction`` of training."""
    span = max(1, int(config.lod_full_fraction * config.iterations))
    extra = config.num_levels - config.lod_start_levels
    return min(config.num_levels, config.lod_start_levels + (extra + 1) * it // span)


def reconstruct_tile(
    submaps: list[SubmapInput],
    tile: TileSpec,
    config: FusionConfig,
    progress: ProgressCallback | None = None,
    border_pins: dict | None = None,
    device: str | None = None,
    warm: dict[str, torch.Tensor] | None = None,
    warm_kind: WarmKind = "alignment",
) -> FusionResult:
    """Fuse the submaps touching ``tile`` into a semantic mesh (map frame) and refine free submaps'
    poses (the service holds every pose: its alignment jobs own them).

    ``warm``: a field state of this tile (its region alignment's, trained on the same data at nearly
    these poses) to start from: ``recon_warm_fraction`` of the steps at every level instead of a cold
    start's full progressive schedule (0: always cold). ``warm_kind`` "reconstruction": the state is the
    tile's previous reconstruction (its held submaps at the poses it was trained at, new submaps added):
    ``refusion_warm_fraction`` of the steps; "carried": that reconstruction carried along with the tile's
    surface (``fusion.field.moved_state``) by a re-alignment that brought the tile no new submap:
    ``refusion_carried_fraction``. The result carries the trained field's state
    (``FusionResult.field_state``).

    Raises ``FusionError`` when no submap overlaps the tile (+ margin).
    """
    t_start, cpu_start = time.perf_counter(), time.process_time()
    dev = resolve_device(device or config.device)
    with reproducible(dev):
        torch.manual_seed(config.seed)
        gen = torch.Generator().manual_seed(config.seed)
        problem = build_problem(submaps, tile, config, dev, inflate_thin=True)
        content = tile_content(_posed_pool(problem), problem.lo, problem.hi, config)  # steps ∝ content (recorded)
        steps = content_iterations(config.iterations, [content], config)
        fraction = warm_fraction(config, warm_kind)
        field = _warm_field(warm, fraction, config, dev)
        if field is not None:
            steps = max(1, round(steps * fraction))
        warm_start = field is not None
        config = config.with_(iterations=steps)
        if field is None:
            field = SemanticSDFField(config, problem.lo, problem.hi).to(dev)
            allocate = getattr(field.grid, "allocate", None)  # sparse ("octree") grids keep cells near the data only
            if callable(allocate):
                allocate(field.norm(_posed_pool(problem)))
        t_train = time.perf_counter()
        losses, evaluated = _train(problem, field, config, gen, progress, all_levels=warm_start,
                                   settled=warm_start and warm_kind == "carried")
        train_s = time.perf_counter() - t_train
        t_extract = time.perf_counter()
        mesh, border, ex_stats = _extract(problem, field, tile, config, border_pins, progress, dev)
        extract_s = time.perf_counter() - t_extract
        metrics = {
            "losses": losses,
            "iterations": config.iterations,
            "content": content,
            "duration_s": time.perf_counter() - t_start,
            # CPU seconds of every thread of the process (other work running in it meanwhile counts too): on a shared
            # machine less inflated by the load than duration_s
            "cpu_s": time.process_time() - cpu_start,
            "duration_train_s": train_s,
            "duration_extract_s": extract_s,
            "points_per_s": evaluated / max(train_s, 1e-9),
            "device": str(dev),
            "warm_start": warm_start,
            "warm_kind": warm_kind if warm_start else None,
            "num_submaps": len(problem.submaps),
            "num_free": int(sum(sm.free for sm in problem.submaps)),
            "pool_points": int(problem.pool.points.shape[0]),
            "mean_conf_target": float(problem.pool.conf_target.mean()),
            "extract": ex_stats,
        }
        poses = map_poses(problem.poses, problem.origin, problem.submaps)
        return FusionResult(mesh, poses, metrics, config.to_dict(), border, field_state(field))


def warm_fraction(config: FusionConfig, kind: WarmKind) -> float:
    """The share of a cold start's steps a reconstruction warm-started from a field of ``kind`` trains."""
    return {"alignment": config.recon_warm_fraction, "reconstruction": config.refusion_warm_fraction,
            "carried": config.refusion_carried_fraction}[kind]


def _warm_field(warm: dict[str, torch.Tensor] | None, fraction: float, config: FusionConfig,
                dev: torch.device) -> SemanticSDFField | None:
    """The warm-start field, or None: no state, warm starts off (``fraction`` 0), or a state of another
    field layout (the preset changed since the alignment: a cold start, not a failed job)."""
    if warm is None or fraction <= 0:
        return None
    try:
        return field_from_state(warm, config).to(dev)
    except (KeyError, RuntimeError):
        return None


def _train(
    problem: TileProblem, field: SemanticSDFField, config: FusionConfig, gen: torch.Generator,
    progress: ProgressCallback | None, all_levels: bool = False, settled: bool = False,
) -> tuple[dict[str, float], int]:
    """The paper's loop on one tile: LOD (``all_levels``: every level from the start, a warm field) →
    posed batch → field + pose terms → step. ``settled``: the field learnt this data's consensus targets
    already, no new submap to build. Returns the last losses and the number of field evaluations."""
    terms_of_poses = PoseTerms.of(problem.submaps, problem.lo.device)
    optimiser = Optimiser(list(field.parameters()), problem.poses, config, config.iterations, config.pose_warmup)
    consensus = consensus_iterations(config, config.iterations)
    if consensus and not any(sm.free for sm in problem.submaps):
        # every pose held (the service's reconstructions): the targets, a function of the poses, come out the same
        # each time, so once, at the first of consensus_at's steps. Not at step 0: until then the targets are 1
        # everywhere, and setting them from the start let more transients survive (exact seed 1 at the true
        # poses, `--rows oracle`: 8.0 -> 12.7 %, geo / sem F unchanged)
        # A field carried to a tile no new submap reaches (``settled``) learnt these targets already and has no new
        # surface to build: they hold from its first step, else its first steps teach confidence 1 to what the
        # consensus had dropped and its few steps do not take it back
        consensus = {0 if settled else min(consensus)}
    report = Reporter(progress, config.iterations, "train")
    evaluated = 0
    for it in range(config.iterations):
        if it in consensus:
            update_consensus(problem, config)
        field.set_active_levels(config.num_levels if all_levels else active_levels(it, config))
        poses64 = problem.poses()
        batch = sample_batch(problem.pool, problem.boxes, poses64.float(), problem.lo, problem.hi,
                             config.surface_samples, config.space_samples, config.sigma_s, gen)
        terms, n_eval = field_losses(field, batch, config, gen)
        terms |= terms_of_poses.losses(poses64, problem.init_tile)
        loss = total_loss(terms, config)
        optimiser.step(it, loss)
        evaluated += n_eval
        report(it, terms, loss)
    return loss_values(terms, loss), evaluated


def _extract(
    problem: TileProblem, field: SemanticSDFField, tile: TileSpec, config: FusionConfig, border_pins: dict | None,
    progress: ProgressCallback | None, dev: torch.device,
) -> tuple[FusedMesh, dict[str, Any], dict[str, Any]]:
    """The tile's mesh on the global lattice at full LOD (map frame), its border samples, statistics."""
    field.eval()
    field.set_active_levels(config.num_levels)
    return extract_mesh(
        _sdf_fn(field, problem.origin, config.extract_chunk, dev),
        _attr_fn(field, problem.origin, config.extract_chunk, dev),
        tile,
        (float(problem.lo[2]) + problem.origin[2], float(problem.hi[2]) + problem.origin[2]),
        config.extract_voxel_m,
        config.extract_block,
        config.extract_band,
        config.c_th,
        border_pins,
        face_labels=config.face_labels,
        support=_posed_pool(problem).double().cpu().numpy() + problem.origin,
        support_labels=problem.pool.labels.cpu().numpy(),
        support_m=config.extract_support_m,
        deflate_labels=config.thin_label_ids() if config.thin_deflate else (),
        deflate_m=config.thin_inflate_m,
        split_labels=config.face_label_split,
        detail=_posed_uploads(problem, config.c_th, tile) if config.detail_m > 0 else None,
        detail_m=config.detail_m,
        relabel=(config.ground_label_ids(), _label_fn(field, problem.origin, config.extract_chunk, dev), NUM_CLASSES)
        if config.label_geometry else None,
        step=(lambda done, total: progress(ProgressEvent(done, total, {}, "extract"))) if progress else None,
    )


# a face's own surface samples: the pool draws a few per m² of a submap, so four lie within half a metre of most
# faces (a pole's too); a face with none that close is one the pool never sampled
KEPT_RADIUS_M = 0.5


def _posed_uploads(problem: TileProblem, kept_above: float | None = None, tile: TileSpec | None = None,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Every submap of the tile's problem at its current pose (map frame): vertices (n, 3), faces (m, 3).
    ``kept_above``: only the faces the cross-session consensus kept, i.e. whose own surface samples nearby
    (the submap's pool points within ``KEPT_RADIUS_M`` of the face's centre, up to four) have a mean
    confidence target at or above it; a face with none nearby is left out. ``tile``: only the faces whose
    centre lies in its square (the only ones the detail takes, ``fusion.extract.detail_faces``)."""
    with torch.no_grad():
        poses = problem.poses().double().cpu().numpy()
    pool_pts = problem.pool.points.cpu().numpy()
    pool_sub = problem.pool.submap.cpu().numpy()
    pool_conf = problem.pool.conf_target.cpu().numpy()
    order = np.argsort(pool_sub, kind="stable")  # each submap's pool points, in pool order, as one slice
    bounds = np.searchsorted(pool_sub[order], np.arange(len(problem.submaps) + 1))
    verts, faces, offset = [], [], 0
    for k, (sm, pose) in enumerate(zip(problem.submaps, poses, strict=True)):
        v = np.asarray(sm.mesh.vertices, np.float64)
        f = np.asarray(sm.mesh.faces, np.int64)
        posed = v @ pose[:3, :3].T + pose[:3, 3] + problem.origin
        centre = (v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3  # local frame (the pool's)
        if tile is not None and len(f):
            c = centre @ pose[:3, :3].T + pose[:3, 3] + problem.origin
            (x0, y0), size = tile.xy_min, tile.size_m
            inside = (c[:, 0] >= x0) & (c[:, 0] < x0 + size) & (c[:, 1] >= y0) & (c[:, 1] < y0 + size)
            f, centre = f[inside], centre[inside]
        if kept_above is not None and len(f):
            own = order[bounds[k]:bounds[k + 1]]
            if len(own):
                dist, idx = cKDTree(pool_pts[own]).query(centre, k=4, distance_upper_bound=KEPT_RADIUS_M,
                                                                   workers=cpu_threads())
                found = np.isfinite(dist)
                conf = np.where(found, pool_conf[own][np.minimum(idx, len(own) - 1)], 0.0)
                mean = conf.sum(axis=1) / np.maximum(found.sum(axis=1), 1)
                f = f[found.any(axis=1) & (mean >= kept_above)]
            else:
                f = f[:0]
        verts.append(posed)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(verts), np.concatenate(faces)


def _posed_pool(problem: TileProblem) -> torch.Tensor:
    """Surface pool ``(P, 3)`` at the current poses, tile frame (metres)."""
    with torch.no_grad():
        pose = problem.poses()[problem.pool.submap].float()  # (P, 4, 4)
        return (pose[:, :3, :3] @ problem.pool.points[:, :, None])[:, :, 0] + pose[:, :3, 3]


def _chunks(x_map: np.ndarray, origin: np.ndarray, chunk: int, dev: torch.device) -> Iterator[tuple[slice, torch.Tensor]]:
    """Map-frame query points in chunks of ``chunk``: (their slice, tile-frame float32 tensor on ``dev``)."""
    for a in range(0, len(x_map), chunk):
        yield slice(a, a + chunk), torch.tensor(x_map[a : a + chunk] - origin, dtype=torch.float32, device=dev)


def _sdf_fn(field: SemanticSDFField, origin: np.ndarray, chunk: int, dev: torch.device):  # noqa: ANN202
    """Map-frame numpy SDF query (no grad, chunked)."""

    def fn(x_map: np.ndarray) -> np.ndarray:
        out = np.empty(len(x_map), np.float64)
        with torch.no_grad():
            for part, x in _chunks(x_map, origin, chunk, dev):
                out[part] = field.sdf(x).double().cpu().numpy()
        return out

    return fn


def _label_fn(field: SemanticSDFField, origin: np.ndarray, chunk: int, dev: torch.device):  # noqa: ANN202
    """Map-frame numpy query of the head's argmax label (n,) among the classes an ``allowed`` (C,) mask keeps."""

    def fn(x_map: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        labels = np.empty(len(x_map), np.int64)
        barred = torch.tensor(~np.asarray(allowed, bool), device=dev)
        with torch.no_grad():
            for part, x in _chunks(x_map, origin, chunk, dev):
                logits = field(x)[2]
                assert logits is not None
                labels[part] = logits.masked_fill(barred, -torch.inf).argmax(-1).cpu().numpy()
        return labels

    return fn


def _attr_fn(field: SemanticSDFField, origin: np.ndarray, chunk: int, dev: torch.device):  # noqa: ANN202
    """Map-frame numpy query of confidence (n,) and argmax label (n,)."""

    def fn(x_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        conf = np.empty(len(x_map), np.float32)
        labels = np.empty(len(x_map), np.int64)
        with torch.no_grad():
            for part, x in _chunks(x_map, origin, chunk, dev):
                _, c_logit, logits = field(x)
                assert logits is not None
                conf[part] = torch.sigmoid(c_logit).cpu().numpy()
                labels[part] = logits.argmax(-1).cpu().numpy()
        return conf, labels

    return fn
