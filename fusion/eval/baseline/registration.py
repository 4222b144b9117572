"""The paper's classical baseline: (G)ICP in a pose graph, then Poisson meshing with label transfer.

Algorithm (paper, "Baseline"):
1. sample ``icp_points`` (500) points on every submap (the registration source and the overlap
   measure) and ``target_points`` (20,000) as the surface they are registered against;
2. for each submap pick the ``neighbours`` (3) submaps whose GPS-posed samples overlap it most and
   register each pair with point-to-point ICP or Generalized ICP (Open3D), coarse to fine: the 500
   source points of one against the dense target sample of the other. (500 against 500 points leaves
   ~1.7 m between samples of the same surface, more than the 0.5 m final correspondence distance:
   every pair then scored a fitness below 0.1 and no loop closure entered the graph.);
3. build an Open3D ``PoseGraph``: one node per submap (initialised at ``pose_init``), an odometry
   edge between consecutive ``seq`` of a session (their relative odometry), an *uncertain*
   loop-closure edge per registered pair (pruned by the line process of global optimisation), and a
   weak prior edge from every submap to a fixed anchor node at the map origin (GPS; the gauge, the
   same role the GPS prior plays in the neural fusion); submaps that are not ``free`` get a stiff
   prior, so they stay where they are;
4. Levenberg–Marquardt global optimisation, then Poisson reconstruction of ``poisson_points``
   (1,000,000) oriented samples from the aligned submaps, density trimming, 5-NN label transfer
   and clipping to the tile (:mod:`fusion.eval.baseline.poisson`).

``method="gps"`` skips 2–4's alignment and meshes the submaps at their initial poses.

Open3D is the optional extra ``fleetmap[baseline]`` (``pip install open3d-cpu``; on Debian it needs
``libusb-1.0-0``); it is imported lazily.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from fusion.eval.baseline.poisson import (
    OrientedSamples,
    label_and_clip,
    mesh_area,
    poisson_mesh,
    sample_oriented,
)
from fusion.types import FusedMesh, Pose, SubmapInput, TileSpec

Method = Literal["icp", "gicp", "gps"]
STIFF_INFORMATION = 1e6  # prior weight that pins a submap the tile does not own


@dataclass(frozen=True)
class BaselineConfig:
    """Baseline parameters; defaults are the paper's, tests pass smaller ones.

    Distances in metres, tile margin in metres around the tile's xy box.
    """

    method: Method = "icp"
    icp_points: int = 500
    target_points: int = 20_000
    neighbours: int = 3
    max_correspondence_m: tuple[float, ...] = (2.0, 1.0, 0.5)  # coarse-to-fine ICP stages
    icp_iterations: int = 30
    min_fitness: float = 0.3  # pairs with fewer inliers than this fraction give no edge
    overlap_radius_m: float = 2.0
    edge_prune_threshold: float = 0.25
    poisson_points: int = 1_000_000
    poisson_depth: int = 11
    density_quantile: float = 0.05
    max_distance_m: float | None = 1.0  # also trim Poisson vertices this far from every sample
    label_neighbours: int = 5
    margin_m: float = 8.0
    seed: int = 0


def _information(trans_m: float, rot_deg: float) -> np.ndarray:
    """6×6 information matrix in Open3D's order (rotation rad, then translation m)."""
    rot = np.deg2rad(max(rot_deg, 1e-3))
    trans = max(trans_m, 1e-3)
    return np.diag([1 / rot**2] * 3 + [1 / trans**2] * 3)


