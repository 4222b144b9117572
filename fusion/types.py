"""Plain data types shared across the fusion library (numpy, no torch).

Frames: a submap's mesh lives in its *local* frame; ``Pose`` maps local → target frame
(``p_target = R(q) · p_local + t``, quaternion Hamilton w-first, metres). The *map* frame is the
deployment's ENU frame (x east, y north, z up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from fusion.errors import PoseError

UNIT_QUATERNION_TOLERANCE = 1e-3


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion ``[w, x, y, z]``."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Rotation angle in degrees of rotation matrices ``(..., 3, 3)`` (shape ``(...)``)."""
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1) / 2
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` (w ≥ 0) of a rotation matrix (3, 3)."""
    m = r
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q, dtype=np.float64)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0 else -qa


@dataclass(frozen=True)
class Pose:
    """Rigid transform local → target: ``t`` (3,) metres, ``q`` (4,) unit quaternion w-first."""

    t: np.ndarray
    q: np.ndarray

    @staticmethod
    def identity() -> Pose:
        return Pose(np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))

    @staticmethod
    def from_json(data: dict[str, Any]) -> Pose:
        """Parse ``{"t": [x, y, z], "q": [w, x, y, z]}``; rejects non-unit quaternions (> 1e-3)."""
        try:
            t = np.asarray(data["t"], dtype=np.float64).reshape(3)
            q = np.asarray(data["q"], dtype=np.float64).reshape(4)
        except (KeyError, TypeError, ValueError) as exc:
            raise PoseError("a pose is {'t': [x, y, z], 'q': [w, x, y, z]}") from exc
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
            raise PoseError("pose values must be finite numbers")
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
            raise PoseError(f"quaternion must be unit length within {UNIT_QUATERNION_TOLERANCE} (norm {norm:.6f})")
        return Pose(t, q / norm)

    def to_json(self) -> dict[str, list[float]]:
        return {"t": [float(v) for v in self.t], "q": [float(v) for v in self.q]}

    @staticmethod
    def from_matrix(m: np.ndarray) -> Pose:
        return Pose(np.asarray(m[:3, 3], dtype=np.float64).copy(), matrix_to_quat(np.asarray(m[:3, :3])))

    def matrix(self) -> np.ndarray:
        """Homogeneous (4, 4) matrix."""
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(self.q)
        m[:3, 3] = self.t
        return m

    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.q)

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: first apply ``other``, then ``self``."""
        return Pose.from_matrix(self.matrix() @ other.matrix())

    def inverse(self) -> Pose:
        r = self.rotation()
        return Pose(-(r.T @ self.t), np.array([self.q[0], -self.q[1], -self.q[2], -self.q[3]]))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (n, 3) from the source into the target frame."""
        return points @ self.rotation().T + self.t


@dataclass
class SemanticMesh:
    """A validated submap mesh in its local frame (metres).

    vertices: float64 (n, 3); faces: int64 (m, 3) triangles; face_labels: int64 (m,) label ids
    (0 = unlabeled).
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_labels: np.ndarray


@dataclass
class FusedMesh:
    """A fused tile mesh in the map frame.

    vertices: float32 (n, 3); faces: int32 (m, 3); vertex_labels: uint8 (n,);
    vertex_confidence: float32 (n,) in [0, 1]; face_labels: uint8 (m,).
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_labels: np.ndarray
    vertex_confidence: np.ndarray
    face_labels: np.ndarray

    @staticmethod
    def empty() -> FusedMesh:
        return FusedMesh(
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.int32),
            np.zeros(0, np.uint8),
            np.zeros(0, np.float32),
            np.zeros(0, np.uint8),
        )


@dataclass(frozen=True)
class Sigma:
    """1-sigma uncertainty of a pose: translation metres, rotation degrees."""

    trans_m: float
    rot_deg: float


@dataclass
class SubmapInput:
    """One submap as the fusion sees it.

    ``pose_init``: initial local → map pose (GPS, or the current refined pose);
    ``pose_gps``: the GPS fix the weak GPS prior (the gauge) anchors to; None means ``pose_init``.
    Re-fusions start from the refined pose but keep anchoring to GPS, so repeated fusions of a tile
    do not let the map's gauge random-walk away from GPS;
    ``odometry``: local → session-odometry-frame pose; ``free``: whether fusion may move the pose
    (submaps owned by another tile are held fixed).
    """

    id: str
    session_id: str
    seq: int
    mesh: SemanticMesh
    pose_init: Pose
    odometry: Pose
    gps_sigma: Sigma = Sigma(2.0, 2.0)
    odometry_sigma: Sigma = Sigma(0.05, 0.5)
    free: bool = True
    pose_gps: Pose | None = None


@dataclass(frozen=True)
class TileSpec:
    """Tile (i, j) of the map frame: x ∈ [i·S, (i+1)·S), y ∈ [j·S, (j+1)·S), all heights."""

    i: int
    j: int
    size_m: float = 64.0

    @property
    def xy_min(self) -> tuple[float, float]:
        return (self.i * self.size_m, self.j * self.size_m)

    @property
    def xy_max(self) -> tuple[float, float]:
        return ((self.i + 1) * self.size_m, (self.j + 1) * self.size_m)


@dataclass
class ProgressEvent:
    """Reported by the optimiser: ``iteration`` of ``total``; ``losses`` by term name."""

    iteration: int
    total: int
    losses: dict[str, float]
    stage: str = "train"


ProgressCallback = Callable[[ProgressEvent], None]

# what a reconstruction's warm start was trained as: the region alignment's field of the tile, the tile's
# previous reconstruction (a re-fusion after a session was added), or that reconstruction carried along with
# the tile's surface by a re-alignment that brought the tile no new submap (fusion.reconstruct.reconstruct_tile)
WarmKind = Literal["alignment", "reconstruction", "carried"]


@dataclass
class FusionResult:
    """Output of fusing one tile.

    mesh: fused mesh clipped to the tile (map frame); poses: refined local → map pose per free
    submap id; metrics: numbers worth recording (losses, iterations, duration_s, points_per_s, ...);
    config: the FusionConfig used, as a dict; border: SDF samples on the tile's border planes,
    keyed by side (``"x0"``, ``"x1"``, ``"y0"``, ``"y1"``), that a neighbouring tile's extraction may pin
    to so that their seam vertices coincide; field_state: the trained field's state (CPU tensors), the warm
    start of the tile's next re-fusion (None where no field was trained).
    """

    mesh: FusedMesh
    poses: dict[str, Pose]
    metrics: dict[str, Any]
    config: dict[str, Any]
    border: dict[str, Any] = field(default_factory=dict)
    field_state: dict[str, Any] | None = None
