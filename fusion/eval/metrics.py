"""Evaluation metrics of the paper (torch-free): reconstruction precision/recall/F-score at a distance
threshold (Knapitsch et al. 2017), mean per-class semantic F-score, and pose RMSE after rigid
(Umeyama) alignment of the whole trajectory. All coordinates in the map frame, metres.

Surfaces are compared as point sets sampled uniformly by area (``sample_surface``). Precision: the
share of predicted points with a ground-truth point within ``d``; recall: the share of ground-truth
points with a predicted point within ``d``. Recall may use a subset of the ground truth (the part any
vehicle observed), precision the whole ground truth, so neither unobserved truth nor correct
reconstructions of it are counted against the prediction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fusion.placement import umeyama
from fusion.types import FusedMesh, Pose, SemanticMesh, rotation_angle_deg

DEFAULT_D = 0.2  # metres (paper: d = 20 cm)
DEFAULT_DENSITY = 100.0  # points per m² (10 cm spacing, well below d)


@dataclass
class PointSet:
    """Points (n, 3) (map frame, metres) with a label id each (0 = unlabeled)."""

    points: np.ndarray
    labels: np.ndarray

    def subset(self, mask: np.ndarray) -> PointSet:
        return PointSet(self.points[mask], self.labels[mask])

    def __len__(self) -> int:
        return len(self.points)


Region = tuple[tuple[float, float], tuple[float, float]]  # ((xmin, ymin), (xmax, ymax)) map frame, metres


def sample_surface(vertices: np.ndarray, faces: np.ndarray, face_labels: np.ndarray | None = None,
                   density: float = DEFAULT_DENSITY, seed: int = 0, face_mask: np.ndarray | None = None) -> PointSet:
    """Points uniformly on a triangle mesh by area (``density`` per m²), labelled by their face."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    lab = np.zeros(len(f), np.int64) if face_labels is None else np.asarray(face_labels, np.int64)
    if face_mask is not None:
        f, lab = f[face_mask], lab[face_mask]
    if len(f) == 0:
        return PointSet(np.zeros((0, 3)), np.zeros(0, np.int64))
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    n = max(int(round(area.sum() * density)), 1)
    idx = rng.choice(len(f), size=n, p=area / area.sum()) if area.sum() > 0 else rng.integers(len(f), size=n)
    u, w = rng.random(n), rng.random(n)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    t = tri[idx]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])
    return PointSet(pts, lab[idx])


def as_points(x: FusedMesh | SemanticMesh | PointSet | np.ndarray, density: float = DEFAULT_DENSITY,
              seed: int = 0) -> PointSet:
    """A point set from a mesh (sampled by area), a ``PointSet``, or bare points (n, 3) (label 0)."""
    if isinstance(x, PointSet):
        return x
    if isinstance(x, FusedMesh | SemanticMesh):
        return sample_surface(x.vertices, x.faces, x.face_labels, density, seed)
    pts = np.asarray(x, np.float64).reshape(-1, 3)
    return PointSet(pts, np.zeros(len(pts), np.int64))


def crop(ps: PointSet, region: Region | None) -> PointSet:
    """Points whose x/y lie in ``region`` (all heights)."""
    if region is None:
        return ps
    (x0, y0), (x1, y1) = region
    p = ps.points
    return ps.subset((p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1))


def _share_within(query: np.ndarray, reference: np.ndarray, d: float) -> float:
    if len(query) == 0:
        return 0.0
    if len(reference) == 0:
        return 0.0
    dist, _ = cKDTree(reference).query(query, distance_upper_bound=d, workers=-1)
    return float(np.mean(dist <= d))


