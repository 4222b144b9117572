"""Fine registration of every submap before the field alignment: joint multi-view point-to-plane ICP.

Why: the field alignment moves a pose only through the field's SDF at the submap's samples, so it needs
the field to hold one surface where two sessions disagree. On submaps of one forward camera (90° × 50°
field of view, 20 m range: strips of road ahead with facades seen obliquely) it did not: on the 3×3
camera bench (seed 0, 5 sessions) the alignment took the poses from 0.89 m (odometry chains on GPS) to
only 0.63 m, and the share of uploaded surface within 0.2 m of the truth stayed at 0.5 (0.83 at the true
poses). With every camera error switched off but the field of view the same held (0.60 m); with a 170°
field of view, same fleet and noise, it reached 0.29 m. A point-to-plane registration pulls each
surface sample onto the nearest compatible surface of another submap directly, whatever the field has
learned, so it does not depend on the field first merging two surfaces into one.

What: every free submap one rigid pose (the centroid-relative ``PoseSet`` of the field alignment), composed
with one rigid correction per session (about its centroid): odometry holds a session's submaps together
within cm, so a whole session moves along a badly conditioned direction of the submap corrections alone
(L-BFGS left a session shifted 1 m where it was); its own variable moves it freely. Surface
samples per submap (area-weighted, vertical faces ``fine_vertical_weight`` × more likely: they fix the
horizontal position, the road only height and tilt; spread over the directions the vertical faces face,
``fine_normal_balance``, so the few surfaces facing along a street hold a share of the data term). Rounds of

1. correspondences: each sample's nearest sample of a submap of *another session* within the round's
   radius whose normal agrees (``fine_normal_dot``); the radius shrinks geometrically from ``fine_max_dist_m``
   (or ``fine_basin_sigmas`` × the GPS σ where wider: ``match_radii``) to
   ``fine_min_dist_m`` over the rounds;
2. L-BFGS on  Σ_submaps ``fine_weight`` · mean ρ(r / σ)  +  odometry  +  GPS prior,  with r the
   point-to-plane residual along the pair's mean normal, σ half the round's radius and ρ(u) = log(1 + u²)
   (Cauchy: a match to a parked car another session did not see, or to a monocular depth blob, pulls
   with a bounded force). Odometry and GPS are the field alignment's terms (``fusion.losses``), summed in
   σ units, so a session's chain bends only where the data outweigh its odometry.

Each submap's data count as ``fine_weight`` observations whatever its sample count: thousands of
correlated matches are not thousands of independent ones, and the odometry must keep its say along a
straight road, where point-to-plane matches leave the direction of travel open.

Frames: poses and samples in the region frame of ``fusion.align`` (metres). Torch for the objective (CPU
or GPU), SciPy k-d trees for the correspondences; no Open3D.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from fusion.config import FusionConfig
from fusion.losses import gps_prior_loss, odometry_loss
from fusion.poses import PoseSet
from fusion.sampling import face_geometry, on_triangles, transform, uniform_barycentric
from fusion.training import PoseTerms
from fusion.types import SubmapInput

UPRIGHT_NZ = 0.7  # a face whose local normal is within ~45° of +z is ground-like (fixes height and tilt only)


@dataclass
class FineResult:
    """``poses``: the registered poses (4, 4) per submap (region frame); ``metrics``: per round the match
    count and median |residual| (m), and the RMS movement of the free submaps' centroids (m)."""

    poses: list[np.ndarray]
    metrics: dict[str, object] = field(default_factory=dict)


AZIMUTH_BINS = 6  # non-ground normals binned by horizontal direction, modulo 180° (30° bins)
AZIMUTH_MAX_GAIN = 8.0  # a rare direction's faces are drawn at most this × more often than their area says


