"""Gauge-aligned scoring of a fused mesh against the ground truth: the one implementation used by the
one-tile bench (``fusion.eval.bench``), the multi-tile bench (``fusion.eval.bench_region``), the ablation
harness (``fusion.eval.harness``) and ``fleetmap demo`` (``service.client.demo``).

Frames and units: every point, pose and region is in the map frame, metres; submap vertices (the
anchors) are in their submap's local frame. A gauge is a rigid ``(R, t)``, ``x ↦ R x + t``, taking the
fused map's frame to the truth's (GPS fixes the map's absolute placement only to a few decimetres, more
than the F-score distance d = 0.2 m, so the method's quality is scored after that alignment).

Torch-free (the demo's process imports it).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from fusion.eval import metrics
from fusion.labels import LABELS
from fusion.types import FusedMesh, Pose, rotation_angle_deg

if TYPE_CHECKING:
    from fusion.offline import LoadedSubmap

Gauge = tuple[np.ndarray, np.ndarray]  # (R (3, 3), t (3,)): x ↦ R x + t, map frame, metres
ANCHORS_PER_SUBMAP = 64
D = metrics.DEFAULT_D
# figures reported twice, gauge-aligned (plain key) and absolute (``abs_`` key)
ABS_KEYS = ("geo_p", "geo_r", "geo_f", "sem_f", "transient_survival", "contested_survival", "per_class_f")
IDENTITY: Gauge = (np.eye(3), np.zeros(3))


@dataclass
class TruthPoints:
    """The ground truth of one region as point sets (map frame, metres), already cropped to ``region``:
    ``gt_all`` every surface, ``gt_observed`` the surface some submap saw (recall is measured on it),
    ``transient`` the observed parts of transient objects standing clear of the static world;
    ``contested`` those of them another session saw through (``contested_transients``; None: unknown)."""

    region: metrics.Region | None  # None: the whole world
    gt_all: metrics.PointSet
    gt_observed: metrics.PointSet
    transient: metrics.PointSet
    contested: metrics.PointSet | None = None

    def cropped(self, region: metrics.Region) -> TruthPoints:
        """The same truth cropped to a sub-``region``."""
        return TruthPoints(region, metrics.crop(self.gt_all, region), metrics.crop(self.gt_observed, region),
                           metrics.crop(self.transient, region),
                           None if self.contested is None else metrics.crop(self.contested, region))


def merge_meshes(meshes: list[FusedMesh]) -> FusedMesh:
    """One mesh holding all ``meshes`` (vertices concatenated; faces re-indexed)."""
    meshes = [m for m in meshes if len(m.faces)]
    if not meshes:
        return FusedMesh.empty()
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return FusedMesh(
        np.concatenate([m.vertices for m in meshes]).astype(np.float32),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]).astype(np.int32),
        np.concatenate([m.vertex_labels for m in meshes]),
        np.concatenate([m.vertex_confidence for m in meshes]),
        np.concatenate([m.face_labels for m in meshes]),
    )


def sample_truth(truth: Any, region: metrics.Region | None, density: float = metrics.DEFAULT_DENSITY,
                 uploads: dict[str, np.ndarray] | None = None) -> TruthPoints:
    """Sample the simulator's ``truth`` (``GroundTruth``) at ``density`` points per m² (seeds 2, 3, 4 for
    all, observed and transient surfaces) and crop it to ``region``; transient points within 2 d of
    the static surface are dropped (they cannot be told apart). ``uploads`` (submap name → its mesh's
    local-frame vertices) gives the ``contested`` share of the transients (``contested_transients``)."""
    gt = metrics.crop(metrics.sample_surface(truth.vertices, truth.faces, truth.labels, density, seed=2), region)
    obs = metrics.crop(metrics.sample_surface(truth.vertices, truth.faces, truth.labels, density, seed=3,
                                              face_mask=truth.observed), region)
    tr = metrics.crop(metrics.sample_surface(truth.transient_vertices, truth.transient_faces, truth.transient_labels,
                                             density, seed=4, face_mask=truth.transient_observed), region)
    if len(tr) and len(gt):
        dist, _ = cKDTree(gt.points).query(tr.points, distance_upper_bound=2 * D)
        tr = tr.subset(dist > 2 * D)
    contested = None
    if uploads is not None and truth.sessions:
        contested = tr.subset(contested_transients(truth, tr.points, uploads))
    return TruthPoints(region, gt, obs, tr, contested)


def contested_transients(truth: Any, points: np.ndarray, uploads: dict[str, np.ndarray], cell: float = 0.5,
                         clearance: float = 0.3) -> np.ndarray:
    """Mask over transient ``points`` (map frame): another session than the object's owner saw through the
    point, i.e. uploaded surface (at its true pose) within one ``cell`` horizontally and more than
    ``clearance`` below it: the road where a parked car stood when the others drove by. Only these can be
    told from the static world by cross-session evidence; an object where no other session looked cannot."""
    out = np.zeros(len(points), bool)
    if not len(points):
        return out
    tv, tf = truth.transient_vertices, truth.transient_faces
    owner = truth.transient_session[cKDTree(tv[tf].mean(axis=1)).query(points)[1]]
    for k in np.unique(owner):
        others = [truth.poses[n].apply(np.asarray(v, np.float64)) for n, v in uploads.items()
                  if truth.sessions.get(n, k) != k]
        if not others:
            continue
        ref = np.concatenate(others)
        lowest: dict[tuple[int, int], float] = {}
        cells = np.floor(ref[:, :2] / cell).astype(np.int64)
        order = np.lexsort((ref[:, 2], cells[:, 1], cells[:, 0]))
        keys, first = np.unique(cells[order], axis=0, return_index=True)
        for (cx, cy), z in zip(keys.tolist(), ref[order[first], 2].tolist(), strict=True):
            lowest[(cx, cy)] = z
        mine = np.flatnonzero(owner == k)
        pc = np.floor(points[mine, :2] / cell).astype(np.int64)
        for n, (cx, cy) in zip(mine.tolist(), pc.tolist(), strict=True):
            floor = min(lowest.get((cx + dx, cy + dy), np.inf) for dx in (-1, 0, 1) for dy in (-1, 0, 1))
            out[n] = floor < points[n, 2] - clearance
    return out


def anchors(vertices: np.ndarray, per_submap: int = ANCHORS_PER_SUBMAP) -> np.ndarray:
    """``per_submap`` vertices (local frame) spread evenly over a submap's vertex list (all if fewer)."""
    v = np.asarray(vertices, np.float64)
    return v[np.linspace(0, len(v) - 1, min(per_submap, len(v))).astype(int)]


