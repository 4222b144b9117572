"""SE(3) identities: exp/log round trips, inverses, quaternions, finite gradients at zero."""

from __future__ import annotations

import numpy as np
import torch

from fusion import se3
from fusion.types import Pose


def _twists(n: int, scale: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 6, generator=g, dtype=torch.float64) * 2 - 1) * scale


def test_exp_log_round_trip_across_angles() -> None:
    for scale in (1e-9, 1e-5, 1e-2, 0.5, 2.0):
        xi = _twists(64, scale)
        assert torch.allclose(se3.se3_log(se3.se3_exp(xi)), xi, atol=1e-9)
        t = se3.se3_exp(xi)
        assert torch.allclose(se3.se3_exp(se3.se3_log(t)), t, atol=1e-9)


def test_log_near_pi() -> None:
    axis = torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64)
    axis = axis / axis.norm()
    for angle in (np.pi - 1e-3, np.pi - 1e-7, np.pi):
        phi = axis * angle
        r = se3.so3_exp(phi)
        back = se3.so3_log(r)
        assert torch.allclose(se3.so3_exp(back), r, atol=1e-7)
        assert abs(float(back.norm()) - angle) < 1e-6


def test_rotation_is_orthonormal_and_inverse_composes_to_identity() -> None:
    t = se3.se3_exp(_twists(32, 1.5))
    r = t[:, :3, :3]
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(32, 3, 3), atol=1e-12)
    assert torch.allclose(torch.det(r), torch.ones(32, dtype=torch.float64))
    eye = torch.eye(4, dtype=torch.float64).expand(32, 4, 4)
    assert torch.allclose(se3.compose(t, se3.inverse(t)), eye, atol=1e-12)
    assert torch.allclose(se3.compose(se3.inverse(t), t), eye, atol=1e-12)


def test_apply_matches_matrix_product() -> None:
    t = se3.se3_exp(_twists(1, 1.0))[0]
    p = torch.randn(10, 3, dtype=torch.float64)
    homog = torch.cat([p, torch.ones(10, 1, dtype=torch.float64)], 1) @ t.T
    assert torch.allclose(se3.apply(t, p), homog[:, :3])


def test_quaternion_round_trip_and_agreement_with_numpy_pose() -> None:
    r = se3.se3_exp(_twists(50, 3.0))[:, :3, :3]
    q = se3.matrix_to_quat(r)
    assert torch.all(q[:, 0] >= 0)
    assert torch.allclose(se3.quat_to_matrix(q), r, atol=1e-10)
    pose = Pose.from_matrix(se3.se3_exp(_twists(1, 1.0, seed=3))[0].numpy())
    m = se3.pose_to_matrix(pose)
    back = se3.matrix_to_pose(m)
    assert np.allclose(back.t, pose.t) and np.allclose(back.q, pose.q)


def test_gradients_finite_at_zero() -> None:
    xi = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    p = torch.randn(3, 5, 3, dtype=torch.float64)
    loss = se3.apply(se3.se3_exp(xi), p).square().sum() + se3.se3_log(se3.se3_exp(xi)).square().sum()
    loss = loss + se3.so3_log(se3.so3_exp(xi[:, 3:])).norm(dim=-1).sum()
    loss.backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all()
    assert torch.autograd.gradcheck(se3.se3_exp, (torch.zeros(2, 6, dtype=torch.float64, requires_grad=True),))
    assert torch.autograd.gradcheck(se3.se3_log, (se3.se3_exp(_twists(2, 0.3)).requires_grad_(True),))