def _select_pairs(posed: list[np.ndarray], neighbours: int, radius: float) -> list[tuple[int, int]]:
    """Unordered pairs (i < j): each submap with its ``neighbours`` most-overlapping others.

    Overlap of i with j: the fraction of i's map-frame samples within ``radius`` of j's samples.
    """
    trees = [cKDTree(p) for p in posed]
    pairs: set[tuple[int, int]] = set()
    for i, pts in enumerate(posed):
        scores = []
        for j, tree in enumerate(trees):
            if j == i or len(pts) == 0 or tree.n == 0:
                continue
            dist, _ = tree.query(pts, k=1, distance_upper_bound=radius)
            overlap = float(np.isfinite(dist).mean())
            if overlap > 0:
                scores.append((overlap, j))
        for _, j in sorted(scores, reverse=True)[:neighbours]:
            pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def _register(source: np.ndarray, target: np.ndarray, init: np.ndarray, cfg: BaselineConfig):
    """(G)ICP of local-frame samples: returns (T_target_source (4, 4), information (6, 6), fitness)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    criteria = reg.ICPConvergenceCriteria(max_iteration=cfg.icp_iterations)
    transform = init
    result = None
    for dist in cfg.max_correspondence_m:
        if cfg.method == "gicp":
            gicp = reg.TransformationEstimationForGeneralizedICP(epsilon=1e-3, kernel=reg.HuberLoss(dist / 2))
            result = reg.registration_generalized_icp(src, tgt, dist, transform, gicp, criteria)
        else:
            p2p = reg.TransformationEstimationPointToPoint()
            result = reg.registration_icp(src, tgt, dist, transform, p2p, criteria)
        transform = result.transformation
    final_dist = cfg.max_correspondence_m[-1]
    info = reg.get_information_matrix_from_point_clouds(src, tgt, final_dist, transform)
    return np.asarray(transform), np.asarray(info), float(result.fitness if result is not None else 0.0)


def align(submaps: list[SubmapInput], cfg: BaselineConfig) -> tuple[dict[str, Pose], dict[str, float]]:
    """Pose-graph alignment of submaps; returns the local → map pose per submap id and statistics."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    rng = np.random.default_rng(cfg.seed)
    init = [s.pose_init.matrix() for s in submaps]
    if cfg.method == "gps" or len(submaps) < 2:
        return {s.id: s.pose_init for s in submaps}, {"pairs": 0, "loop_edges": 0, "odometry_edges": 0}

    local = [sample_oriented(s.mesh, cfg.icp_points, rng).points for s in submaps]
    dense = [sample_oriented(s.mesh, cfg.target_points, rng).points for s in submaps]
    posed = [s.pose_init.apply(p) for s, p in zip(submaps, local, strict=True)]
    pairs = _select_pairs(posed, cfg.neighbours, cfg.overlap_radius_m)

    graph = reg.PoseGraph()
    graph.nodes.append(reg.PoseGraphNode(np.eye(4)))  # anchor: the map frame itself, fixed
    for m in init:
        graph.nodes.append(reg.PoseGraphNode(m))
    # Edge (s, t, T): T maps node s's frame into node t's, i.e. pose_s ≈ pose_t · T.
    _add_prior_edges(graph, submaps, init)
    odometry_edges = _add_odometry_edges(graph, submaps)
    loop_edges, fitness_sum = _add_loop_edges(graph, pairs, local, dense, init, cfg)
    _optimise(graph, cfg)
    # The anchor is the reference node, but re-express relative to it in case the solver moved it.
    anchor_inv = np.linalg.inv(np.asarray(graph.nodes[0].pose))
    poses = {
        s.id: Pose.from_matrix(anchor_inv @ np.asarray(graph.nodes[k + 1].pose))
        for k, s in enumerate(submaps)
    }
    stats: dict[str, float] = {
        "pairs": len(pairs),
        "loop_edges": loop_edges,
        "loop_edges_kept": sum(bool(e.uncertain) for e in graph.edges),  # after the line-process pruning
        "mean_fitness": fitness_sum / max(len(pairs), 1),
        "odometry_edges": odometry_edges,
    }
    return poses, stats


def _add_prior_edges(graph: Any, submaps: list[SubmapInput], init: list[np.ndarray]) -> None:
    """Each submap tied to the anchor (node 0) at its initial (GPS) pose, weighted by its GPS sigma; held
    submaps (not ``free``) stiffly."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    for k, s in enumerate(submaps):
        info = _information(s.gps_sigma.trans_m, s.gps_sigma.rot_deg)
        if not s.free:
            info = np.eye(6) * STIFF_INFORMATION
        graph.edges.append(reg.PoseGraphEdge(k + 1, 0, init[k], info, uncertain=False))


def _add_odometry_edges(graph: Any, submaps: list[SubmapInput]) -> int:
    """An edge between consecutive submaps of a session (their relative odometry); returns the count."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    by_session: dict[str, list[int]] = {}
    for k, s in enumerate(submaps):
        by_session.setdefault(s.session_id, []).append(k)
    odometry_edges = 0
    for members in by_session.values():
        members.sort(key=lambda k: submaps[k].seq)
        for a, b in zip(members, members[1:], strict=False):
            sa, sb = submaps[a], submaps[b]
            if sb.seq != sa.seq + 1:
                continue  # a gap in the session: no odometry between these two
            rel = sb.odometry.inverse().compose(sa.odometry).matrix()
            info = _information(sa.odometry_sigma.trans_m, sa.odometry_sigma.rot_deg)
            graph.edges.append(reg.PoseGraphEdge(a + 1, b + 1, rel, info, uncertain=False))
            odometry_edges += 1
    return odometry_edges


def _add_loop_edges(graph: Any, pairs: list[tuple[int, int]], local: list[np.ndarray], dense: list[np.ndarray],
                    init: list[np.ndarray], cfg: BaselineConfig) -> tuple[int, float]:
    """A registration (ICP / GICP) edge per overlapping pair that fits well enough (``min_fitness``);
    returns (edges added, sum of the fitness over all pairs)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    loop_edges = 0
    fitness_sum = 0.0
    for i, j in pairs:
        guess = np.linalg.inv(init[j]) @ init[i]
        transform, info, fitness = _register(local[i], dense[j], guess, cfg)
        fitness_sum += fitness
        if fitness < cfg.min_fitness:
            continue
        graph.edges.append(reg.PoseGraphEdge(i + 1, j + 1, transform, info, uncertain=True))
        loop_edges += 1
    return loop_edges, fitness_sum


def _optimise(graph: Any, cfg: BaselineConfig) -> None:
    """Levenberg-Marquardt over the pose graph, the anchor (node 0) as reference; prunes bad loop edges."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=cfg.max_correspondence_m[-1],
        edge_prune_threshold=cfg.edge_prune_threshold,
        preference_loop_closure=1.0,
        reference_node=0,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(
            graph,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )


def reconstruct(
    submaps: list[SubmapInput], poses: dict[str, Pose], tile: TileSpec, cfg: BaselineConfig
) -> tuple[FusedMesh, dict[str, float]]:
    """Poisson mesh of the posed submaps, labelled and clipped to the tile (map frame); timings (s)."""
    rng = np.random.default_rng(cfg.seed + 1)
    areas = np.array([mesh_area(s.mesh) for s in submaps])
    counts = np.floor(cfg.poisson_points * areas / max(areas.sum(), 1e-12)).astype(int)
    t0 = time.perf_counter()
    samples = OrientedSamples.concatenate(
        [
            sample_oriented(s.mesh, int(c), rng).transformed(poses[s.id])
            for s, c in zip(submaps, counts, strict=True)
        ]
    )
    t1 = time.perf_counter()
    if len(samples.points) < 4:
        return FusedMesh.empty(), {"sample_s": t1 - t0, "poisson_s": 0.0, "label_s": 0.0}
    vertices, faces = poisson_mesh(samples, cfg.poisson_depth, cfg.density_quantile, cfg.max_distance_m)
    t2 = time.perf_counter()
    mesh = label_and_clip(vertices, faces, samples, tile, cfg.label_neighbours)
    t3 = time.perf_counter()
    return mesh, {"sample_s": t1 - t0, "poisson_s": t2 - t1, "label_s": t3 - t2}


def _near_tile(submap: SubmapInput, tile: TileSpec, margin_m: float) -> bool:
    """Whether the submap's GPS-posed bounding box touches the tile grown by ``margin_m``."""
    v = submap.pose_init.apply(submap.mesh.vertices)
    lo, hi = v.min(axis=0), v.max(axis=0)
    (x0, y0), (x1, y1) = tile.xy_min, tile.xy_max
    return bool(
        lo[0] <= x1 + margin_m
        and hi[0] >= x0 - margin_m
        and lo[1] <= y1 + margin_m
        and hi[1] >= y0 - margin_m
    )


def run_baseline(
    submaps: list[SubmapInput],
    tile: TileSpec,
    method: Method | None = None,
    config: BaselineConfig | None = None,
) -> tuple[FusedMesh, dict[str, Pose], dict[str, float]]:
    """Classical baseline for one tile.

    Returns the labelled Poisson mesh clipped to the tile (map frame), the refined local → map pose
    of every free submap by id, and timings in seconds (``align_s``, ``sample_s``, ``poisson_s``,
    ``label_s``, ``total_s``) plus graph statistics.
    """
    cfg = config or BaselineConfig()
    if method is not None and method != cfg.method:
        cfg = BaselineConfig(**{**cfg.__dict__, "method": method})
    t0 = time.perf_counter()
    near = [s for s in submaps if _near_tile(s, tile, cfg.margin_m)]
    poses, stats = align(near, cfg)
    t1 = time.perf_counter()
    mesh, timing = reconstruct(near, poses, tile, cfg)
    timing = {"align_s": t1 - t0, **timing, "total_s": time.perf_counter() - t0, **stats}
    free = {s.id: poses[s.id] for s in near if s.free}
    return mesh, free, timing


def run_baseline_region(
    submaps: list[SubmapInput],
    tiles: list[TileSpec],
    method: Method | None = None,
    config: BaselineConfig | None = None,
) -> tuple[dict[tuple[int, int], FusedMesh], dict[str, Pose], dict[str, Any]]:
    """Classical baseline for a multi-tile region, as a tiled service would run it: ONE pose graph over
    every submap of the region (the same data the fusion's region alignment sees), then a Poisson
    mesh per tile from the submaps near it, clipped to the tile (map frame).

    Returns the mesh per tile key, the aligned pose of every free submap, and timings (``align_s``,
    ``tile_s`` per tile key, ``total_s``) with the graph statistics."""
    cfg = config or BaselineConfig()
    if method is not None and method != cfg.method:
        cfg = BaselineConfig(**{**cfg.__dict__, "method": method})
    t0 = time.perf_counter()
    poses, stats = align(submaps, cfg)
    align_s = time.perf_counter() - t0
    meshes: dict[tuple[int, int], FusedMesh] = {}
    tile_s: dict[str, float] = {}
    for tile in tiles:
        t1 = time.perf_counter()
        near = [s for s in submaps if _near_tile(s, tile, cfg.margin_m)]
        meshes[(tile.i, tile.j)] = reconstruct(near, poses, tile, cfg)[0] if near else FusedMesh.empty()
        tile_s[f"{tile.i}_{tile.j}"] = time.perf_counter() - t1
    timing: dict[str, Any] = {"align_s": align_s, "tile_s": tile_s, "total_s": time.perf_counter() - t0, **stats}
    return meshes, {s.id: poses[s.id] for s in submaps if s.free}, timing
