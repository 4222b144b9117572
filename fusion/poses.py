"""Submap poses under optimisation: one se(3) correction per free submap, applied about its centroid.

Frames: poses map a submap's local frame → the *tile* frame (map frame shifted by the tile origin,
metres). The refined pose is ``C ∘ exp(ξ) ∘ C⁻¹ ∘ P_start`` where ``C`` translates to the submap's
centroid, so a rotation correction turns the submap about itself rather than about the map origin
(better conditioned: rotation and translation decouple).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from fusion import se3
from fusion.types import SubmapInput


class PoseSet(nn.Module):
    """Corrections for M submaps; ``free`` (M,) bool masks which may move."""

    start: Tensor
    to_centroid: Tensor
    free: Tensor

    def __init__(self, start: Tensor, centroid: Tensor, free: Tensor) -> None:
        super().__init__()
        m = start.shape[0]
        self.register_buffer("start", start.double().clone())  # (M, 4, 4) local → tile
        c = torch.eye(4, dtype=torch.float64).repeat(m, 1, 1)
        c[:, :3, 3] = centroid.double()
        self.register_buffer("to_centroid", c)  # (M, 4, 4)
        self.register_buffer("free", free.double()[:, None])  # (M, 1)
        self.rho = nn.Parameter(torch.zeros(m, 3, dtype=torch.float64))  # metres
        self.phi = nn.Parameter(torch.zeros(m, 3, dtype=torch.float64))  # radians

    def forward(self) -> Tensor:
        """Current poses (M, 4, 4) float64, local → tile frame."""
        xi = torch.cat([self.rho, self.phi], dim=-1) * self.free
        corr = self.to_centroid @ se3.se3_exp(xi) @ se3.inverse(self.to_centroid)
        return corr @ self.start


def odometry_pairs(submaps: list[SubmapInput]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Consecutive submaps (by seq) of each session within the list.

    Returns pairs (E, 2) int64 (i, next), odometry relative poses ``O_next⁻¹ O_i`` (E, 4, 4) float64,
    and 1/σ translation (1/m) and rotation (1/rad) per pair (σ grows with √(seq gap)).
    """
    by_session: dict[str, list[int]] = {}
    for k, sm in enumerate(submaps):
        by_session.setdefault(sm.session_id, []).append(k)
    pairs, rels, ist, isr = [], [], [], []
    for members in by_session.values():
        members.sort(key=lambda k: submaps[k].seq)
        for a, b in zip(members[:-1], members[1:], strict=True):
            gap = math.sqrt(max(1, submaps[b].seq - submaps[a].seq))
            rel = np.linalg.inv(submaps[b].odometry.matrix()) @ submaps[a].odometry.matrix()
            sig = submaps[b].odometry_sigma
            pairs.append((a, b))
            rels.append(rel)
            ist.append(1.0 / (max(sig.trans_m, 1e-4) * gap))
            isr.append(1.0 / (math.radians(max(sig.rot_deg, 1e-3)) * gap))
    if not pairs:
        return (torch.zeros(0, 2, dtype=torch.long), torch.zeros(0, 4, 4, dtype=torch.float64),
                torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))
    return (torch.tensor(pairs, dtype=torch.long), torch.tensor(np.stack(rels)),
            torch.tensor(ist, dtype=torch.float64), torch.tensor(isr, dtype=torch.float64))


def odometry_consistent_start(
    submaps: list[SubmapInput], init: list[np.ndarray], centroids_local: list[np.ndarray]
) -> list[np.ndarray]:
    """Starting poses (4, 4) per submap: each session's odometry chain placed by its GPS poses.

    The odometry → map transform ``G`` of a session takes its rotation from the chordal mean of the
    per-submap estimates ``R_gps · R_odomᵀ`` and its translation from the mean centroid offset, each
    weighted by 1/σ² (fixed submaps dominate, so they keep their pose). With accurate odometry this
    averages the independent GPS errors of a session's submaps. Sessions with one submap keep theirs.
    """
    out = [m.copy() for m in init]
    by_session: dict[str, list[int]] = {}
    for k, sm in enumerate(submaps):
        by_session.setdefault(sm.session_id, []).append(k)
    for members in by_session.values():
        if len(members) < 2 or not any(submaps[k].free for k in members):
            continue
        acc_r, acc_t, acc_w = np.zeros((3, 3)), np.zeros(3), 0.0
        odo = {k: submaps[k].odometry.matrix() for k in members}
        wr = {k: (1.0 if submaps[k].free else 1e6) / max(math.radians(submaps[k].gps_sigma.rot_deg), 1e-6) ** 2
              for k in members}
        for k in members:
            acc_r += wr[k] * init[k][:3, :3] @ odo[k][:3, :3].T
        u, _, vt = np.linalg.svd(acc_r)
        rot = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        for k in members:
            w = (1.0 if submaps[k].free else 1e6) / max(submaps[k].gps_sigma.trans_m, 1e-6) ** 2
            c_gps = init[k][:3, :3] @ centroids_local[k] + init[k][:3, 3]
            c_odo = odo[k][:3, :3] @ centroids_local[k] + odo[k][:3, 3]
            acc_t += w * (c_gps - rot @ c_odo)
            acc_w += w
        g = np.eye(4)
        g[:3, :3], g[:3, 3] = rot, acc_t / acc_w
        for k in members:
            if submaps[k].free:
                out[k] = g @ odo[k]
    return out
