"""Write a synthetic fleet's uploads to a directory, and its ground truth beside them.

Layout of ``out_dir``::

    NAME.ply, NAME.json      one per submap: the mesh (local frame) and the API ``meta`` object
    ground_truth/world.ply   static world mesh (map frame): face ``label``, ``observed`` (seen by a
                             submap and not dropped), ``part`` (-1: ground)
    ground_truth/transients.ply  single-session objects: face ``label``, ``observed``, ``session``
    ground_truth/poses.json  {"submaps": [{"name", "session_id", "seq", "pose_true", "pose_gps", ...}]}
    ground_truth/world.json  generator parameters

Vehicles upload only the first two; the ground truth is for evaluation.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import plyfile

from fusion.eval.synth import shapes
from fusion.eval.synth.camera import sensor_model
from fusion.eval.synth.fleet import FleetParams, SubmapRecord
from fusion.eval.synth.submap import drive
from fusion.eval.synth.world import World, WorldParams, world_overrides
from fusion.meshio import write_submap_ply
from fusion.types import Pose


@dataclass
class GroundTruth:
    """Evaluation truth (map frame, metres): the static world mesh with per-face labels and observed
    flags, the transient objects (per-face owning session), and the true pose of every submap."""

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray
    observed: np.ndarray
    transient_vertices: np.ndarray
    transient_faces: np.ndarray
    transient_labels: np.ndarray
    transient_observed: np.ndarray
    transient_session: np.ndarray
    poses: dict[str, Pose]  # submap name → true local → map pose
    info: dict
    sessions: dict[str, int] = field(default_factory=dict)  # submap name → session index (``transient_session``)


def _assemble(world: World, records: list[SubmapRecord]) -> tuple[tuple, tuple]:
    gv, gf, gl = world.gt_ground()
    g_obs = np.zeros(len(gf), bool)
    for r in records:
        g_obs[r.seen_ground] = True
    # (vertices, faces, labels, observed, tag): tag = part index (static) or session (transient); ground -1
    static: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]] = [(gv, gf, gl, g_obs, -1)]
    trans: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]] = []
    for i, part in enumerate(world.parts):
        obs = np.zeros(len(part.faces), bool)
        for r in records:
            if i in r.seen_parts:
                obs[r.seen_parts[i]] = True
        (static if part.session is None else trans).append(
            (part.vertices, part.faces, part.labels, obs, i if part.session is None else part.session))

    def cat(items: list) -> tuple:
        if not items:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, bool), np.zeros(0, np.int64)
        v, f = shapes.merge([(it[0], it[1]) for it in items])
        tag = np.concatenate([np.full(len(it[1]), it[4]) for it in items])
        return v, f, np.concatenate([it[2] for it in items]), np.concatenate([it[3] for it in items]), tag

    return cat(static), cat(trans)


def _write_gt_ply(path: Path, v: np.ndarray, f: np.ndarray, labels: np.ndarray, observed: np.ndarray,
                  tag_name: str, tag: np.ndarray) -> None:
    vert = np.empty(len(v), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    vert["x"], vert["y"], vert["z"] = v.T
    face = np.empty(len(f), dtype=[("vertex_indices", "i4", (3,)), ("label", "u1"), ("observed", "u1"), (tag_name, "i4")])
    face["vertex_indices"], face["label"], face["observed"], face[tag_name] = f, labels, observed, tag
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex"), plyfile.PlyElement.describe(face, "face")]).write(str(path))


def _read_gt_ply(path: Path, tag_name: str) -> tuple[np.ndarray, ...]:
    ply = plyfile.PlyData.read(str(path))
    v = np.column_stack([ply["vertex"][k] for k in ("x", "y", "z")]).astype(np.float64)
    face = ply["face"].data
    f = np.asarray(np.stack(face["vertex_indices"]) if len(face) else np.zeros((0, 3)), np.int64).reshape(-1, 3)
    return v, f, face["label"].astype(np.int64), face["observed"].astype(bool), face[tag_name].astype(np.int64)


def simulate(out_dir: str | Path, seed: int = 0, sessions: int = 5, gps_noise: tuple[float, float] = (1.5, 1.5),
             world_params: WorldParams | None = None, fleet_params: FleetParams | None = None,
             sensor: str | None = None, camera: Sequence[str] = (), world: Sequence[str] = ()
             ) -> list[SubmapRecord]:
    """Generate a world (``seed``), drive ``sessions`` sessions through it and write what they upload
    (``NAME.ply`` + ``NAME.json``) plus ``ground_truth/``. ``gps_noise``: (σ metres, σ degrees).

    ``world_params``/``fleet_params`` override the defaults (their seed/sessions/GPS fields are set
    from the arguments). ``sensor``: ``camera`` or ``exact`` (``fusion.eval.synth.camera.sensor_model``)
    sets ``fleet_params.camera``; None keeps it (the default fleet: exact). ``camera`` / ``world``: ``KEY=VALUE``
    overrides of the camera model's fields (``CameraSensor``; with ``sensor`` camera) and of the world's
    (``WorldParams``; ``seed`` and the core are the caller's: rejected). Raises ``ValueError`` on a bad
    override before anything is written. Returns the submap records (with their truth).
    """
    out = Path(out_dir)
    wp = world_overrides(world_params or WorldParams(), world)
    wp.seed = seed
    fp = fleet_params or FleetParams()
    fp.sessions, fp.gps_sigma_m, fp.gps_sigma_deg = sessions, float(gps_noise[0]), float(gps_noise[1])
    if sensor is not None:
        fp.camera = sensor_model(sensor, camera)
    elif camera:
        raise ValueError("camera overrides need the camera sensor (sensor='camera')")
    scene = World(wp)
    records = drive(scene, fp, np.random.default_rng(seed + 7919))
    out.mkdir(parents=True, exist_ok=True)
    for r in records:
        (out / f"{r.name}.ply").write_bytes(write_submap_ply(r.mesh))
        (out / f"{r.name}.json").write_text(json.dumps(r.meta(), indent=1))
    gt = out / "ground_truth"
    gt.mkdir(exist_ok=True)
    (sv, sf, sl, so, spart), (tv, tf, tl, to, tsess) = _assemble(scene, records)
    _write_gt_ply(gt / "world.ply", sv, sf, sl, so, "part", spart)
    _write_gt_ply(gt / "transients.ply", tv, tf, tl, to, "session", tsess)
    poses = [{"name": r.name, "session_id": r.session_id, "session": r.session, "seq": r.seq, "pose_true": r.pose_true.to_json(),
              "pose_gps": r.pose_gps.to_json(), "odometry": r.odometry.to_json()} for r in records]
    sessions_ids = sorted({r.session_id for r in records})
    (gt / "poses.json").write_text(json.dumps({"submaps": poses, "sessions": sessions_ids}, indent=1))
    info = {"world": asdict(wp), "fleet": asdict(fp), "sensor": "exact" if fp.camera is None else "camera",
            "sidewalk_width_m": scene.sidewalk_width,
            "roads": len(scene.roads), "submaps": len(records)}
    (gt / "world.json").write_text(json.dumps(info, indent=1))
    return records


def load_ground_truth(out_dir: str | Path) -> GroundTruth:
    """Read ``out_dir/ground_truth`` written by ``simulate``."""
    gt = Path(out_dir) / "ground_truth"
    v, f, lab, obs, _ = _read_gt_ply(gt / "world.ply", "part")
    tv, tf, tl, to, ts = _read_gt_ply(gt / "transients.ply", "session")
    records = json.loads((gt / "poses.json").read_text())["submaps"]
    poses = {p["name"]: Pose.from_json(p["pose_true"]) for p in records}
    sessions = {p["name"]: int(p["session"]) for p in records if "session" in p}
    return GroundTruth(v, f, lab, obs, tv, tf, tl, to, ts, poses, json.loads((gt / "world.json").read_text()), sessions)