def surface_samples(sm: SubmapInput, count: int, vertical_weight: float, rng: np.random.Generator,
                    normal_balance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points (local frame) and their face normals on ``sm``'s mesh, drawn by face area, faces
    that are not ground-like ``vertical_weight`` × more likely.

    ``normal_balance`` (0: off, 1: full) spreads the non-ground samples over the horizontal directions
    their normals face (normal-space sampling, Rusinkiewicz & Levoy 2001): a face's weight is multiplied by
    (mean direction-bin area / its bin's area) ** ``normal_balance``, at most ``AZIMUTH_MAX_GAIN``, and the
    non-ground total is kept. Along a street the facades, kerbs and fences face across the road and
    point-to-plane matches on them leave the direction of travel open; what fixes it (pole sides, sign
    plates, building corners, cross streets) is a few % of the area, so without this it held a few % of
    each submap's data term."""
    area, normal = face_geometry(sm.mesh.vertices, sm.mesh.faces)
    upright = np.abs(normal[:, 2]) >= UPRIGHT_NZ
    weight = area * np.where(upright, 1.0, vertical_weight)
    side = ~upright & (area > 0)
    if normal_balance > 0 and side.any():
        azimuth = np.mod(np.arctan2(normal[side, 1], normal[side, 0]), np.pi)
        bins = np.minimum((azimuth / np.pi * AZIMUTH_BINS).astype(int), AZIMUTH_BINS - 1)
        bin_area = np.bincount(bins, weights=area[side], minlength=AZIMUTH_BINS)
        mean = bin_area[bin_area > 0].mean()
        gain = np.minimum((mean / bin_area[bins]) ** normal_balance, AZIMUTH_MAX_GAIN)
        balanced = weight[side] * gain
        weight[side] = balanced * (weight[side].sum() / balanced.sum())
    if weight.sum() <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    face = rng.choice(len(area), size=count, p=weight / weight.sum())
    u, v = uniform_barycentric(count, rng)
    return on_triangles(sm.mesh.vertices[sm.mesh.faces[face]], u, v), normal[face]


def match_radii(config: FusionConfig, gps_sigma_m: float) -> np.ndarray:
    """The rounds' match radii (m): from ``fine_max_dist_m``, or ``fine_basin_sigmas`` × the submaps' GPS σ
    (``gps_sigma_m``, their median) where that is wider, shrinking geometrically to ``fine_min_dist_m``.

    Why σ: a session's odometry chain placed on its GPS fixes starts about σ from the others (σ 4 m:
    1.3-3 m per session on the bench), and a match is found only within the radius; from 2 m the widest
    round left exact sessions 1-1.4 m off (3×3 bench, σ 4 m, seeds 0-2: 0.72 / 1.02 / 0.84 m before the
    field) where 5 m brought them to 0.24 / 0.22 / 0.29 m. A wider start keeps the default schedule's
    shrink per round (``fine_rounds`` rounds over the default range), so it adds rounds instead of
    coarsening each step."""
    lo, hi = config.fine_min_dist_m, config.fine_max_dist_m
    if config.fine_rounds <= 1 or hi <= lo:
        return np.geomspace(hi, lo, max(1, config.fine_rounds))
    start = max(hi, config.fine_basin_sigmas * gps_sigma_m)
    per_round = math.log(hi / lo) / (config.fine_rounds - 1)
    rounds = max(config.fine_rounds, 1 + math.ceil(math.log(start / lo) / per_round - 1e-9))
    return np.geomspace(start, lo, rounds)


def fine_register(subs: list[SubmapInput], start: list[np.ndarray], gps: torch.Tensor, config: FusionConfig,
                  device: torch.device | None = None) -> FineResult:
    """Register the free submaps of ``subs`` (start poses ``start``, GPS anchors ``gps`` (M, 4, 4), one
    frame for all) jointly onto each other. Submaps that overlap no other keep their odometry/GPS
    balance; fixed submaps (``free`` False) hold."""
    dev = device or torch.device("cpu")
    rng = np.random.default_rng(config.seed)
    local, normals, owner = [], [], []
    for k, sm in enumerate(subs):
        p, n = surface_samples(sm, config.fine_samples, config.fine_vertical_weight, rng, config.fine_normal_balance)
        local.append(p)
        normals.append(n)
        owner.append(np.full(len(p), k))
    pts, nrm, own = np.concatenate(local), np.concatenate(normals), np.concatenate(owner)
    cents = [s.mesh.vertices.mean(0) for s in subs]
    centroids = np.stack([m[:3, :3] @ c + m[:3, 3] for m, c in zip(start, cents, strict=True)])
    poses = PoseSet(torch.tensor(np.stack(start)), torch.tensor(centroids), torch.tensor([s.free for s in subs])).to(dev)
    # one more rigid correction per session, about its centroid (why: the module docstring, "What")
    label = {sid: k for k, sid in enumerate(sorted({s.session_id for s in subs}))}
    of = np.array([label[s.session_id] for s in subs])
    rigid = [of == k for k in range(len(label))]
    whole = PoseSet(torch.eye(4, dtype=torch.float64).repeat(len(label), 1, 1),
                    torch.tensor(np.stack([centroids[m].mean(0) for m in rigid])),
                    torch.tensor([all(s.free for s, inside in zip(subs, m, strict=True) if inside) for m in rigid])).to(dev)
    of_t = torch.tensor(of, device=dev)
    # samples match only other sessions' unless fine_same_session: a session's consecutive submaps overlap
    # and agree wherever the session is, so their samples were often the nearest and diluted the matches
    # that move it; within a session odometry rules
    group = np.arange(len(subs)) if config.fine_same_session else of

    def posed_now() -> torch.Tensor:
        return whole()[of_t] @ poses()

    if len(pts) == 0 or not any(s.free for s in subs) or config.fine_rounds <= 0:
        return FineResult([m.copy() for m in start], {"rounds": []})
    terms = PoseTerms.of(subs, dev)
    n_pairs, n_subs = len(terms.pairs), len(subs)
    pts_t = torch.tensor(pts, device=dev)
    nrm_t = torch.tensor(nrm, device=dev)
    own_t = torch.tensor(own, device=dev)
    radii = match_radii(config, float(np.median([s.gps_sigma.trans_m for s in subs if s.free])))
    rounds = []
    for radius in radii:
        with torch.no_grad():
            current = posed_now()
            posed = transform(current, own_t, pts_t).cpu().numpy()
            posed_n = (current[own_t][:, :3, :3] @ nrm_t[:, :, None])[:, :, 0].cpu().numpy()
        src, dst = _correspondences(posed, posed_n, own, float(radius), config.fine_normal_dot, group)
        if len(src) == 0:
            rounds.append({"radius_m": float(radius), "matches": 0})
            continue
        mean_n = posed_n[src] + posed_n[dst]
        mean_n /= np.linalg.norm(mean_n, axis=1, keepdims=True)
        counts = np.bincount(own[src], minlength=n_subs)
        w = torch.tensor(config.fine_weight / counts[own[src]], device=dev)  # each submap: fine_weight observations
        s_idx, d_idx = torch.tensor(src, device=dev), torch.tensor(dst, device=dev)
        n_pair = torch.tensor(mean_n, device=dev)
        sigma = radius / 2

        def residual(t: torch.Tensor, s_idx: torch.Tensor = s_idx, d_idx: torch.Tensor = d_idx,
                     n_pair: torch.Tensor = n_pair) -> torch.Tensor:
            """Point-to-plane residual (m) of every match at poses ``t``."""
            a = transform(t, own_t[s_idx], pts_t[s_idx])
            return ((a - transform(t, own_t[d_idx], pts_t[d_idx])) * n_pair).sum(-1)

        def objective(residual: Callable[[torch.Tensor], torch.Tensor] = residual, w: torch.Tensor = w,
                      sigma: float = sigma) -> torch.Tensor:
            t = posed_now()
            r = residual(t) / sigma
            data = (w * torch.log1p(r * r)).sum()
            odo = odometry_loss(t, terms.pairs, terms.odom_rel, terms.odom_ist, terms.odom_isr) * n_pairs
            prior = gps_prior_loss(t, gps, terms.gps_ist, terms.gps_isr) * n_subs
            return data + odo + prior

        _minimise([poses.rho, poses.phi, whole.rho, whole.phi], objective, config.fine_steps)
        with torch.no_grad():
            res = residual(posed_now())
        rounds.append({"radius_m": float(radius), "matches": int(len(src)),
                       "median_residual_m": float(res.abs().median())})
    with torch.no_grad():
        final = posed_now().cpu().numpy()
    moved = np.stack([m[:3, :3] @ c + m[:3, 3] for m, c in zip(final, cents, strict=True)]) - centroids
    free = np.array([s.free for s in subs])
    rms = float(np.sqrt((moved[free] ** 2).sum(1).mean())) if free.any() else 0.0
    return FineResult(list(final), {"rounds": rounds, "moved_rms_m": rms})


def _correspondences(posed: np.ndarray, normals: np.ndarray, owner: np.ndarray, radius: float, min_dot: float,
                     group: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(source, target) sample indices: each sample's nearest sample of another submap within ``radius``
    whose normal agrees with its own (dot ≥ ``min_dot``; none: unmatched), never of a submap in the same
    ``group`` (per submap index; default: each its own, i.e. only the own submap). One k-d tree per submap, each
    sample queried against the submaps whose boxes (grown by ``radius``) overlap its own: linear in the
    overlaps, not quadratic in the region's submaps; a single tree over all samples would let a submap's
    own samples, denser nearby, hide the others'."""
    k = 4
    ids = np.unique(owner)
    members = {i: np.flatnonzero(owner == i) for i in ids}
    trees = {i: cKDTree(posed[m]) for i, m in members.items()}
    lo = {i: posed[m].min(0) - radius for i, m in members.items()}
    hi = {i: posed[m].max(0) + radius for i, m in members.items()}
    src, dst = [], []
    for i in ids:
        mine = members[i]
        best_d = np.full(len(mine), np.inf)
        best_j = np.full(len(mine), -1)
        for j in ids:
            if j == i or (group is not None and group[j] == group[i]) or np.any(lo[j] > hi[i]) or np.any(hi[j] < lo[i]):
                continue
            dist, idx = trees[j].query(posed[mine], k=k, distance_upper_bound=radius)
            valid = np.isfinite(dist)
            cand = members[j][np.where(valid, idx, 0)]
            valid &= np.einsum("nkd,nd->nk", normals[cand], normals[mine]) >= min_dot
            d = np.where(valid, dist, np.inf)
            first = np.argmin(d, axis=1)
            d_first = d[np.arange(len(mine)), first]
            better = d_first < best_d
            best_d[better] = d_first[better]
            best_j[better] = cand[better, first[better]]
        has = best_j >= 0
        src.append(mine[has])
        dst.append(best_j[has])
    if not src:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(src), np.concatenate(dst)


def _minimise(params: list[torch.nn.Parameter], objective: Callable[[], torch.Tensor], steps: int) -> None:
    """L-BFGS (strong Wolfe line search) on the pose corrections ``params`` for ``steps`` iterations."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    opt.step(closure)