def _f(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


def geometric_prf(pred: FusedMesh | PointSet | np.ndarray, gt: FusedMesh | SemanticMesh | PointSet | np.ndarray,
                  d: float = DEFAULT_D, region: Region | None = None,
                  gt_observed: PointSet | None = None) -> tuple[float, float, float]:
    """(precision, recall, F) at distance ``d`` metres, both sets cropped to ``region``.

    ``gt_observed``: the ground truth recall is measured on (default: ``gt``)."""
    p, g = crop(as_points(pred, seed=1), region), crop(as_points(gt, seed=2), region)
    g_rec = g if gt_observed is None else crop(gt_observed, region)
    precision = _share_within(p.points, g.points, d)
    recall = _share_within(g_rec.points, p.points, d)
    return precision, recall, _f(precision, recall)


def semantic_f1(pred: FusedMesh | PointSet, gt: FusedMesh | SemanticMesh | PointSet, d: float = DEFAULT_D,
                region: Region | None = None, gt_observed: PointSet | None = None,
                classes: list[int] | None = None) -> tuple[float, dict[int, tuple[float, float, float]]]:
    """Mean per-class F-score: for class k, precision is the share of points predicted as k that have
    a ground-truth point of class k within ``d``; recall the share of (observed) ground-truth points
    of class k with a point predicted as k within ``d``. Averaged over ``classes`` (default: every
    class present in the observed ground truth; label 0 excluded). Returns (mean F, {k: (P, R, F)})."""
    p, g = crop(as_points(pred, seed=1), region), crop(as_points(gt, seed=2), region)
    g_rec = g if gt_observed is None else crop(gt_observed, region)
    if classes is None:
        classes = sorted(int(k) for k in np.unique(g_rec.labels) if k != 0)
    per_class = {}
    for k in classes:
        pk, gk, rk = p.points[p.labels == k], g.points[g.labels == k], g_rec.points[g_rec.labels == k]
        prec, rec = _share_within(pk, gk, d), _share_within(rk, pk, d)
        per_class[k] = (prec, rec, _f(prec, rec))
    mean = float(np.mean([v[2] for v in per_class.values()])) if per_class else 0.0
    return mean, per_class


def gauge_alignment(estimated: list[Pose], truth: list[Pose],
                    anchors: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rigid transform ``(R, t)`` (map frame) taking the estimated map's gauge to the truth's: the
    least-squares (Umeyama) fit of points carried by the estimated poses onto the same points carried
    by the true poses. ``anchors``: per pose, local points (k, 3) it carries (default: its origin, i.e.
    the pose positions, as ``pose_rmse`` aligns). Points spread over each submap (e.g. a sample of its
    vertices) also fix the rotation about a straight trajectory, which positions alone leave
    ill-conditioned. Identity when fewer than 3 points. Uses poses only, never the reconstruction."""
    if len(estimated) != len(truth) or not estimated:
        raise ValueError("gauge_alignment needs two equally long, non-empty pose lists")
    if anchors is None:
        src = np.array([p.t for p in estimated], np.float64)
        dst = np.array([p.t for p in truth], np.float64)
    else:
        src = np.concatenate([e.apply(np.asarray(a, np.float64)) for e, a in zip(estimated, anchors, strict=True)])
        dst = np.concatenate([g.apply(np.asarray(a, np.float64)) for g, a in zip(truth, anchors, strict=True)])
    if len(src) < 3:
        return np.eye(3), np.zeros(3)
    r, t, _ = umeyama(src, dst)
    return r, t


def transform_points(ps: PointSet, rotation: np.ndarray, translation: np.ndarray) -> PointSet:
    """``ps`` moved by ``x ↦ R x + t`` (labels kept)."""
    return PointSet(ps.points @ np.asarray(rotation).T + np.asarray(translation), ps.labels)


def pose_rmse(estimated: list[Pose], truth: list[Pose], align: bool = True) -> tuple[float, float]:
    """(translation RMSE m, rotation RMSE deg) of estimated vs true local → map poses, after the rigid
    transform that best aligns the estimated positions to the true ones (if ``align``)."""
    if len(estimated) != len(truth) or not estimated:
        raise ValueError("pose_rmse needs two equally long, non-empty pose lists")
    te = np.array([p.t for p in estimated])
    tt = np.array([p.t for p in truth])
    r, t = gauge_alignment(estimated, truth) if align else (np.eye(3), np.zeros(3))
    te_al = te @ r.T + t
    trans = float(np.sqrt(np.mean(np.sum((te_al - tt) ** 2, axis=1))))
    re = np.array([r @ p.rotation() for p in estimated])
    rt = np.array([p.rotation() for p in truth])
    rot = float(np.sqrt(np.mean(rotation_angle_deg(np.transpose(rt, (0, 2, 1)) @ re) ** 2)))
    return trans, rot
