"""What tile reconstruction (``fusion.reconstruct``) and region alignment (``fusion.align``) share in
their training loops: the pose terms (odometry chain, GPS prior), the optimiser and its schedule, one
optimisation step, progress reports and the final map-frame poses.

Frames: poses are ``(M, 4, 4)`` float64 local → *working frame* (a tile's or a region's frame: the map
frame shifted by ``origin``); :func:`map_poses` shifts them back to the map frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from fusion.config import FusionConfig
from fusion.losses import gps_prior_loss, odometry_loss
from fusion.poses import PoseSet, odometry_pairs
from fusion.types import Pose, ProgressCallback, ProgressEvent, SubmapInput


@dataclass
class PoseTerms:
    """Odometry pairs of every session chain and the inverse GPS sigmas, on the device."""

    pairs: Tensor
    odom_rel: Tensor
    odom_ist: Tensor
    odom_isr: Tensor
    gps_ist: Tensor  # (M,) 1 / σ_trans, 1/m
    gps_isr: Tensor  # (M,) 1 / σ_rot, 1/rad

    @classmethod
    def of(cls, submaps: list[SubmapInput], dev: torch.device) -> PoseTerms:
        pairs, rel, ist, isr = (t.to(dev) for t in odometry_pairs(submaps))
        gps_ist = torch.tensor([1 / max(s.gps_sigma.trans_m, 1e-3) for s in submaps], dtype=torch.float64, device=dev)
        gps_isr = torch.tensor([1 / np.radians(max(s.gps_sigma.rot_deg, 1e-3)) for s in submaps],
                               dtype=torch.float64, device=dev)
        return cls(pairs, rel, ist, isr, gps_ist, gps_isr)

    def losses(self, poses: Tensor, gps: Tensor) -> dict[str, Tensor]:
        """``odom`` and ``gps`` terms of poses ``(M, 4, 4)`` against GPS anchors ``gps`` (same frame)."""
        return {
            "odom": odometry_loss(poses, self.pairs, self.odom_rel, self.odom_ist, self.odom_isr).float(),
            "gps": gps_prior_loss(poses, gps, self.gps_ist, self.gps_isr).float(),
        }


class Optimiser:
    """AdamW over the field parameters (if any) and the poses (separate translation / rotation rates),
    exponential decay to ``lr_decay_final`` over ``iterations``; pose gradients are dropped during the
    first ``warmup`` steps (the field takes a rough shape before the poses move)."""

    def __init__(self, field_params: list[nn.Parameter], poses: PoseSet, config: FusionConfig, iterations: int,
                 warmup: int) -> None:
        groups = [{"params": [poses.rho], "lr": config.lr_pose_trans, "weight_decay": 0.0},
                  {"params": [poses.phi], "lr": config.lr_pose_rot, "weight_decay": 0.0}]
        if field_params:
            groups.insert(0, {"params": field_params, "lr": config.lr_field, "weight_decay": config.weight_decay})
        self.poses, self.warmup = poses, warmup
        self.optimizer = torch.optim.AdamW(groups)
        gamma = config.lr_decay_final ** (1.0 / max(iterations, 1))
        self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma)

    def step(self, it: int, loss: Tensor, planar: bool = False) -> None:
        """One step; ``planar``: the poses move only in x, y and yaw (height, roll and pitch held)."""
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if it < self.warmup:
            self.poses.rho.grad = None
            self.poses.phi.grad = None
        elif planar:
            for grad, held in ((self.poses.rho.grad, slice(2, 3)), (self.poses.phi.grad, slice(0, 2))):
                if grad is not None:
                    grad[:, held] = 0.0
        self.optimizer.step()
        self.scheduler.step()


def consensus_iterations(config: FusionConfig, iterations: int) -> set[int]:
    """Steps at which the confidence targets are recomputed from the current poses."""
    return {int(f * iterations) for f in config.consensus_at} if config.consensus else set()


def loss_values(terms: dict[str, Tensor], loss: Tensor) -> dict[str, float]:
    return {k: float(v.detach()) for k, v in terms.items()} | {"total": float(loss.detach())}


class Reporter:
    """Progress about 50 times per run (and at the last step) under ``stage``."""

    def __init__(self, progress: ProgressCallback | None, iterations: int, stage: str) -> None:
        self.progress, self.iterations, self.stage = progress, iterations, stage
        self.every = max(1, iterations // 50)

    def __call__(self, it: int, terms: dict[str, Tensor], loss: Tensor) -> None:
        if self.progress is not None and (it % self.every == 0 or it == self.iterations - 1):
            self.progress(ProgressEvent(it + 1, self.iterations, loss_values(terms, loss), self.stage))


def map_poses(poses: PoseSet, origin: np.ndarray, submaps: list[SubmapInput]) -> dict[str, Pose]:
    """The free submaps' poses, local → map frame (``origin``: the working frame's map position)."""
    with torch.no_grad():
        final = poses().cpu().numpy()
    to_map = np.eye(4)
    to_map[:3, 3] = origin
    return {s.id: Pose.from_matrix(to_map @ final[k]) for k, s in enumerate(submaps) if s.free}
