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

What: every free submap one rigid pose, corrected about its centroid. The L-BFGS solver composes it with
one rigid correction per session (about its centroid): odometry holds a session's submaps together
within cm, so a whole session moves along a badly conditioned direction of the submap corrections alone
(L-BFGS left a session shifted 1 m where it was); its own variable moves it freely. The Gauss-Newton
solver needs no such help: it solves every direction of the normal equations at once. Surface
samples per submap (area-weighted, vertical faces ``fine_vertical_weight`` × more likely: they fix the
horizontal position, the road only height and tilt; spread over the directions the vertical faces face,
``fine_normal_balance``, so the few surfaces facing along a street hold a share of the data term). Rounds of

1. correspondences: each sample's nearest sample of a submap of *another session* within the round's
   radius whose normal agrees (``fine_normal_dot``); the radius shrinks geometrically from ``fine_max_dist_m``
   (or ``fine_basin_sigmas`` × the GPS σ where wider: ``fusion.match_weights.match_radii``) to
   ``fine_min_dist_m`` over the rounds, but not narrower than the surfaces disagree between sessions
   (``fusion.match_weights.spread_floor``: a monocular camera's walls disagree by decimetres, and rounds
   narrower than that keep only the patches that happen to agree and fit each submap to them);
2. minimise  Σ_submaps ``fine_weight`` · mean ρ(r / σ)  +  odometry  +  GPS prior,  with r the
   point-to-plane residual along the pair's mean normal, σ half the round's radius and ρ(u) = log(1 + u²)
   (Cauchy: a match to a parked car another session did not see, or to a monocular depth blob, pulls
   with a bounded force). Odometry and GPS are the field alignment's terms (``fusion.losses``), summed in
   σ units, so a session's chain bends only where the data outweigh its odometry. The solver
   (``fine_solver``): Levenberg-Marquardt on the reweighted normal equations (``gn``, the default), or
   L-BFGS (``lbfgs``, which needs the per-session correction above to move a session at all).

Each submap's data count as ``fine_weight`` observations whatever its sample count: thousands of
correlated matches are not thousands of independent ones, and the odometry must keep its say along a
straight road, where point-to-plane matches leave the direction of travel open.

Frames: poses and samples in the region frame of ``fusion.align`` (metres). Torch for the objective (CPU
or GPU), SciPy k-d trees for the correspondences; no Open3D.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from fusion import drift, se3
from fusion.config import FusionConfig
from fusion.drift_fit import Matches, corrected_samples, drift_step, fit_prior, prior_sigmas
from fusion.losses import gps_prior_loss, odometry_loss, pose_residual
from fusion.match_weights import data_gains, match_radii, own_gains, spread_floor, wall_spread
from fusion.matching import HeldPairs, correspondences
from fusion.poses import PoseSet
from fusion.sampling import face_geometry, on_triangles, transform, uniform_barycentric
from fusion.training import PoseTerms
from fusion.types import SubmapInput

UPRIGHT_NZ = 0.7  # a face whose local normal is within ~45° of +z is ground-like (fixes height and tilt only)


@dataclass
class FineResult:
    """``poses``: the registered poses (4, 4) per submap (region frame), of the submaps corrected by
    ``drifts`` (``fusion.drift``; identity unless ``fine_drift``); ``metrics``: per round the match count and
    median |residual| (m), and the RMS movement of the free submaps' centroids (m)."""

    poses: list[np.ndarray]
    metrics: dict[str, object] = field(default_factory=dict)
    drifts: list[drift.Drift] = field(default_factory=list)


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