def gauge_fit(estimated: Sequence[Pose], true: Sequence[Pose], vertices: Iterable[np.ndarray]) -> Gauge:
    """Rigid gauge taking the fused map to the truth: Umeyama fit of each submap's anchors (from its
    local-frame ``vertices``) carried by its ``estimated`` pose onto the same anchors carried by its
    ``true`` pose. Uses poses only, never the fused or the true surface."""
    return metrics.gauge_alignment(list(estimated), list(true), [anchors(v) for v in vertices])


def submap_gauge(submaps: Sequence[LoadedSubmap], poses: dict[str, Pose], true: dict[str, Pose]) -> Gauge:
    """``gauge_fit`` over ``submaps`` as the fusion posed them: the refined pose from ``poses``, else the
    GPS pose they were held at."""
    return gauge_fit([poses.get(s.input.id, s.pose_gps) for s in submaps], [true[s.input.id] for s in submaps],
                     [s.input.mesh.vertices for s in submaps])


def pose_figures(submaps: Sequence[LoadedSubmap], poses: dict[str, Pose], true: dict[str, Pose]) -> dict[str, Any]:
    """Pose RMSE (``pose_trans_m`` m, ``pose_rot_deg`` deg) of those ``submaps`` that have a pose in
    ``poses``, against their ``true`` poses after rigid alignment; ``poses``: how many; ``pose_session_m``
    the translation RMSE per session; ``pose_surface_m`` the RMS offset of the submaps' surfaces (their
    anchors) after the anchor gauge. Empty if none."""
    used = [s for s in submaps if s.input.id in poses]
    if not used:
        return {}
    est, tru = [poses[s.input.id] for s in used], [true[s.input.id] for s in used]
    t, r = metrics.pose_rmse(est, tru)
    # per session, the same translation RMSE (one alignment for all); and how far each submap's surface sits
    # off the truth (RMS over its anchors after the anchor gauge): what the geometric scores feel, free of
    # where a submap's local origin lies (a rotation error moves a far origin more than the surface)
    g_r, g_t = metrics.gauge_alignment(est, tru)
    err = np.array([g_r @ e.t + g_t - g.t for e, g in zip(est, tru, strict=True)])
    sessions = np.array([s.input.session_id for s in used])
    per_session = {str(k): float(np.sqrt(np.mean(np.sum(err[sessions == k] ** 2, axis=1)))) for k in np.unique(sessions)}
    anchor = [anchors(s.input.mesh.vertices) for s in used]
    a_r, a_t = metrics.gauge_alignment(est, tru, anchor)
    surface = [np.mean(np.sum((e.apply(a) @ a_r.T + a_t - g.apply(a)) ** 2, axis=1))
               for e, g, a in zip(est, tru, anchor, strict=True)]
    return {"pose_trans_m": t, "pose_rot_deg": r, "poses": len(used), "pose_session_m": per_session,
            "pose_surface_m": float(np.sqrt(np.mean(surface))),
            "pose_relative_m": relative_offset(used, est, tru, (g_r, g_t))}


