"""Vehicles driving through a synthetic world, and the submaps they would upload.

Each session follows a route (straight along a road, or turning at a junction) in the right-hand
lane, in either direction. Every ~``submap_length`` metres it closes a submap: the part of the world
its sensor saw along that stretch (range, facing and occlusion tests), re-triangulated and noisy,
in the submap's own local frame (origin at the vehicle pose where the submap starts: x forward,
z up, tilted with the road). The vehicle reports an odometry pose (session odometry frame, with
accumulated drift) and a GPS pose (map frame, noisy). Truth stays in the ``SubmapRecord``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from fusion.eval.synth.camera import CameraSensor
from fusion.eval.synth.placement import make_object, road_frame
from fusion.eval.synth.world import World
from fusion.types import Pose, SemanticMesh, Sigma


@dataclass
class FleetParams:
    """Sessions, sensor and noise model. Lengths in metres, angles in degrees. ``sensor_range``,
    ``vertex_noise_m``, ``label_noise``, ``drops_*`` describe the exact sensor; a ``camera`` brings its own."""

    sessions: int = 5
    submap_length: float = 25.0
    sensor_range: float = 25.0
    sensor_height: float = 1.6
    submap_res: float = 0.4
    drive_margin: float = 6.0
    lane_offset: float = 1.75
    speed_mps: float = 8.0
    vertex_noise_m: float = 0.025
    label_noise: float = 0.05
    drops_per_submap: tuple[int, int] = (0, 3)
    drop_radius_m: tuple[float, float] = (1.0, 3.5)
    gps_sigma_m: float = 1.5
    gps_sigma_deg: float = 1.5
    gps_z_factor: float = 0.3  # z and roll/pitch noise relative to x/y and yaw
    odo_trans_per_m: float = 0.004
    odo_yaw_deg_per_m: float = 0.01
    transients_per_session: tuple[int, int] = (1, 2)
    # None: the exact sensor (crops of the world with the white vertex/label noise and dropouts above);
    # a CameraSensor: one front camera's pipeline (``fusion.eval.synth.camera``) replaces that noise model
    camera: CameraSensor | None = None


@dataclass
class SubmapRecord:
    """What one submap uploads (``mesh``, ``meta()``) plus its truth (never uploaded)."""

    name: str
    agent_id: str
    session_id: str
    seq: int
    captured_at: str
    mesh: SemanticMesh
    pose_true: Pose
    pose_gps: Pose
    odometry: Pose
    gps_sigma: Sigma
    odometry_sigma: Sigma
    seen_ground: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    seen_parts: dict[int, np.ndarray] = field(default_factory=dict)
    session: int = 0  # the session's index in the fleet (the transients' owner tag)

    def meta(self) -> dict:
        """The ``meta`` JSON object of API.md."""
        return {
            "agent_id": self.agent_id,
            "session_id": self.session_id,
            "seq": self.seq,
            "captured_at": self.captured_at,
            "gps": {"pose": self.pose_gps.to_json()},
            "gps_sigma": {"trans_m": self.gps_sigma.trans_m, "rot_deg": self.gps_sigma.rot_deg},
            "odometry": self.odometry.to_json(),
            "odometry_sigma": {"trans_m": self.odometry_sigma.trans_m, "rot_deg": self.odometry_sigma.rot_deg},
        }


def _smooth(path: np.ndarray, window: int) -> np.ndarray:
    pad = np.concatenate([np.repeat(path[:1], window, 0), path, np.repeat(path[-1:], window, 0)])
    kernel = np.ones(2 * window + 1) / (2 * window + 1)
    return np.column_stack([np.convolve(pad[:, k], kernel, mode="same")[window:-window] for k in range(2)])


def _resample(path: np.ndarray, step: float) -> np.ndarray:
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    t = np.arange(0.0, s[-1], step)
    return np.column_stack([np.interp(t, s, path[:, k]) for k in range(path.shape[1])])


def route_options(world: World) -> list[list[tuple[int, int, int, int]]]:
    """Routes as lists of legs (road, from index, to index, direction): straight along every road in
    both directions, and every turn at every junction."""
    options = [[(k, 0, len(r) - 1, 1)] for k, r in enumerate(world.roads)]
    options += [[(k, len(r) - 1, 0, -1)] for k, r in enumerate(world.roads)]
    for k, rk in enumerate(world.roads):
        for m, rm in enumerate(world.roads):
            if m == k:
                continue
            dist, j = cKDTree(rm).query(rk)
            i = int(np.argmin(dist))
            if dist[i] > 0.5:
                continue
            j = int(j[i])
            for dk in (1, -1):
                for dm in (1, -1):
                    leg1 = (k, 0, i, 1) if dk == 1 else (k, len(rk) - 1, i, -1)
                    leg2 = (m, j, len(rm) - 1, 1) if dm == 1 else (m, j, 0, -1)
                    if abs(leg1[2] - leg1[1]) > 40 and abs(leg2[2] - leg2[1]) > 40:
                        options.append([leg1, leg2])
    return options


def make_route(world: World, legs: list[tuple[int, int, int, int]], params: FleetParams,
               rng: np.random.Generator) -> np.ndarray:
    """Driven path (k, 3) in the map frame at 0.25 m steps: lane-offset, smoothed, clipped to the core."""
    pts = []
    for road, a, b, d in legs:
        lo, hi = min(a, b), max(a, b)
        seg = world.roads[road][lo : hi + 1]
        pts.append(seg if d == 1 else seg[::-1])
    centre = _resample(_smooth(np.concatenate(pts), 24), 0.25)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True) + 1e-12
    right = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    path = centre + right * (params.lane_offset + rng.uniform(-0.3, 0.3))
    p = world.params
    core_lo = np.asarray(p.core_min) - params.drive_margin
    core_hi = np.asarray(p.core_max) + params.drive_margin
    inside = np.all((path >= core_lo) & (path <= core_hi), axis=1)
    runs = np.diff(np.concatenate([[0], inside.astype(int), [0]]))
    starts, ends = np.flatnonzero(runs == 1), np.flatnonzero(runs == -1)
    if len(starts) == 0:
        return np.zeros((0, 3))
    best = int(np.argmax(ends - starts))
    path = _resample(path[starts[best] : ends[best]], 0.25)
    return np.column_stack([path, world.base_height(path)])


def path_poses(path: np.ndarray) -> list[Pose]:
    """Vehicle poses (vehicle → map) along a 3D path: x forward along the path, z up (pitch with the road)."""
    fwd = np.gradient(path, axis=0)
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    left = np.cross([0.0, 0.0, 1.0], fwd)
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    up = np.cross(fwd, left)
    return [Pose.from_matrix(_mat(np.column_stack([f, lf, u]), p)) for f, lf, u, p in zip(fwd, left, up, path, strict=True)]


def _mat(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, t
    return m


def perturb(pose: Pose, sigma_m: float, sigma_deg: float, z_factor: float, rng: np.random.Generator,
            local: bool = False) -> Pose:
    """Pose with Gaussian noise: x/y translation σ ``sigma_m`` (z: × z_factor), yaw σ ``sigma_deg``
    (roll/pitch: × z_factor); in the target frame, or in the local frame if ``local``."""
    dt = rng.normal(size=3) * sigma_m * np.array([1.0, 1.0, z_factor])
    dr = np.radians(rng.normal(size=3) * sigma_deg * np.array([z_factor, z_factor, 1.0]))
    noise = Pose.from_matrix(_mat(Rotation.from_rotvec(dr).as_matrix(), np.zeros(3)))
    if local:
        return pose.compose(Pose.from_matrix(_mat(noise.rotation(), dt)))
    rotated = noise.compose(Pose(np.zeros(3), pose.q))
    return Pose(pose.t + dt, rotated.q)


def place_transients(world: World, session: int, path: np.ndarray, params: FleetParams,
                     rng: np.random.Generator) -> None:
    """Objects that only this session sees (a parked car, an obstacle), near its path in the core."""
    p = world.params
    lo, hi = np.asarray(p.core_min), np.asarray(p.core_max)
    in_core = np.flatnonzero(np.all((path[:, :2] > lo + 4) & (path[:, :2] < hi - 4), axis=1))
    want = int(rng.integers(params.transients_per_session[0], params.transients_per_session[1] + 1))
    placed = 0
    for _ in range(200):
        if placed >= want or len(in_core) == 0:
            break
        xy = path[rng.choice(in_core), :2]
        road, i = world.road_point(xy)
        kind = "vehicle" if rng.random() < 0.6 else "obstacle"
        lateral = p.road_half_width - (1.0 if kind == "vehicle" else 0.5)
        pos, yaw = road_frame(world.roads[road], i, int(rng.choice([-1, 1])), lateral)
        parts = make_object(world, kind, pos, yaw, rng, world.occupancy, session=session)
        world.parts += parts
        placed += bool(parts)