def fine_register(subs: list[SubmapInput], start: list[np.ndarray], gps: torch.Tensor, config: FusionConfig,
                  device: torch.device | None = None, radii: np.ndarray | None = None) -> FineResult:
    """Register the free submaps of ``subs`` (start poses ``start``, GPS anchors ``gps`` (M, 4, 4), one
    frame for all) jointly onto each other. Submaps that overlap no other keep their odometry/GPS
    balance; fixed submaps (``free`` False) hold. ``radii``: the rounds' match radii (default
    ``match_radii``), each raised to ``spread_floor`` of the previous round's residuals; the first round
    so raised is the last."""
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
    label = {sid: k for k, sid in enumerate(sorted({s.session_id for s in subs}))}
    of = np.array([label[s.session_id] for s in subs])
    # samples match only other sessions' unless fine_same_session: a session's consecutive submaps overlap
    # and agree wherever the session is, so their samples were often the nearest and diluted the matches
    # that move it; within a session odometry rules
    group = np.arange(len(subs)) if config.fine_same_session and config.fine_same_session_ground else of
    # fine_same_session without the ground: upright samples may match their own session's other submaps
    within = (np.abs(nrm[:, 2]) < UPRIGHT_NZ) if config.fine_same_session and not config.fine_same_session_ground \
        else None
    gauss_newton = config.fine_solver == "gn"
    if not gauss_newton:  # the L-BFGS path's parameters: a pose per submap, one more rigid one per session
        poses = PoseSet(torch.tensor(np.stack(start)), torch.tensor(centroids),
                        torch.tensor([s.free for s in subs])).to(dev)
        # one more rigid correction per session, about its centroid (why: the module docstring, "What")
        rigid = [of == k for k in range(len(label))]
        whole = PoseSet(torch.eye(4, dtype=torch.float64).repeat(len(label), 1, 1),
                        torch.tensor(np.stack([centroids[m].mean(0) for m in rigid])),
                        torch.tensor([all(s.free for s, inside in zip(subs, m, strict=True) if inside)
                                      for m in rigid])).to(dev)
        of_t = torch.tensor(of, device=dev)

    def posed_now() -> torch.Tensor:
        return whole()[of_t] @ poses()

    if len(pts) == 0 or not any(s.free for s in subs) or config.fine_rounds <= 0:
        return FineResult([m.copy() for m in start], {"rounds": []})
    terms = PoseTerms.of(subs, dev)
    n_pairs, n_subs = len(terms.pairs), len(subs)
    pts_t = torch.tensor(pts, device=dev)
    nrm_t = torch.tensor(nrm, device=dev)
    own_t = torch.tensor(own, device=dev)
    if radii is None:
        radii = match_radii(config, float(np.median([s.gps_sigma.trans_m for s in subs if s.free])))
    current = torch.tensor(np.stack(start), device=dev)  # the Gauss-Newton path's poses (region frame)
    correct = gauss_newton and config.fine_drift  # each free submap's drift (fusion.drift) with its pose
    axes = np.array([drift.ahead_axis(s.mesh.vertices) for s in subs])
    bends = np.zeros((n_subs, drift.PARAMS))
    ceiling = prior_sigmas(config)  # the drift priors: the configured σ, or (fine_drift_prior_fit) the fleet's own
    sigma_p = ceiling
    local_cents = torch.tensor(np.stack(cents), device=dev)
    # how far a submap's farthest vertex lies from its centroid (m): a twist (t, ω) about the centroid moves
    # no point of it farther than |t| + |ω| × this
    reach = torch.tensor([float(np.linalg.norm(s.mesh.vertices - c, axis=1).max(initial=0.0))
                          for s, c in zip(subs, cents, strict=True)], device=dev)
    free_t = torch.tensor([s.free for s in subs], device=dev)
    colour = torch.tensor(_chain_colours(subs), device=dev)
    rounds: list[dict[str, float | None]] = []
    held = HeldPairs(~free_t.cpu().numpy())  # held submaps never move here: their mutual queries once
    spread: float | None = None  # the latest round's wall spread (spread_floor)
    for scheduled in radii:
        radius = max(float(scheduled), spread_floor(config, spread)) if scheduled <= config.fine_max_dist_m \
            else float(scheduled)
        last = radius > scheduled  # the surfaces disagree this much: no narrower round
        with torch.no_grad():
            now = current if gauss_newton else posed_now()
            posed = transform(now, own_t, pts_t).cpu().numpy()
            posed_n = (now[own_t][:, :3, :3] @ nrm_t[:, :, None])[:, :, 0].cpu().numpy()
        src, dst = correspondences(posed, posed_n, own, float(radius), config.fine_normal_dot, group, within,
                                    held=held)
        n_other = len(src)
        if config.fine_own_overlap:  # the own session's other submaps, as data of their own (weights below)
            s_own, d_own = correspondences(posed, posed_n, own, float(radius), config.fine_normal_dot, of, same=True,
                                            held=held)
            src, dst = np.concatenate([src, s_own]), np.concatenate([dst, d_own])
        if len(src) == 0:
            rounds.append({"radius_m": float(radius), "matches": 0})
            if last:
                break
            continue
        mean_n = posed_n[src] + posed_n[dst]
        mean_n /= np.linalg.norm(mean_n, axis=1, keepdims=True)
        s_idx, d_idx = torch.tensor(src, device=dev), torch.tensor(dst, device=dev)
        n_pair = torch.tensor(mean_n, device=dev)
        sigma = radius / 2
        # each submap: fine_weight observations (× gain: in units of the data's own noise, ground and other
        # surfaces each by their own spread)
        # (rounds wider than fine_max_dist_m, the basin's extension for a wide GPS σ, keep the base weight:
        # their residuals are still the misalignment, and weighted up the wrong walls matched there won)
        r0 = ((posed[src] - posed[dst]) * mean_n).sum(-1)
        ground = np.abs(mean_n[:, 2]) >= UPRIGHT_NZ
        basin = radius > config.fine_max_dist_m
        w_np = np.zeros(len(src))
        gain = 1.0
        for is_own in (False, True):
            part = (np.arange(len(src)) >= n_other) == is_own
            if not part.any():
                continue
            if is_own:  # own-session overlaps: per session, by their spread, as far as the session fits rigidly
                gains = own_gains(r0, ground, part, of[own[src]], sigma, config, basin)
            else:
                gains = data_gains(r0, ground, part, sigma, config, basin)
                gain = float(gains.mean())
            counts = np.bincount(own[src[part]], minlength=n_subs)
            w_np[part] = config.fine_weight * gains / counts[own[src[part]]]
        w = torch.tensor(w_np, device=dev)

        def residual(t: torch.Tensor, s_idx: torch.Tensor = s_idx, d_idx: torch.Tensor = d_idx,
                     n_pair: torch.Tensor = n_pair, pts_t: torch.Tensor = pts_t) -> torch.Tensor:
            """Point-to-plane residual (m) of every match at poses ``t``."""
            a = transform(t, own_t[s_idx], pts_t[s_idx])
            return ((a - transform(t, own_t[d_idx], pts_t[d_idx])) * n_pair).sum(-1)

        if gauss_newton:
            match = Matches(own_t[s_idx], own_t[d_idx], pts_t[s_idx], pts_t[d_idx], n_pair, w, sigma)
            current, steps = _gauss_newton(current, match, terms, gps, local_cents, free_t, colour, config.fine_steps,
                                           reach, config.fine_converged_m)
            # the drift given the poses, then the poses given the drift, on the same matches; not in the basin's
            # extra rounds (wider than fine_max_dist_m), whose matches still include the wrong walls
            if correct and not basin:
                bends, variance = drift_step(current, match, (src, dst), bends, pts, axes, local_cents, free_t, sigma_p)
                if config.fine_drift_prior_fit:  # the next round's priors: the fleet's own (one EM update)
                    sigma_p = fit_prior(bends, variance, ceiling, config.fine_drift_prior_min_submaps)
                pts_t = torch.tensor(corrected_samples(pts, own, bends, axes), device=dev)
                match = Matches(own_t[s_idx], own_t[d_idx], pts_t[s_idx], pts_t[d_idx], n_pair, w, sigma)
                current, more = _gauss_newton(current, match, terms, gps, local_cents, free_t, colour,
                                              config.fine_steps, reach, config.fine_converged_m)
                steps += more
            with torch.no_grad():
                res = match.residual(current)
            solver: dict[str, float | None] = {"steps": steps, "gain": gain}
        else:
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
            solver = {}
        spread = None if basin else wall_spread(res.cpu().numpy()[:n_other], ground[:n_other])
        rounds.append({"radius_m": float(radius), "matches": int(len(src)), **solver,
                       "median_residual_m": float(res.abs().median()), "wall_spread_m": spread})
        if last:
            break
    with torch.no_grad():
        final = (current if gauss_newton else posed_now()).cpu().numpy()
    moved = np.stack([m[:3, :3] @ c + m[:3, 3] for m, c in zip(final, cents, strict=True)]) - centroids
    free = np.array([s.free for s in subs])
    rms = float(np.sqrt((moved[free] ** 2).sum(1).mean())) if free.any() else 0.0
    drifts = [drift.Drift(axis=(float(a[0]), float(a[1]))).with_params(b) for a, b in zip(axes, bends, strict=True)]
    metrics = {"rounds": rounds, "moved_rms_m": rms}
    if correct:
        metrics["drift_rms"] = {"scale": float(np.sqrt(np.mean(np.expm1(bends[free, 0]) ** 2))) if free.any() else 0.0,
                                "bend_deg_per_m": float(np.degrees(np.sqrt(np.mean(bends[free, 1:] ** 2))))
                                if free.any() else 0.0,
                                "prior_sigma": [float(np.expm1(sigma_p[0])), *np.degrees(sigma_p[1:]).tolist()]}
    return FineResult(list(final), metrics, drifts)


