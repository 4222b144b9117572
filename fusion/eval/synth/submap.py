"""Turn what a vehicle saw along a stretch of road into a noisy submap in its local frame."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from fusion.eval.synth import shapes
from fusion.eval.synth.camera import CameraSensor, Place, degrade
from fusion.eval.synth.fleet import (
    FleetParams,
    SubmapRecord,
    make_route,
    path_poses,
    perturb,
    place_transients,
    route_options,
)
from fusion.eval.synth.visibility import FieldOfView, visible_faces
from fusion.eval.synth.world import World
from fusion.labels import NUM_CLASSES
from fusion.types import Pose, SemanticMesh, Sigma

CAMERA_STREAM = 0xCA  # seeds the camera's per-submap generators apart from the world's and the fleet's


class _Context:
    """Per-world caches: face centroids/normals of the GT ground and of every part (map frame)."""

    def __init__(self, world: World) -> None:
        v, f, _ = world.gt_ground()
        self.ground_c = v[f].mean(axis=1)
        self.ground_n = shapes.face_normals(v, f)[0]
        self.parts = []
        for p in world.parts:
            self.parts.append((p.vertices[p.faces].mean(axis=1), shapes.face_normals(p.vertices, p.faces)[0],
                               p.vertices.min(axis=0), p.vertices.max(axis=0)))


def _in_box(xy: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((xy >= lo) & (xy <= hi), axis=1)


def _visible(world: World, ctx: _Context, session: int, sensors: np.ndarray, pose: Pose, params: FleetParams,
             max_range: float, fov: FieldOfView | None = None,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """What the sensors (k, 3) (map frame) see within ``max_range`` (and ``fov``): the submap's ground grid
    vertices (map frame), the centres, faces and labels of its visible faces, the GT ground faces seen and
    the faces seen of each part (by index)."""
    r = max_range
    lo, hi = sensors[:, :2].min(axis=0) - r, sensors[:, :2].max(axis=0) + r
    mine = [i for i, p in enumerate(world.parts) if p.session in (None, session)
            and np.all(ctx.parts[i][2][:2] <= hi) and np.all(ctx.parts[i][3][:2] >= lo)]
    my_parts = [world.parts[i] for i in mine]
    occluders = [q.footprint for q in my_parts if q.occluder and q.footprint is not None]  # occluders have one
    hidden = [q.footprint for q in my_parts if q.footprint is not None]

    gv, gc, g_faces, g_labels = _seen_ground_mesh(world, sensors, pose, params, occluders, hidden, r, fov)
    cand = np.flatnonzero(_in_box(ctx.ground_c[:, :2], lo, hi))
    seen_ground = cand[visible_faces(ctx.ground_c[cand], ctx.ground_n[cand], sensors, r, occluders, hidden, fov)]
    seen_parts = {}
    for i in mine:
        c, n = ctx.parts[i][:2]
        idx = np.flatnonzero(visible_faces(c, n, sensors, r, occluders, fov=fov))
        if len(idx):
            seen_parts[i] = idx
    return gv, gc, g_faces, g_labels, seen_ground, seen_parts


def observe(world: World, ctx: _Context, session: int, sensors: np.ndarray, pose: Pose, params: FleetParams,
            rng: np.random.Generator) -> tuple[SemanticMesh, np.ndarray, dict[int, np.ndarray]]:
    """The exact sensor's submap seen from ``sensors`` (k, 3) (map frame), in the local frame of ``pose``
    (local → map): a crop of the world with white vertex and label noise and dropout discs.

    Returns the noisy mesh, the GT ground faces seen and the faces seen of each part (by index).
    """
    gv, gc, g_faces, g_labels, seen_ground, seen_parts = _visible(world, ctx, session, sensors, pose, params,
                                                                  params.sensor_range)

    # sensor dropouts: discs of the map where this submap has nothing
    n_drop = int(rng.integers(params.drops_per_submap[0], params.drops_per_submap[1] + 1))
    if n_drop and len(g_faces):
        centres = gc[rng.choice(len(g_faces), n_drop), :2]
        radii = rng.uniform(*params.drop_radius_m, size=n_drop)

        def dropped(points: np.ndarray) -> np.ndarray:
            d = np.linalg.norm(points[:, None, :2] - centres[None], axis=2)
            return np.any(d < radii[None], axis=1)

        g_ok = ~dropped(gv[g_faces].mean(axis=1))
        g_faces, g_labels = g_faces[g_ok], g_labels[g_ok]
        seen_ground = seen_ground[~dropped(ctx.ground_c[seen_ground])]
        seen_parts = {i: f[~dropped(ctx.parts[i][0][f])] for i, f in seen_parts.items()}
        seen_parts = {i: f for i, f in seen_parts.items() if len(f)}

    return _noisy_local_mesh(world, gv, g_faces, g_labels, seen_parts, pose, params, rng), seen_ground, seen_parts


def observe_camera(world: World, ctx: _Context, session: int, sensors: np.ndarray, views: np.ndarray, pose: Pose,
                   params: FleetParams, camera: CameraSensor, rng: np.random.Generator,
                   ) -> tuple[SemanticMesh, np.ndarray, dict[int, np.ndarray]]:
    """The camera's submap: what the front camera at ``sensors`` (k, 3) looking along ``views`` (k, 3, 3,
    camera → map: forward, left, up; map frame) saw within its field of view and range, made by a
    camera pipeline (``fusion.eval.synth.camera.degrade``), in the local frame of ``pose``.

    Returns the mesh, the GT ground faces seen and the faces seen of each part (by index): the truth's
    ``observed`` set is what the camera saw; its holes and missed labels count as errors.
    """
    fov = FieldOfView(views, camera.hfov_deg, camera.vfov_deg)
    gv, _, g_faces, g_labels, seen_ground, seen_parts = _visible(world, ctx, session, sensors, pose, params,
                                                                 camera.range_m, fov)
    v, f, lab = _merge_seen(world, gv, g_faces, g_labels, seen_parts)
    to_local = pose.inverse()
    rotations = np.einsum("ij,kjl->kil", to_local.rotation(), views)
    place = Place(pose, world.params.seed)
    mesh = degrade(to_local.apply(v), f, lab, to_local.apply(sensors), rotations, camera, rng, place)
    return mesh, seen_ground, seen_parts


def _seen_ground_mesh(world: World, sensors: np.ndarray, pose: Pose, params: FleetParams, occluders: list,
                      hidden: list, max_range: float, fov: FieldOfView | None,
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ground the sensors see, re-triangulated on a grid of the submap's own frame: its vertices
    (map frame), the centres of the visible faces, those faces and their labels."""
    r = max_range
    local_sensors = pose.inverse().apply(sensors)
    res = params.submap_res
    llo, lhi = local_sensors[:, :2].min(axis=0) - r, local_sensors[:, :2].max(axis=0) + r
    xy_local, faces = shapes.grid(np.arange(llo[0], lhi[0] + res, res), np.arange(llo[1], lhi[1] + res, res))
    xy = pose.apply(np.column_stack([xy_local, np.zeros(len(xy_local))]))[:, :2]
    gv = np.column_stack([xy, world.ground_height(xy)])
    gc = gv[faces].mean(axis=1)
    keep = visible_faces(gc, shapes.face_normals(gv, faces)[0], sensors, r, occluders, hidden, fov)
    return gv, gc[keep], faces[keep], world.ground_label(gc[keep, :2])


