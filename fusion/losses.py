"""The training objective (DESIGN.md): SDF, normal, semantic, eikonal, confidence, odometry (+ GPS prior).

All distances in metres, rotations in radians. Normals and the eikonal term come from the same
central differences of the SDF, taken on a fraction of the samples with a step tied to the finest
active grid level (Neuralangelo), so the step shrinks as progressive LOD adds levels.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from fusion import se3
from fusion.config import FusionConfig
from fusion.field import SemanticSDFField
from fusion.labels import UNLABELED
from fusion.sampling import Batch


def pose_residual(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Translation (…, 3) metres and rotation vector (…, 3) radians of ``b⁻¹ ∘ a`` ((…, 4, 4) each)."""
    e = se3.inverse(b) @ a
    return e[..., :3, 3], se3.so3_log(e[..., :3, :3])


def odometry_loss(
    poses: Tensor, pairs: Tensor, odom_rel: Tensor, inv_sigma_t: Tensor, inv_sigma_r: Tensor
) -> Tensor:
    """Mean squared weighted discrepancy of consecutive relative poses against odometry.

    poses (M, 4, 4) local → tile; pairs (E, 2) indices (i, i+1) of the same session; odom_rel (E, 4, 4)
    the odometry relative pose ``O_{i+1}⁻¹ O_i``; inv_sigma_t / inv_sigma_r (E,) 1/σ of the pair.
    """
    if pairs.numel() == 0:
        return poses.new_zeros(())
    rel = se3.inverse(poses[pairs[:, 1]]) @ poses[pairs[:, 0]]
    dt, dr = pose_residual(rel, odom_rel)
    return ((dt * inv_sigma_t[:, None]) ** 2 + (dr * inv_sigma_r[:, None]) ** 2).sum(-1).mean()


def gps_prior_loss(poses: Tensor, init: Tensor, inv_sigma_t: Tensor, inv_sigma_r: Tensor) -> Tensor:
    """Weak anchor of every pose to its initial (GPS) pose: fixes the gauge. Shapes (M, 4, 4), (M,)."""
    dt, dr = pose_residual(poses, init)
    return ((dt * inv_sigma_t[:, None]) ** 2 + (dr * inv_sigma_r[:, None]) ** 2).sum(-1).mean()


def robust_square(r: Tensor, delta: float) -> Tensor:
    """``r²`` up to ``|r| = delta``, then linear (Huber, scaled to match ``r²`` below ``delta``): a sample
    the field contradicts by more than ``delta`` (another session's depth error, a parked car gone)
    pulls the field and the poses with a bounded force ``2·delta`` instead of one growing with its
    residual. ``delta`` 0: plain ``r²``."""
    if delta <= 0:
        return r**2
    a = r.abs()
    return torch.where(a <= delta, r**2, 2 * delta * a - delta**2)


def field_losses(
    field: SemanticSDFField, batch: Batch, config: FusionConfig, gen: torch.Generator
) -> tuple[dict[str, Tensor], int]:
    """Field terms of the loss on one batch. Returns terms by name and the number of field points
    evaluated (for throughput)."""
    n_surf = batch.surf_x.shape[0]
    n_space = batch.space_x.shape[0]
    x = torch.cat([batch.surf_x, batch.space_x], dim=0)  # (n + m, 3)
    s, c_logit, logits = field(x)
    assert logits is not None
    terms: dict[str, Tensor] = {}
    terms["sdf"] = robust_square(s[:n_surf] - batch.surf_sdf, config.sdf_robust_m).mean()

    labelled = batch.surf_label != UNLABELED
    if bool(labelled.any()):
        terms["sem"] = F.cross_entropy(logits[:n_surf][labelled], batch.surf_label[labelled])
    else:
        terms["sem"] = s.new_zeros(())

    conf_target = torch.cat([batch.surf_conf, batch.surf_conf.new_zeros(n_space)])
    terms["conf"] = F.binary_cross_entropy_with_logits(c_logit, conf_target)

    # numerical gradients on a subset of surface and space samples
    eps = config.normal_eps_cells * field.finest_active_cell_m()
    k_surf = max(1, int(math.ceil(n_surf * config.normal_fraction)))
    k_space = min(n_space, max(1, int(math.ceil(n_space * config.normal_fraction))))
    sub_surf = torch.randperm(n_surf, generator=gen, device="cpu")[:k_surf].to(x.device)
    sub_space = torch.randperm(max(n_space, 1), generator=gen, device="cpu")[:k_space].to(x.device) + n_surf
    probe = torch.cat([sub_surf, sub_space]) if n_space > 0 else sub_surf
    grad = field.numerical_gradient(x[probe], eps)  # (k, 3)
    gnorm = grad.norm(dim=-1)
    normal = grad[:k_surf] / gnorm[:k_surf, None].clamp_min(1e-6)
    terms["norm"] = ((normal - batch.surf_normal[sub_surf]) ** 2).sum(-1).mean()
    terms["eik"] = ((gnorm - 1) ** 2).mean()
    evaluated = x.shape[0] + 6 * probe.shape[0]
    return terms, evaluated


def total_loss(terms: dict[str, Tensor], config: FusionConfig) -> Tensor:
    weights = {
        "sdf": config.lambda_sdf,
        "norm": config.lambda_norm,
        "sem": config.lambda_sem,
        "eik": config.lambda_eik,
        "conf": config.lambda_conf,
        "odom": config.lambda_odom,
        "gps": config.lambda_gps,
    }
    return sum((weights[k] * v for k, v in terms.items()), start=torch.zeros((), device=next(iter(terms.values())).device))