def _chain_colours(subs: list[SubmapInput]) -> list[int]:
    """0/1 alternating along each session's chain (by seq): an odometry pair always joins one of each, so
    perturbing every submap of one colour at once gives each pair's derivative for its submap of that colour."""
    colour = [0] * len(subs)
    by_session: dict[str, list[int]] = {}
    for k, s in enumerate(subs):
        by_session.setdefault(s.session_id, []).append(k)
    for members in by_session.values():
        for rank, k in enumerate(sorted(members, key=lambda k: subs[k].seq)):
            colour[k] = rank % 2
    return colour


def _perturb(poses: torch.Tensor, centroids: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """``C ∘ exp(δ) ∘ C⁻¹ ∘ P`` per submap: a twist ``δ`` (M, 6) applied about each submap's centroid."""
    c = torch.eye(4, dtype=poses.dtype, device=poses.device).repeat(len(poses), 1, 1)
    c[:, :3, 3] = centroids
    return c @ se3.se3_exp(delta) @ se3.inverse(c) @ poses


def _prior_residuals(poses: torch.Tensor, terms: PoseTerms, gps: torch.Tensor) -> torch.Tensor:
    """Odometry (E, 6) then GPS (M, 6) residuals in σ units: their squares sum to the L-BFGS objective's
    odometry and GPS terms."""
    parts = []
    if len(terms.pairs):
        rel = se3.inverse(poses[terms.pairs[:, 1]]) @ poses[terms.pairs[:, 0]]
        dt, dr = pose_residual(rel, terms.odom_rel)
        parts.append(torch.cat([dt * terms.odom_ist[:, None], dr * terms.odom_isr[:, None]], -1))
    dt, dr = pose_residual(poses, gps)
    parts.append(torch.cat([dt * terms.gps_ist[:, None], dr * terms.gps_isr[:, None]], -1))
    return torch.cat(parts)


FD_STEP = 1e-6  # central-difference step of the odometry/GPS Jacobian (m, rad)


@dataclass
class _PriorJacobian:
    """The odometry/GPS Jacobian, block-sparse: residual block ``r`` (6 rows of ``_prior_residuals``)
    depends on submaps ``owners[r, 0]`` and ``owners[r, 1]`` through the 6×6 blocks ``blocks[r, 0]`` and
    ``blocks[r, 1]`` (a GPS block: one submap, its second block zero)."""

    owners: torch.Tensor  # (R, 2)
    blocks: torch.Tensor  # (R, 2, 6, 6)

    def dense(self, m: int) -> torch.Tensor:
        """The (R·6, M·6) matrix (tests, small regions)."""
        rows = len(self.owners)
        out = torch.zeros(rows, 6, m, 6, dtype=self.blocks.dtype, device=self.blocks.device)
        for slot in (0, 1):
            out[torch.arange(rows), :, self.owners[:, slot], :] += self.blocks[:, slot]
        return out.reshape(rows * 6, m * 6)


def _prior_jacobian(poses: torch.Tensor, centroids: torch.Tensor, terms: PoseTerms, gps: torch.Tensor,
                    colour: torch.Tensor) -> _PriorJacobian:
    """Jacobian of ``_prior_residuals`` w.r.t. each submap's twist about its centroid, by central
    differences: 2 colours × 6 directions × 2 evaluations whatever the region's size (an odometry block
    depends on one submap of each colour, a GPS block on its own submap). Block slot = colour."""
    m = len(poses)
    pairs = terms.pairs
    n_odo = len(pairs)
    rows = n_odo + m
    own = torch.arange(m, device=poses.device)
    owners = torch.empty(rows, 2, dtype=torch.long, device=poses.device)
    blocks = torch.zeros(rows, 2, 6, 6, dtype=poses.dtype, device=poses.device)
    for c in (0, 1):
        mine = colour == c
        owners[:n_odo, c] = torch.where(mine[pairs[:, 0]], pairs[:, 0], pairs[:, 1]) if n_odo else pairs[:, 0]
        owners[n_odo:, c] = own
        keep = torch.cat([torch.ones(n_odo, dtype=torch.bool, device=poses.device), mine])
        for k in range(6):
            delta = torch.zeros(m, 6, dtype=poses.dtype, device=poses.device)
            delta[mine, k] = FD_STEP
            plus = _prior_residuals(_perturb(poses, centroids, delta), terms, gps)
            minus = _prior_residuals(_perturb(poses, centroids, -delta), terms, gps)
            blocks[keep, c, :, k] = ((plus - minus) / (2 * FD_STEP))[keep]  # (rows, 6)
    return _PriorJacobian(owners, blocks)


def _normal_equations(m: int, keys: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
                      free_dofs: np.ndarray) -> scipy.sparse.csc_matrix:
    """The (free) normal matrix from its 6×6 blocks: ``keys`` lists (row submap, column submap, blocks
    (n, 6, 6)); blocks at the same place add. Only the submap pairs that share a match or an odometry
    link hold a block: memory and the sparse solve grow with the region's overlaps, not with M²."""
    rows = torch.cat([a for a, _, _ in keys])
    cols = torch.cat([b for _, b, _ in keys])
    vals = torch.cat([v for _, _, v in keys])
    place, inverse = torch.unique(rows * m + cols, return_inverse=True)
    summed = torch.zeros(len(place), 6, 6, dtype=vals.dtype, device=vals.device).index_add_(0, inverse, vals)
    i = np.arange(6)
    br, bc = (place // m).cpu().numpy(), (place % m).cpu().numpy()
    r = (br[:, None, None] * 6 + i[None, :, None]).repeat(6, 2)
    c = (bc[:, None, None] * 6 + i[None, None, :]).repeat(6, 1)
    full = scipy.sparse.csc_matrix((summed.cpu().numpy().ravel(), (r.ravel(), c.ravel())), shape=(6 * m, 6 * m))
    return full[free_dofs][:, free_dofs].tocsc()


def _linearise(poses: torch.Tensor, match: Matches, terms: PoseTerms, gps: torch.Tensor, local_cents: torch.Tensor,
               colour: torch.Tensor, free_dofs: np.ndarray) -> tuple[scipy.sparse.csc_matrix, np.ndarray, torch.Tensor]:
    """The IRLS normal equations at ``poses`` over the twists ``free_dofs`` (indices into M·6): the
    sparse matrix JᵀWJ, the gradient JᵀWr (both of the data, odometry and GPS terms) and the submaps'
    centroids the twists turn about (region frame)."""
    m = len(poses)
    sigma2 = match.sigma ** 2
    cents = (poses[:, :3, :3] @ local_cents[:, :, None])[:, :, 0] + poses[:, :3, 3]
    q_s = transform(poses, match.src, match.p_src)
    q_d = transform(poses, match.dst, match.p_dst)
    r = ((q_s - q_d) * match.normal).sum(-1)
    weight = match.w / (sigma2 + r * r)  # IRLS: the Cauchy loss's curvature at the current residual
    # a match's Jacobian: j_s = [n, x_s] for its source's twist, j_d = -[n, x_d] for its target's
    v = torch.cat([match.normal, torch.linalg.cross(q_s - cents[match.src], match.normal),
                   torch.linalg.cross(q_d - cents[match.dst], match.normal)], -1)  # [n, x_s, x_d]
    at_s, at_d = [0, 1, 2, 3, 4, 5], [0, 1, 2, 6, 7, 8]
    j_s, j_d = v[:, at_s], -v[:, at_d]
    jp = _prior_jacobian(poses, cents, terms, gps, colour)
    rp = _prior_residuals(poses, terms, gps)  # (R, 6)
    # the matches' four blocks j_aᵀ w j_b, summed per (source, target) submap pair first (few pairs, many
    # matches), all four read off one 9×9 sum of w v vᵀ per pair (the same products, signs exact): 81
    # products a match instead of 144
    pair, inverse = torch.unique(match.src * m + match.dst, return_inverse=True)
    outer = torch.zeros(len(pair), 9, 9, dtype=poses.dtype, device=poses.device).index_add_(
        0, inverse, weight[:, None, None] * v[:, :, None] * v[:, None, :])
    ends = ((pair // m, at_s, 1.0), (pair % m, at_d, -1.0))
    keys = [(a, b, outer[:, ia][:, :, ib] * (sa * sb)) for a, ia, sa in ends for b, ib, sb in ends]
    keys += [(jp.owners[:, s], jp.owners[:, t], jp.blocks[:, s].transpose(1, 2) @ jp.blocks[:, t])
             for s in (0, 1) for t in (0, 1)]
    h = _normal_equations(m, keys, free_dofs)
    grad = torch.zeros(m, 6, dtype=poses.dtype, device=poses.device)
    grad.index_add_(0, match.src, (weight * r)[:, None] * j_s)
    grad.index_add_(0, match.dst, (weight * r)[:, None] * j_d)
    for s in (0, 1):
        grad.index_add_(0, jp.owners[:, s], (jp.blocks[:, s].transpose(1, 2) @ rp[:, :, None])[:, :, 0])
    g = grad.reshape(-1).cpu().numpy()[free_dofs]
    return h, g, cents


def _gauss_newton(poses: torch.Tensor, match: Matches, terms: PoseTerms, gps: torch.Tensor,
                  local_cents: torch.Tensor, free: torch.Tensor, colour: torch.Tensor, steps: int,
                  reach: torch.Tensor | None = None, converged_m: float = 0.0) -> tuple[torch.Tensor, int]:
    """Minimise  Σ w·log(1 + (r/σ)²)  +  odometry  +  GPS  over the free submaps' poses by
    Levenberg-Marquardt on the iteratively reweighted (Cauchy) normal equations, at most ``steps``
    accepted steps, until the objective stops falling (by 1e-9 of itself) or, with ``reach`` (per submap,
    its vertices' farthest distance from its centroid) and ``converged_m`` > 0, a step moved no point of
    any submap farther than ``converged_m``. Returns the poses and the steps taken.

    Why not L-BFGS: the data term holds neighbouring submaps within cm while the map's large-scale shape
    (how a session's chain bends between the places other sessions pin it) is held only by odometry
    and GPS, orders of magnitude softer; a first-order method crawls along those directions (150 L-BFGS
    steps per round left the exact 3×3 map 0.17 m off, 600 steps 0.08 m). The normal equations solve
    every direction in one step. They are block-sparse (a 6×6 block per pair of submaps that overlap or
    follow each other) and solved sparse (SuperLU): a region of thousands of submaps costs what its
    overlaps cost."""
    m = len(poses)
    free_dofs = np.flatnonzero(free.repeat_interleave(6).cpu().numpy())
    sigma2 = match.sigma ** 2

    def objective(p: torch.Tensor) -> torch.Tensor:
        r = match.residual(p)
        return (match.w * torch.log1p(r * r / sigma2)).sum() + (_prior_residuals(p, terms, gps) ** 2).sum()

    # a match between two held submaps adds nothing to the free twists' equations (its blocks and gradient
    # rows are the held submaps', dropped): linearised without them (an addition: most of a round's matches)
    moving = free[match.src] | free[match.dst]
    linear = match if bool(moving.all()) else Matches(
        match.src[moving], match.dst[moving], match.p_src[moving], match.p_dst[moving], match.normal[moving],
        match.w[moving], match.sigma)
    damping = 1e-4
    value = objective(poses)
    taken = 0
    for _ in range(steps):
        h, g, cents = _linearise(poses, linear, terms, gps, local_cents, colour, free_dofs)
        diag = scipy.sparse.diags(np.maximum(h.diagonal(), 1e-12))
        improved = False
        for _ in range(10):
            step = scipy.sparse.linalg.spsolve((h + damping * diag).tocsc(), -g)
            delta = np.zeros(m * 6)
            delta[free_dofs] = step
            trial = _perturb(poses, cents, torch.tensor(delta.reshape(m, 6), dtype=poses.dtype, device=poses.device))
            new = objective(trial)
            if new < value:
                improved = True
                break
            damping *= 10
        if not improved:
            break
        poses, taken = trial, taken + 1
        converged = float(value - new) <= 1e-9 * float(value)
        if reach is not None and converged_m > 0:
            twist = torch.tensor(delta.reshape(m, 6), dtype=poses.dtype, device=poses.device)
            moved = twist[:, :3].norm(dim=1) + twist[:, 3:].norm(dim=1) * reach
            converged |= float(moved.max()) < converged_m
        value = new
        damping = max(damping / 10, 1e-7)
        if converged:
            break
    return poses, taken


def _minimise(params: list[torch.nn.Parameter], objective: Callable[[], torch.Tensor], steps: int) -> None:
    """L-BFGS (strong Wolfe line search) on the pose corrections ``params`` for ``steps`` iterations."""
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = objective()
        loss.backward()
        return loss

    opt.step(closure)
