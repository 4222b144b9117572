"""A monocular camera's submaps: what one front camera maps, and the errors of a camera pipeline.

The fleets this service is for carry one forward-looking camera; their submaps come from a semantic
occupancy network or a lightweight monocular mesher. Compared with an exact crop of the world, such a
submap

- covers only what the camera saw: a forward field of view and a range limit (``hfov_deg``,
  ``vfov_deg``, ``range_m``; the visibility test of ``fusion.eval.synth.visibility``);
- has depth errors that grow with range and are smooth in patches, along the viewing ray
  (``depth_*``), plus a little white noise (voxel quantisation, ``white_noise_m``);
- is mis-scaled and slowly bent as a whole, about its origin (monocular scale drift and heading /
  pitch drift inside the local map: ``scale_sigma``, ``bend_*``);
- carries a segmenter's labels: bleeding across class borders (``bleed_*``), confusion between
  neighbouring classes (``confusion``), thin things (lane markings, poles, signs) often missed
  (``thin_miss``);
- has holes (``hole_*``).

Each error is drawn per submap from the submap's own generator. "Patchy" errors are the excursion
sets of smooth random fields (``random_field``): an error of rate ``p`` covers the patches where a
unit Gaussian field lies below its ``p`` quantile, so it hits about a share ``p`` of the surface, in
blobs about as large as the field's correlation length. Labels are decided on the true surface (the
segmenter sees the image, not the reconstructed depth); geometry is degraded afterwards.

Frames and units: everything here is in the submap's local frame (origin at the vehicle pose where
the submap starts, x forward, z up), metres and degrees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import ndtri

from fusion.eval.synth import shapes
from fusion.eval.synth.visibility import in_frustum
from fusion.labels import LABEL_BY_NAME
from fusion.overrides import with_overrides
from fusion.types import Pose, SemanticMesh

FEATURES = 32  # random Fourier features per field: enough for a near-Gaussian marginal
SYSTEMATIC_STREAM = 0x5E6  # seeds the world-fixed part of the segmenter's errors


@dataclass
class CameraSensor:
    """The camera sensor model's parameters (metres, degrees; rates are shares of surface area).

    Defaults are calibrated so that a five-session fleet's submaps, concatenated at their true poses,
    score geo F ≈ 0.85–0.92 and sem F ≈ 0.45–0.60 at d = 0.2 m (README, "Sensor models"), the regime
    of the monocular submaps in the paper. See each field for its physical basis.
    """

    # -- what one front camera maps ---------------------------------------------------------
    hfov_deg: float = 90.0  # horizontal field of view (full angle): a typical automotive front camera
    vfov_deg: float = 50.0  # vertical field of view (full angle) about the vehicle's forward axis: at 1.6 m
    # height the ground is seen from 3.4 m ahead, a wall 10 m away up to 6 m
    range_m: float = 20.0  # farthest surface mapped: monocular depth beyond it is too poor to keep

    # -- depth: smooth, range-dependent error along the viewing ray ---------------------------
    depth_sigma_10m: float = 0.15  # σ of the depth error at 10 m range (1.5 %, after fusing a submap's frames)
    depth_exponent: float = 1.0  # σ(ρ) = depth_sigma_10m · (ρ / 10 m)^exponent: 1, a constant relative error
    # (learned monocular depth, its scale held by the known camera height); 2 would be triangulation from motion
    depth_corr_m: float = 4.0  # correlation length of the depth-error field: networks are wrong in patches
    depth_systematic: float = 0.0  # share of the depth-error field fixed to the place (misjudged alike every pass)
    white_noise_m: float = 0.02  # independent per-vertex noise (0.2 m voxels / mesh quantisation)

    # -- monocular drift inside the local map, about the submap origin ------------------------
    scale_sigma: float = 0.01  # σ of the per-submap scale error (1 %: scale held by the known camera height)
    bend_yaw_deg_per_m: float = 0.015  # σ of the heading drift rate κ: a point x metres ahead moves κ x² / 2
    # sideways (0.21 m at 40 m), a visual odometry's slow yaw drift inside the local map
    bend_pitch_deg_per_m: float = 0.02  # σ of the pitch drift rate: the map curls up or down ahead (0.28 m at
    # 40 m); pitch is the worse-observed angle of a forward camera

    # -- the segmenter ------------------------------------------------------------------------
    label_corr_m: float = 1.5  # size of the segmenter's error patches (correlation length)
    label_systematic: float = 0.7  # share of the segmenter's errors fixed to the place (its appearance fools
    # every pass the same way); the rest is each submap's own, so concatenating passes votes only that part out
    bleed_width_m: float = 0.7  # labels bleed up to this far across a class border (2D boundary error of a
    # few pixels, 0.2 m voxels, depth smeared across object edges) ...
    bleed_prob: float = 0.7  # ... in this share of the border (patches along it)
    # (true class, labelled as, rate): the segmenter labels ``rate`` of the true class's surface as the other,
    # between classes that look alike and meet. Directed, and mostly from the smaller class into the larger:
    # a sidewalk is often taken for road, a road rarely for sidewalk (a large class mislabelled into a small
    # one at any rate would swamp it, and no trained segmenter does that).
    confusion: tuple[tuple[str, str, float], ...] = (
        ("road", "sidewalk", 0.03), ("sidewalk", "road", 0.15),
        ("sidewalk", "terrain", 0.10), ("terrain", "sidewalk", 0.03),
        ("terrain", "vegetation", 0.05), ("vegetation", "terrain", 0.20),
        ("fence", "building", 0.10), ("fence", "vegetation", 0.10),
        ("obstacle", "vehicle", 0.05), ("traffic_sign", "pole", 0.25),
    )
    # (thin class, miss rate): missed surface takes the class around it (markings: road); a 0.2 m marking
    # or a 0.1–0.25 m pole is one voxel or less wide, and faded or far markings vanish in the image
    thin_miss: tuple[tuple[str, float], ...] = (("lane_marking", 0.6), ("pole", 0.6), ("traffic_sign", 0.6))
    thin_corr_m: float = 1.5  # size of the missed stretches (correlation length)

    # -- holes ----------------------------------------------------------------------------------
    hole_rate: float = 0.05  # share of the seen surface missing (texture-less, over-exposed, filtered)
    hole_size_m: float = 1.5  # correlation length of the hole field: holes are blobs about this size


SENSORS = ("camera", "exact")


def sensor_model(name: str, overrides: Sequence[str] = ()) -> CameraSensor | None:
    """The sensor model called ``name``: ``camera`` (the defaults above, with ``KEY=VALUE`` ``overrides`` of
    its fields: ``--camera``) or ``exact`` (None: exact crops of the world with the fleet's white vertex and
    label noise, ``FleetParams``; no overrides). Raises ``ValueError`` on an unknown name or override."""
    if name == "camera":
        return with_overrides(CameraSensor(), list(overrides))
    if name == "exact":
        if overrides:
            raise ValueError("camera overrides need the camera sensor (--sensor camera)")
        return None
    raise ValueError(f"unknown sensor {name!r} (known: {', '.join(SENSORS)})")


def random_field(points: np.ndarray, length_m: float, rng: np.random.Generator, features: int = FEATURES,
                 ) -> np.ndarray:
    """A smooth random field at ``points`` (n, 3), metres: zero mean, unit variance, correlation
    exp(−r² / 2ℓ²) with ℓ = ``length_m`` (random Fourier features, Rahimi & Recht 2007)."""
    omega = rng.normal(size=(features, 3)) / length_m
    phase = rng.uniform(0.0, 2 * np.pi, features)
    # float32 halves the cost of the cosines; phases of a few hundred radians keep ~1e-5 rad precision
    arg = np.asarray(points, np.float32) @ omega.T.astype(np.float32) + phase.astype(np.float32)
    return np.sqrt(2.0 / features) * np.cos(arg).sum(axis=1, dtype=np.float64)


def patches(points: np.ndarray, rate: float, length_m: float, rng: np.random.Generator) -> np.ndarray:
    """Mask of ``points`` inside random patches covering about a share ``rate`` of space, in blobs of
    about ``length_m``: where a ``random_field`` lies below its Gaussian ``rate`` quantile. Always draws
    the field (a rate of 0 or a few points do not shift the generator's later draws)."""
    g = random_field(points, length_m, rng)
    return g < ndtri(min(rate, 1.0)) if rate > 0.0 else np.zeros(len(points), bool)


@dataclass
class Place:
    """Where a submap lies in the world, for the errors a camera pipeline repeats on every pass over the
    same place (its appearance fools it the same way): ``to_map`` the submap's true pose (local → map),
    ``seed`` the world's."""

    to_map: Pose
    seed: int


def mixed_field(points: np.ndarray, length_m: float, rng: np.random.Generator, place: Place | None, share: float,
                key: tuple[int, ...]) -> np.ndarray:
    """A unit ``random_field`` at ``points`` (n, 3) (the submap's true local frame): this submap's own part
    (``rng``) mixed with, given a ``place``, a part fixed to the world (drawn from its seed and ``key`` at the
    points' map-frame positions, the same for every submap) holding a share ``share`` of the variance."""
    g = random_field(points, length_m, rng)
    if place is None or share <= 0.0:
        return g
    shared = random_field(place.to_map.apply(points), length_m, np.random.default_rng([place.seed, SYSTEMATIC_STREAM,
                                                                                       *key]))
    return np.sqrt(1.0 - share) * g + np.sqrt(share) * shared


# -- geometry ---------------------------------------------------------------------------------------
def observing_camera(vertices: np.ndarray, cameras: np.ndarray, rotations: np.ndarray, cam: CameraSensor,
                     ) -> np.ndarray:
    """Index of the camera position each vertex is mapped from: the nearest one that has it in view and
    range (else the nearest one). ``cameras`` (k, 3), ``rotations`` (k, 3, 3) camera → local frame."""
    dist = np.linalg.norm(vertices[None] - cameras[:, None], axis=2)  # (k, n)
    in_view = np.stack([in_frustum((vertices - c) @ r, cam.hfov_deg, cam.vfov_deg) for c, r in zip(cameras, rotations,
                                                                                                 strict=True)])
    in_view &= dist <= cam.range_m
    best = np.argmin(np.where(in_view, dist, np.inf), axis=0)
    none = ~in_view.any(axis=0)
    best[none] = np.argmin(dist[:, none], axis=0)
    return best


def depth_error(vertices: np.ndarray, cameras: np.ndarray, rotations: np.ndarray, cam: CameraSensor,
                rng: np.random.Generator, place: Place | None = None) -> np.ndarray:
    """``vertices`` moved along their viewing rays by σ(ρ) · g(x): σ grows with the range ρ from the
    observing camera (``depth_sigma_10m``, ``depth_exponent``), g is a smooth unit field
    (``depth_corr_m``; given a ``place``, a share ``depth_systematic`` of it fixed to the world). Local
    frame, metres."""
    origin = cameras[observing_camera(vertices, cameras, rotations, cam)]
    ray = vertices - origin
    rho = np.maximum(np.linalg.norm(ray, axis=1), 1e-6)
    sigma = cam.depth_sigma_10m * (rho / 10.0) ** cam.depth_exponent
    g = mixed_field(vertices, cam.depth_corr_m, rng, place, cam.depth_systematic, (0,))
    return vertices + (sigma * g / rho)[:, None] * ray


def drift(vertices: np.ndarray, cam: CameraSensor, rng: np.random.Generator) -> np.ndarray:
    """The local map's monocular drift about its origin: one scale factor 1 + N(0, ``scale_sigma``) and a
    bend, a heading (pitch) error growing linearly with the distance x ahead, θ(x) = κ x, which moves a
    point ≈ κ x² / 2 sideways (up); κ ~ N(0, ``bend_*_deg_per_m``)."""
    scale = 1.0 + rng.normal() * cam.scale_sigma
    k_yaw, k_pitch = np.radians(rng.normal(size=2) * [cam.bend_yaw_deg_per_m, cam.bend_pitch_deg_per_m])
    x, y, z = vertices.T
    yaw, pitch = k_yaw * x / 2, k_pitch * x / 2  # rotating by half the heading error integrates θ(x)
    x1, y1 = np.cos(yaw) * x - np.sin(yaw) * y, np.sin(yaw) * x + np.cos(yaw) * y
    x2, z2 = np.cos(pitch) * x1 - np.sin(pitch) * z, np.sin(pitch) * x1 + np.cos(pitch) * z
    return scale * np.column_stack([x2, y1, z2])


# -- the segmenter --------------------------------------------------------------------------------
def _label_id(name: str) -> int:
    return LABEL_BY_NAME[name].id


def error_patches(centroids: np.ndarray, idx: np.ndarray, rate: float, length_m: float, cam: CameraSensor,
                  rng: np.random.Generator, place: Place | None, key: tuple[int, ...]) -> np.ndarray:
    """Mask over the faces ``idx``: inside the segmenter's error patches covering about a share ``rate``, in
    blobs of about ``length_m``. The field mixes this submap's own part (``rng``) and, given a ``place``, a
    part fixed to the world (a share ``label_systematic`` of its variance, drawn from the world's seed and
    the error's ``key``); the mix keeps unit variance, so ``rate`` holds either way."""
    g = mixed_field(centroids[idx], length_m, rng, place, cam.label_systematic, key)
    return g < ndtri(min(rate, 1.0)) if rate > 0.0 else np.zeros(len(idx), bool)


def nearest_other_class(centroids: np.ndarray, labels: np.ndarray, within_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For each face (centroid), the nearest face of another class within ``within_m``: its label and
    distance (inf and the face's own label where none is that close)."""
    best_d = np.full(len(labels), np.inf)
    best_l = labels.copy()
    for k in np.unique(labels):
        mine = labels == k
        others = np.flatnonzero(~mine)
        if len(others) == 0:
            continue
        d, _ = cKDTree(centroids[mine]).query(centroids[others], distance_upper_bound=within_m)
        closer = d < best_d[others]
        best_d[others[closer]] = d[closer]
        best_l[others[closer]] = k
    return best_l, best_d


def bleed(centroids: np.ndarray, labels: np.ndarray, cam: CameraSensor, rng: np.random.Generator,
          place: Place | None = None) -> np.ndarray:
    """Labels bled across class borders: a face within ``bleed_width_m`` of another class takes that class
    in patches covering ``bleed_prob`` of the border."""
    near, dist = nearest_other_class(centroids, labels, cam.bleed_width_m)
    border = np.flatnonzero(dist <= cam.bleed_width_m)
    take = border[error_patches(centroids, border, cam.bleed_prob, cam.label_corr_m, cam, rng, place, (1,))]
    out = labels.copy()
    out[take] = near[take]
    return out


def confuse(centroids: np.ndarray, labels: np.ndarray, cam: CameraSensor, rng: np.random.Generator,
            place: Place | None = None) -> np.ndarray:
    """Classes confused (``confusion``): for each (true class, labelled as, rate), that class is labelled as
    the other in patches covering ``rate`` of its surface. Other classes are left alone."""
    out = labels.copy()
    for i, (true, wrong, rate) in enumerate(cam.confusion):
        faces = np.flatnonzero(labels == _label_id(true))
        out[faces[error_patches(centroids, faces, rate, cam.label_corr_m, cam, rng, place, (2, i))]] = _label_id(wrong)
    return out


def miss_thin(centroids: np.ndarray, labels: np.ndarray, cam: CameraSensor, rng: np.random.Generator,
              place: Place | None = None) -> np.ndarray:
    """Thin classes missed (``thin_miss``): in patches covering each thin class's miss rate, its faces take
    the label of the nearest face of a class that is not thin (under a marking: the road)."""
    thin = np.array([_label_id(name) for name, _ in cam.thin_miss], np.int64)
    around = ~np.isin(labels, thin)
    out = labels.copy()
    if not around.any():
        return out
    missed = [np.zeros(0, np.int64)]
    for i, (name, rate) in enumerate(cam.thin_miss):
        faces = np.flatnonzero(labels == _label_id(name))
        missed.append(faces[error_patches(centroids, faces, rate, cam.thin_corr_m, cam, rng, place, (3, i))])
    lost = np.concatenate(missed)
    if len(lost):  # the tree of the other classes only when something was missed
        out[lost] = labels[around][cKDTree(centroids[around]).query(centroids[lost])[1]]
    return out


def segment(centroids: np.ndarray, labels: np.ndarray, cam: CameraSensor, rng: np.random.Generator,
            place: Place | None = None) -> np.ndarray:
    """The segmenter's face labels from the true ones: bleed, then confusion, then thin misses."""
    labels = bleed(centroids, labels, cam, rng, place)
    return miss_thin(centroids, confuse(centroids, labels, cam, rng, place), cam, rng, place)


# -- the whole pipeline ------------------------------------------------------------------------------
def degrade(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, cameras: np.ndarray, rotations: np.ndarray,
            cam: CameraSensor, rng: np.random.Generator, place: Place | None = None) -> SemanticMesh:
    """The submap a camera pipeline makes of the true surface it saw: ``vertices`` (n, 3) and ``faces``
    (m, 3) in the submap's local frame with true face ``labels``; ``cameras`` (k, 3) the camera positions
    and ``rotations`` (k, 3, 3) their orientations (camera → local: forward, left, up); ``place`` where the
    submap lies in the world (without it every error is this submap's own). Labels from the
    segmenter, vertices moved by depth error, noise and drift, holes cut (unused vertices dropped)."""
    centroids = vertices[faces].mean(axis=1)
    out_labels = segment(centroids, np.asarray(labels, np.int64), cam, rng, place)
    v = depth_error(vertices, cameras, rotations, cam, rng, place)
    v = v + rng.normal(scale=cam.white_noise_m, size=v.shape)
    v = drift(v, cam, rng)
    keep = ~patches(centroids, cam.hole_rate, cam.hole_size_m, rng)
    v, f = shapes.compact(v, faces[keep])
    return SemanticMesh(v, f, out_labels[keep])