RELATIVE_NEAR_M = 20.0  # submaps whose true centroids lie this close count as neighbours (a submap is ~25 m long)


def relative_offset(used: Sequence[LoadedSubmap], est: Sequence[Pose], true: Sequence[Pose], gauge: Gauge,
                    near_m: float = RELATIVE_NEAR_M) -> float | None:
    """RMS over neighbouring submaps of *different* sessions (true centroids within ``near_m``) of the
    difference of their centroids' offsets from the truth after ``gauge``, metres; None without such a
    pair. What two sessions meeting at one place disagree by, free of the map's common low-frequency
    warp: pose RMSE after a rigid gauge also counts how the joint map bends as a whole (each session's
    chain between the places other sessions pin it, held by its own submaps' overlaps and its odometry)."""
    g_r, g_t = gauge
    cent = [s.input.mesh.vertices.mean(0)[None] for s in used]
    at_true = np.array([g.apply(c)[0] for g, c in zip(true, cent, strict=True)])
    err = np.array([g_r @ e.apply(c)[0] + g_t for e, c in zip(est, cent, strict=True)]) - at_true
    session = np.array([s.input.session_id for s in used])
    i, j = np.array(sorted(cKDTree(at_true[:, :2]).query_pairs(near_m)), dtype=np.int64).reshape(-1, 2).T
    other = session[i] != session[j]
    if not other.any():
        return None
    return float(np.sqrt(np.mean(np.sum((err[i[other]] - err[j[other]]) ** 2, axis=1))))


def gauge_size(gauge: Gauge, region: metrics.Region) -> dict[str, float]:
    """Size of a gauge: ``gauge_m`` how far it moves the region's centre (z = 0), metres; ``gauge_deg``
    its rotation angle, degrees."""
    r, t = gauge
    (x0, y0), (x1, y1) = region
    centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
    return {"gauge_m": float(np.linalg.norm(r @ centre + t - centre)), "gauge_deg": float(rotation_angle_deg(r))}


def score_mesh(truth: TruthPoints, mesh: FusedMesh, gauge: Gauge | None = None) -> dict[str, Any]:
    """Geometric P/R/F, mean semantic F (per class too, by label name) at d, surviving transient share
    (None without transient truth) and face count of ``mesh`` in ``truth.region``, after moving it by
    ``gauge`` if given (its surface is sampled with seed 1)."""
    pred = metrics.sample_surface(mesh.vertices, mesh.faces, mesh.face_labels, seed=1)
    if gauge is not None:
        pred = metrics.transform_points(pred, *gauge)
    pred = metrics.crop(pred, truth.region)
    p, r, f = metrics.geometric_prf(pred, truth.gt_all, D, truth.region, truth.gt_observed)
    sem, per_class = metrics.semantic_f1(pred, truth.gt_all, D, truth.region, truth.gt_observed)
    survive = _survival(pred, truth.transient)
    contested = None if truth.contested is None else _survival(pred, truth.contested)
    return {"geo_p": p, "geo_r": r, "geo_f": f, "sem_f": sem, "transient_survival": survive,
            "contested_survival": contested, "contested_points": None if truth.contested is None else len(truth.contested),
            "per_class_f": {LABELS[k].name: v[2] for k, v in per_class.items()}, "faces": int(len(mesh.faces))}


def _survival(pred: metrics.PointSet, transient: metrics.PointSet) -> float | None:
    """Share of ``transient`` points with a predicted surface point within d (None: no transient points;
    0 if nothing is predicted)."""
    if not len(transient):
        return None
    if not len(pred):
        return 0.0
    dist, _ = cKDTree(pred.points).query(transient.points, distance_upper_bound=D)
    return float(np.mean(dist <= D))


def score_aligned_and_absolute(truth: TruthPoints, mesh: FusedMesh, gauge: Gauge | None,
                               centre_region: metrics.Region | None = None) -> dict[str, Any]:
    """``score_mesh`` gauge-aligned (plain keys), in the absolute map frame (``abs_`` keys of
    ``ABS_KEYS``) and the gauge's size at the centre of ``centre_region`` (default ``truth.region``).
    ``gauge`` None: the mesh is already in the true gauge (e.g. fused at the true poses), so the
    absolute figures are the aligned ones and the size is zero."""
    aligned = score_mesh(truth, mesh, gauge)
    absolute = score_mesh(truth, mesh) if gauge is not None else aligned
    centre = centre_region or truth.region
    if centre is None:
        raise ValueError("the gauge's size needs a region (its centre)")
    size = gauge_size(gauge, centre) if gauge is not None else {"gauge_m": 0.0, "gauge_deg": 0.0}
    return aligned | {f"abs_{k}": absolute[k] for k in ABS_KEYS} | size
