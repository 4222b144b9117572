"""The drift estimate inside the fine registration (``fusion.register``, ``fine_drift``): each free submap's
monocular scale and bend (``fusion.drift``) solved on a round's matches, and the samples corrected by it.

Frames: samples in each submap's local frame (as uploaded, or corrected); poses and matches in the region frame
of ``fusion.align`` (metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from fusion import drift
from fusion.config import FusionConfig
from fusion.sampling import transform


@dataclass
class Matches:
    """One round of ``fusion.register``'s correspondences: owners (submap index), local points (as corrected)
    and the pair's normal (region frame), each submap's per-match weight ``w`` and the Cauchy scale ``sigma`` (m).
    Here, not in ``fusion.register``, so the drift solve needs no import back."""

    src: torch.Tensor
    dst: torch.Tensor
    p_src: torch.Tensor
    p_dst: torch.Tensor
    normal: torch.Tensor
    w: torch.Tensor
    sigma: float

    def residual(self, poses: torch.Tensor) -> torch.Tensor:
        """Point-to-plane residuals (m) at ``poses``."""
        return ((transform(poses, self.src, self.p_src) - transform(poses, self.dst, self.p_dst)) * self.normal).sum(-1)


def corrected_samples(raw: np.ndarray, owner: np.ndarray, bends: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """The samples ``raw`` (local frames, as uploaded) under their submap's drift correction (same order)."""
    out = raw.copy()
    for k in np.unique(owner):
        sel = owner == k
        out[sel] = drift.deform(raw[sel], bends[k], axes[k])
    return out


def prior_sigmas(config: FusionConfig) -> np.ndarray:
    """The drift priors' σ from the config: (log scale, yaw bend rad/m, pitch bend rad/m)."""
    return np.array([config.fine_drift_scale_sigma, *[math.radians(config.fine_drift_bend_deg_per_m)] * 2])


def drift_step(poses: torch.Tensor, match: Matches, samples: tuple[np.ndarray, np.ndarray], bends: np.ndarray,
               raw: np.ndarray, axes: np.ndarray, local_cents: torch.Tensor, free: torch.Tensor,
               sigma_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Gauss-Newton step of every free submap's drift parameters (``fusion.drift``; (M, 3)) on the round's
    matches, the other submaps held where they are.

    Each submap's step solves its drift jointly with a rigid correction of its own (9 unknowns, the IRLS
    weights of the matches at the current residuals) and keeps the drift part: the drift that fits best
    whatever rigid move goes with it, so a residual a rigid move explains (an offset the odometry holds
    against) is not read as scale. The priors ``sigma_p`` (log scale, yaw and pitch bend rates: the config's
    ``prior_sigmas`` or the fleet's own, ``fit_prior``) hold what the matches leave open; a step is kept within
    3 σ of them. Returns the new drift parameters (M, 3) and their posterior variances (M, 3; NaN for the
    submaps without a step), for ``fit_prior``.

    ``raw``: every sample (local frame, as uploaded), ``samples`` the matches' source and target rows of it
    (``match.p_src`` / ``p_dst`` are their corrected copies); normals are held (the bend turns them by tenths
    of a degree)."""
    m = len(poses)
    with torch.no_grad():
        cents = ((poses[:, :3, :3] @ local_cents[:, :, None])[:, :, 0] + poses[:, :3, 3]).cpu().numpy()
        q_s = transform(poses, match.src, match.p_src).cpu().numpy()
        q_d = transform(poses, match.dst, match.p_dst).cpu().numpy()
    normal = match.normal.cpu().numpy()
    r = ((q_s - q_d) * normal).sum(-1)
    weight = match.w.cpu().numpy() / (match.sigma ** 2 + r * r)
    rot = poses[:, :3, :3].cpu().numpy()
    src, dst = match.src.cpu().numpy(), match.dst.cpu().numpy()
    h = np.zeros((m, 9, 9))
    g = np.zeros((m, 9))
    for sign, who, q, idx in ((1.0, src, q_s, samples[0]), (-1.0, dst, q_d, samples[1])):
        jac = np.empty((len(who), 9))
        jac[:, :3] = normal
        jac[:, 3:6] = np.cross(q - cents[who], normal)
        for k in np.unique(who):
            sel = who == k
            dd = drift.jacobian(raw[idx[sel]], bends[k], axes[k])  # (n, 3, 3) local
            jac[sel, 6:] = np.einsum("ni,ij,njk->nk", normal[sel], rot[k], dd)
        jac *= sign
        np.add.at(h, who, weight[:, None, None] * jac[:, :, None] * jac[:, None, :])
        np.add.at(g, who, (weight * r)[:, None] * jac)
    out, variance = bends.copy(), np.full(bends.shape, np.nan)
    for k in np.flatnonzero(free.cpu().numpy()):
        if not h[k].any():
            continue
        hk, gk = h[k].copy(), g[k].copy()
        hk[6:, 6:] += np.diag(1.0 / sigma_p ** 2)
        gk[6:] += bends[k] / sigma_p ** 2
        hk += np.eye(9) * 1e-9 * max(np.trace(hk), 1.0)
        out[k] = np.clip(bends[k] + np.linalg.solve(hk, -gk)[6:], -3 * sigma_p, 3 * sigma_p)
        variance[k] = np.diag(np.linalg.inv(hk))[6:]
    return out, variance


def fit_prior(bends: np.ndarray, variance: np.ndarray, ceiling: np.ndarray, min_submaps: int) -> np.ndarray:
    """The drift priors' σ from the fleet itself (empirical Bayes): one EM update of a zero-mean Gaussian
    prior's variance per parameter from a drift step's posteriors (``drift_step``), τ² = mean over the submaps
    with a step of (posterior mean² + posterior variance), at most the configured ``ceiling`` σ; the ceiling
    where fewer than ``min_submaps`` submaps had a step.

    Why: one prior cannot serve every fleet. Wide enough for a monocular camera's drift (~1 % scale,
    ~0.02°/m), it lets an exact mapper's submaps take 0.1-0.2 % of scale from noise and correlated residuals,
    and their poses suffer (docs/METHOD_LOG.md, "A submap's monocular drift"). Pooled over the fleet, per
    parameter (the fleet's sensor is what its submaps share): a fleet whose submaps carry no drift gives
    estimates within their own uncertainty and each update shrinks τ (the estimates with it); a fleet whose
    submaps drift keeps τ near their spread. One update per registration round (eight in all), not run to
    convergence: with each submap's matches counted as ``fine_weight`` observations (``fusion.register``), the
    marginal likelihood's optimum is no drift for the camera fleets too, and their poses lose what the drift
    gains them (docs/METHOD_LOG.md, "The drift prior fitted to the fleet")."""
    seen = np.isfinite(variance).all(axis=1)
    if seen.sum() < min_submaps:
        return ceiling
    return np.minimum(np.sqrt(np.mean(bends[seen] ** 2 + variance[seen], axis=0)), ceiling)
