"""SE(3) / so(3) maths in torch, batched over leading dimensions.

Twists are ``(..., 6)`` vectors ``[rho (3), phi (3)]`` (translation part first, rotation vector
second, radians); transforms are homogeneous ``(..., 4, 4)`` matrices mapping source → target
frame (``p_target = R · p_source + t``). Quaternions are Hamilton, w-first, as in ``fusion.types``.

Every function is differentiable and safe at zero angle (Taylor series below ``SMALL_ANGLE``), so
pose corrections initialised at zero get finite gradients.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from fusion.types import Pose

SMALL_ANGLE = 1e-3


def hat(phi: Tensor) -> Tensor:
    """Skew-symmetric matrices ``(..., 3, 3)`` of vectors ``(..., 3)``."""
    x, y, z = phi.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*phi.shape[:-1], 3, 3)


def vee(m: Tensor) -> Tensor:
    """Vector ``(..., 3)`` of the skew-symmetric part of ``(..., 3, 3)`` matrices."""
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], dim=-1
    )


def _rodrigues_coeffs(theta2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``A = sin θ/θ``, ``B = (1 − cos θ)/θ²``, ``C = (θ − sin θ)/θ³`` with series near zero."""
    small = theta2 < SMALL_ANGLE**2
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    c = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (t - torch.sin(t)) / (t2 * t))
    return a, b, c


def so3_exp(phi: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (radians)."""
    theta2 = (phi * phi).sum(-1)[..., None, None]
    a, b, _ = _rodrigues_coeffs(theta2)
    k = hat(phi)
    eye = torch.eye(3, dtype=phi.dtype, device=phi.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def so3_log(r: Tensor) -> Tensor:
    """Rotation vectors ``(..., 3)`` of rotation matrices ``(..., 3, 3)``; handles θ near 0 and π."""
    sv = vee(r)  # sin θ · axis
    ss = (sv * sv).sum(-1)
    s = ss.clamp_min(1e-30).sqrt()
    c = ((r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]) - 1) / 2
    theta = torch.atan2(s, c)
    small = (s < SMALL_ANGLE) & (c > 0)
    factor = torch.where(small, 1 + ss / 6 + 7 * ss**2 / 360, theta / torch.where(small, torch.ones_like(s), s))
    phi = factor[..., None] * sv
    # Near π, sin θ vanishes: recover the axis from the symmetric part (R + Rᵀ)/2 = cos θ I + (1 − cos θ) aaᵀ.
    near_pi = c < -0.99
    if bool(near_pi.any()):
        sym = 0.5 * (r + r.transpose(-1, -2))
        eye = torch.eye(3, dtype=r.dtype, device=r.device)
        aat = (sym - c[..., None, None] * eye) / (1 - c)[..., None, None]
        col = torch.diagonal(aat, dim1=-2, dim2=-1).argmax(-1)
        axis = torch.take_along_dim(aat, col[..., None, None].expand(*col.shape, 3, 1), dim=-1)[..., 0]
        axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        sign = torch.where((axis * sv).sum(-1) < 0, -1.0, 1.0).to(r.dtype)
        phi = torch.where(near_pi[..., None], axis * (sign * theta)[..., None], phi)
    return phi


def se3_exp(xi: Tensor) -> Tensor:
    """Transforms ``(..., 4, 4)`` of twists ``(..., 6)`` = ``[rho, phi]``."""
    rho, phi = xi[..., :3], xi[..., 3:]
    theta2 = (phi * phi).sum(-1)[..., None, None]
    a, b, c = _rodrigues_coeffs(theta2)
    k = hat(phi)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    rot = eye + a * k + b * k2
    v = eye + b * k + c * k2
    t = (v @ rho[..., None])[..., 0]
    return from_rt(rot, t)


def se3_log(m: Tensor) -> Tensor:
    """Twists ``(..., 6)`` = ``[rho, phi]`` of transforms ``(..., 4, 4)``."""
    rot, t = m[..., :3, :3], m[..., :3, 3]
    phi = so3_log(rot)
    theta2 = (phi * phi).sum(-1)[..., None, None]
    small = theta2 < SMALL_ANGLE**2
    a, b, _ = _rodrigues_coeffs(theta2)
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    d = torch.where(small, 1 / 12 + theta2 / 720 + theta2**2 / 30240, (1 - a / (2 * b)) / safe2)
    k = hat(phi)
    eye = torch.eye(3, dtype=m.dtype, device=m.device).expand_as(k)
    v_inv = eye - 0.5 * k + d * (k @ k)
    rho = (v_inv @ t[..., None])[..., 0]
    return torch.cat([rho, phi], dim=-1)


def from_rt(rot: Tensor, t: Tensor) -> Tensor:
    """Homogeneous ``(..., 4, 4)`` from rotation ``(..., 3, 3)`` and translation ``(..., 3)``."""
    top = torch.cat([rot, t[..., None]], dim=-1)
    bottom = torch.zeros(*rot.shape[:-2], 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def compose(a: Tensor, b: Tensor) -> Tensor:
    """``a ∘ b`` (apply ``b`` first), ``(..., 4, 4)``."""
    return a @ b


def inverse(m: Tensor) -> Tensor:
    """Inverse of rigid transforms ``(..., 4, 4)``."""
    rt = m[..., :3, :3].transpose(-1, -2)
    return from_rt(rt, -(rt @ m[..., :3, 3:4])[..., 0])


def apply(m: Tensor, points: Tensor) -> Tensor:
    """Transform points ``(..., n, 3)`` by ``(..., 4, 4)`` (broadcast over leading dims)."""
    return points @ m[..., :3, :3].transpose(-1, -2) + m[..., None, :3, 3]


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` ``[w, x, y, z]`` (normalised here)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def matrix_to_quat(r: Tensor) -> Tensor:
    """Unit quaternions ``(..., 4)`` ``[w, x, y, z]`` with ``w ≥ 0`` of rotation matrices ``(..., 3, 3)``."""
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Four candidate formulas; each is well conditioned when its leading component is the largest.
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    lead = 0.5 * sq.clamp_min(1e-12).sqrt()  # |w|, |x|, |y|, |z|
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s01, s02, s12 = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    lw, lx, ly, lz = lead.unbind(-1)
    cands = torch.stack(
        [
            torch.stack([lw, d21 / (4 * lw), d02 / (4 * lw), d10 / (4 * lw)], -1),
            torch.stack([d21 / (4 * lx), lx, s01 / (4 * lx), s02 / (4 * lx)], -1),
            torch.stack([d02 / (4 * ly), s01 / (4 * ly), ly, s12 / (4 * ly)], -1),
            torch.stack([d10 / (4 * lz), s02 / (4 * lz), s12 / (4 * lz), lz], -1),
        ],
        dim=-2,
    )
    best = sq.argmax(-1)
    q = torch.take_along_dim(cands, best[..., None, None].expand(*best.shape, 1, 4), dim=-2)[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def pose_to_matrix(pose: Pose, dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu") -> Tensor:
    """``(4, 4)`` tensor of a ``fusion.types.Pose`` (local → target)."""
    return torch.as_tensor(pose.matrix(), dtype=dtype, device=device)


def matrix_to_pose(m: Tensor) -> Pose:
    """``fusion.types.Pose`` of a ``(4, 4)`` tensor (re-orthonormalised through the quaternion)."""
    md = m.detach().to("cpu", torch.float64)
    q = matrix_to_quat(md[:3, :3]).numpy()
    return Pose(np.asarray(md[:3, 3].numpy(), dtype=np.float64).copy(), q)
