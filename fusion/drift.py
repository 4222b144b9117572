"""A submap's monocular drift: one scale and a slow bend of its local frame, estimated with its pose.

Why: a local map built by one camera is not rigid. Its scale is held only by what the network believes
(the camera's known height) and its heading and pitch drift slowly along the way, so a point ``x``
metres ahead of the submap's reference ends up ``(s − 1)·x`` too far and ``κ·x²/2`` off to the side or
up. A rigid pose cannot undo either: it fits the middle of the submap and leaves its far end dm off,
where another session's surface then stands as a second one. Concatenating the camera bench's uploads
at their *true* poses (3×3 world, seed 0) scores geo F 0.897 / sem F 0.503 at 0.2 m; without the
simulated scale error 0.902 / 0.541; without scale and bend 0.988 / 0.606.

What: the correction ``D`` maps a submap's uploaded local frame to a corrected local frame, about the
local origin (the point its pose, odometry and GPS fix describe: drift is zero there and grows away
from it). With ``a`` the submap's direction ahead (its vertices' main horizontal axis, pointing to their
mean), ``b = z × a`` and ``x = p·a``, a point ``p`` is turned about ``z`` by ``κ_yaw·x/2`` and about ``b``
by ``κ_pitch·x/2`` (half the heading error at ``x``: the rotation that integrates a heading drift growing
linearly with distance), then scaled by ``exp(log_scale)``. The pose maps the corrected frame to the map
as before, so a vehicle's refined pose stays rigid. Priors (``fusion.config``, ``fine_drift_*``) keep the
three numbers near zero where the overlaps say nothing (a straight road leaves the stretch along it open).

Frames: local frame of the submap (metres); angles in radians, bend rates in rad/m.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fusion.types import SubmapInput

PARAMS = 3  # log scale, yaw bend rate (rad/m), pitch bend rate (rad/m)


@dataclass(frozen=True)
class Drift:
    """The correction of one submap (see the module docstring); ``axis`` the unit horizontal direction
    ahead in its local frame (x, y)."""

    log_scale: float = 0.0
    bend_yaw: float = 0.0  # rad/m
    bend_pitch: float = 0.0  # rad/m
    axis: tuple[float, float] = (1.0, 0.0)

    @property
    def params(self) -> np.ndarray:
        return np.array([self.log_scale, self.bend_yaw, self.bend_pitch])

    def is_identity(self) -> bool:
        return not self.params.any()

    def with_params(self, params: np.ndarray) -> Drift:
        return Drift(float(params[0]), float(params[1]), float(params[2]), self.axis)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Points ``(n, 3)`` of the uploaded local frame in the corrected local frame (metres)."""
        return deform(points, self.params, np.asarray(self.axis, dtype=np.float64))

    def to_json(self) -> dict[str, Any]:
        return {"scale": float(np.exp(self.log_scale)), "bend_yaw_rad_per_m": self.bend_yaw,
                "bend_pitch_rad_per_m": self.bend_pitch, "axis": [float(a) for a in self.axis]}

    @staticmethod
    def from_json(data: dict[str, Any] | None) -> Drift:
        if not data:
            return Drift()
        ax = data.get("axis", [1.0, 0.0])
        return Drift(float(np.log(data["scale"])), float(data["bend_yaw_rad_per_m"]),
                     float(data["bend_pitch_rad_per_m"]), (float(ax[0]), float(ax[1])))


def ahead_axis(vertices: np.ndarray) -> tuple[float, float]:
    """The unit horizontal direction (local x, y) along which a submap's surface spreads most from its
    origin, signed towards the vertices' mean: the way the vehicle mapped (a forward camera's strip of
    road ahead, a loop's chord)."""
    xy = vertices[:, :2]
    if len(xy) < 2:
        return (1.0, 0.0)
    mean = xy.mean(0)
    _, vecs = np.linalg.eigh(np.cov((xy - mean).T) + np.eye(2) * 1e-12)
    axis = vecs[:, -1]
    if axis @ mean < 0:
        axis = -axis
    return (float(axis[0]), float(axis[1]))


def deform(points: np.ndarray, params: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``points`` (n, 3) local → corrected local frame under ``params`` (log scale, yaw and pitch bend rates)
    with ``axis`` (2,) the unit direction ahead; see the module docstring."""
    log_scale, k_yaw, k_pitch = (float(v) for v in params)
    a = np.array([axis[0], axis[1], 0.0])
    b = np.array([-axis[1], axis[0], 0.0])
    x, y, z = points @ a, points @ b, points[:, 2]
    yaw, pitch = k_yaw * x / 2, k_pitch * x / 2
    x1, y1 = np.cos(yaw) * x - np.sin(yaw) * y, np.sin(yaw) * x + np.cos(yaw) * y
    x2, z2 = np.cos(pitch) * x1 - np.sin(pitch) * z, np.sin(pitch) * x1 + np.cos(pitch) * z
    return np.exp(log_scale) * (x2[:, None] * a + y1[:, None] * b + z2[:, None] * np.array([0.0, 0.0, 1.0]))


def jacobian(points: np.ndarray, params: np.ndarray, axis: np.ndarray, step: float = 1e-6) -> np.ndarray:
    """d deform / d params at ``params``: (n, 3, PARAMS), by central differences (three cheap evaluations)."""
    out = np.empty((len(points), 3, PARAMS))
    for k in range(PARAMS):
        d = np.zeros(PARAMS)
        d[k] = step
        out[:, :, k] = (deform(points, params + d, axis) - deform(points, params - d, axis)) / (2 * step)
    return out


def corrected_input(submap: SubmapInput, correction: Drift | None) -> SubmapInput:
    """``submap`` with its mesh in the corrected local frame (itself where there is no correction)."""
    if correction is None or correction.is_identity():
        return submap
    mesh = replace(submap.mesh, vertices=correction.apply(submap.mesh.vertices))
    return replace(submap, mesh=mesh)