def _merge_seen(world: World, gv: np.ndarray, g_faces: np.ndarray, g_labels: np.ndarray,
                seen_parts: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seen ground faces and seen part faces as one mesh (map frame): vertices, faces, face labels."""
    pieces = [shapes.compact(gv, g_faces)]
    labels = [g_labels]
    for i, f in seen_parts.items():
        part = world.parts[i]
        pieces.append(shapes.compact(part.vertices, part.faces[f]))
        labels.append(part.labels[f])
    v, f = shapes.merge(pieces)
    return v, f, np.concatenate(labels).astype(np.int64)


def _noisy_local_mesh(world: World, gv: np.ndarray, g_faces: np.ndarray, g_labels: np.ndarray,
                      seen_parts: dict[int, np.ndarray], pose: Pose, params: FleetParams,
                      rng: np.random.Generator) -> SemanticMesh:
    """Ground and seen part faces merged into one mesh in the submap's local frame, with vertex noise
    (``vertex_noise_m``) and label noise (``label_noise``: a wrong non-zero label)."""
    v, f, lab = _merge_seen(world, gv, g_faces, g_labels, seen_parts)
    v = pose.inverse().apply(v) + rng.normal(scale=params.vertex_noise_m, size=v.shape)
    flip = rng.random(len(lab)) < params.label_noise
    lab[flip] = (lab[flip] - 1 + rng.integers(1, NUM_CLASSES - 1, size=int(flip.sum()))) % (NUM_CLASSES - 1) + 1
    return SemanticMesh(v, f, lab)


def drive(world: World, params: FleetParams, rng: np.random.Generator) -> list[SubmapRecord]:
    """Drive ``params.sessions`` sessions through the world; every submap they upload, with truth."""
    options = route_options(world)
    order = rng.permutation(len(options))
    paths = []
    for k in range(params.sessions):
        for attempt in range(len(options)):
            path = make_route(world, options[order[(k + attempt) % len(options)]], params, rng)
            if len(path) * 0.25 >= 20.0:
                break
        paths.append(path)
        place_transients(world, k, path, params, rng)
    ctx = _Context(world)
    t0 = datetime(2026, 11, 24, 8, 0, 0, tzinfo=UTC)
    records = []
    for k, path in enumerate(paths):
        agent = f"veh-{k % 3 + 1:03d}"
        start = t0 + timedelta(hours=3 * k, minutes=int(rng.integers(0, 60)))
        session_id = f"{agent}/{start.strftime('%Y-%m-%dT%H:%M:%SZ')}"
        poses = path_poses(path)
        step = int(round(params.submap_length / 0.25))
        bounds = list(range(0, len(path), step))
        if len(path) - 1 - bounds[-1] < step // 3 and len(bounds) > 1:
            bounds.pop()
        bounds.append(len(path) - 1)
        odometry = Pose.identity()
        nominal = params.submap_length
        for seq, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            sensors = path[a : b + 1 : 10] + np.array([0.0, 0.0, params.sensor_height])
            if params.camera is None:
                mesh, seen_ground, seen_parts = observe(world, ctx, k, sensors, poses[a], params, rng)
            else:  # its own generator per submap: each submap's camera errors are reproducible alone
                views = np.stack([p.rotation() for p in poses[a : b + 1 : 10]])
                camera_rng = np.random.default_rng([world.params.seed, CAMERA_STREAM, k, seq])
                mesh, seen_ground, seen_parts = observe_camera(world, ctx, k, sensors, views, poses[a], params,
                                                               params.camera, camera_rng)
            if seq > 0:
                length = 0.25 * (a - bounds[seq - 1])
                rel = poses[bounds[seq - 1]].inverse().compose(poses[a])
                noisy = perturb(rel, params.odo_trans_per_m * length, params.odo_yaw_deg_per_m * length, 0.3, rng,
                                local=True)
                odometry = odometry.compose(noisy)
            records.append(SubmapRecord(
                name=f"s{k:02d}_{seq:03d}", agent_id=agent, session_id=session_id, seq=seq,
                captured_at=(start + timedelta(seconds=0.25 * a / params.speed_mps)).strftime("%Y-%m-%dT%H:%M:%SZ"),
                mesh=mesh, pose_true=poses[a],
                pose_gps=perturb(poses[a], params.gps_sigma_m, params.gps_sigma_deg, params.gps_z_factor, rng),
                odometry=odometry, gps_sigma=Sigma(params.gps_sigma_m, params.gps_sigma_deg),
                odometry_sigma=Sigma(params.odo_trans_per_m * nominal, params.odo_yaw_deg_per_m * nominal),
                seen_ground=seen_ground, seen_parts=seen_parts, session=k,
            ))
    return records
