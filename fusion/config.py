"""Fusion hyperparameters: one dataclass, named presets, recorded with every fused tile version.

Units: metres for lengths, radians per Adam step for the rotation learning rate, metres per Adam step
for the translation learning rate. Coordinates fed to the grid are the tile box normalised to
[0, 1]³ (see ``fusion.field.TileNormalizer``).

Deviations from the paper (DESIGN.md), all for the CPU preset's short schedule:
- Pose learning rates are 0.1 m and 1e-3 rad per step (paper: 1e-2 / 1e-4): with a few hundred
  decaying Adam steps, 1e-4 rad/step cannot undo a 1.5° GPS heading error nor 1e-2 m/step a 3 m
  (2σ) GPS offset. Tune per deployment.
- ``lambda_odom`` is 0.01 (residuals are in units of the odometry σ, so 1 made each session's chain
  too stiff for the field to align it); instead each session's chain is initialised by placing its
  odometry on the GPS poses (``odom_init``, rotation/translation averaging), which removed most of
  the GPS error on the synthetic bench.
- Confidence targets of surface samples are the cross-session consensus (of the sessions with
  evidence about a point, the fraction that saw a surface there; a session has evidence when it saw
  through the point: bare ground below it) instead of a constant 1, so objects seen by one session of
  many fall below ``c_th`` independent of the grid resolution (``consensus_*``). Surfaces of movable
  classes (vehicles, obstacles) need a second session's witness as well (``consensus_movable*``): no
  free-space evidence exists where one session drove alone.
- A tile's reconstruction starts from its region alignment's field (``recon_warm_fraction`` of the
  steps, every level at once) rather than from scratch: the alignment already trained it on the
  same data at nearly the final poses.
- Surface samples are class-balanced (``class_balance``, ``class_weight_max``): faces of classes rarer
  (by the submaps' labelled area) than average are drawn up to 4× more often than their area says,
  so thin classes (lane markings, signs, poles, fences) get enough samples for the semantic head.
- Thin classes (poles, sign plates, fences) get a minimum thickness in the reconstruction
  (``thin_inflate_m``): their surface samples sit 0.15 m out along the normal, so a structure thinner than
  two of the finest cells keeps an interior the field can hold instead of vanishing; the extracted faces
  of those classes move back in by as much (``thin_deflate``), so the map reports them where they are.
- Face labels are the semantic head's argmax at each face's centroid (``face_labels``), not the
  majority of its vertex labels: a 0.2 m lane marking between 0.25 m lattice columns has no vertex
  on it. A label that contradicts its face's geometry (a ground class on a steep face raised above the
  ground beside it, any other class on level ground at ground height) is replaced by the head's best label
  of the other group (``label_geometry``): a camera segmenter's 2D mistakes, lifted into 3D.
- Progressive LOD starts at 3 of 12 levels (``lod_start_levels``; ~2 m cells on a 64 m tile) rather
  than a finer start: with 6 levels (~1 m cells) the field fitted sessions ~1 m apart as two surfaces
  before the poses had moved, and the pose optimisation stalled there (bench seed 2, 3 sessions).
  The paper preset starts at 5 of 16 levels, the same ~2.5 m cells on a 128 m tile (DESIGN.md's
  "coarser half", 8 levels, is ~1 m cells there: poses went only from 2.50 m to 1.53 m on a GPU).
- Before the field alignment, every submap is registered onto the others' sessions by a joint robust
  point-to-plane ICP with the odometry and GPS terms and one more rigid correction per session
  (``fine_register``, ``fusion.register``), and while
  the field's active cells are coarser than ``align_planar_cell_m`` the alignment moves poses only in
  x, y and yaw: the coarse levels' pull on height and tilt depends on each submap's coverage, and bent
  forward-camera sessions apart in height (docs/METHOD_LOG.md, "Camera fleets").
- The paper preset extracts at 0.2 m (the F-score distance d of the paper's evaluation); 0.1 m made
  the lattice 8x and the mesh 4x larger.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from fusion.labels import LABEL_BY_NAME
from fusion.overrides import with_overrides

GRID_TYPES = ("hash", "dense", "octree")
CONSENSUS_EVIDENCE = ("free_space", "cover")
FINE_SOLVERS = ("gn", "lbfgs")


PRESETS = ("cpu", "paper", "tiny")


@dataclass(frozen=True)
class FusionConfig:
    # feature grid
    grid_type: str = "hash"  # "hash"; "dense" / "octree" are hooks for alternative FeatureGrids
    num_levels: int = 12
    features_per_level: int = 2
    log2_table_size: int = 16
    base_resolution: int = 16  # cells along the longest tile-box side at the coarsest level
    max_resolution: int = 512  # cells along the longest side at the finest level
    # positional encoding and heads
    pe_frequencies: int = 6  # sin/cos(2^k π x01), k < pe_frequencies
    geo_hidden: int = 64
    geo_layers: int = 2
    sem_hidden: int = 64
    sem_layers: int = 2
    # loss weights
    lambda_sdf: float = 1.0
    lambda_norm: float = 1.0
    lambda_sem: float = 1.0
    lambda_eik: float = 0.1
    lambda_conf: float = 1.0
    lambda_odom: float = 0.01  # odometry residuals are in σ units; 1 made chains too stiff to align (bench)
    lambda_gps: float = 1e-2
    sigma_s: float = 0.05  # metres, std of the surface-sample offset along the normal
    # SDF data term: squared up to this residual (metres), linear beyond (Huber; fusion.losses.robust_square);
    # 0: squared everywhere (the paper). 0.1 on the 2x2 camera bench, seeds 0/1/2: geo F 0.852/0.774/0.745 ->
    # 0.848/0.773/0.733, pose within run-to-run noise: off
    sdf_robust_m: float = 0.0
    # optimiser
    lr_field: float = 1e-2
    lr_pose_trans: float = 0.1  # metres per step (3e-2 until 2026-12: camera 2x2 bench, seeds 0-2, below)
    lr_pose_rot: float = 1e-3  # radians per step
    weight_decay: float = 1e-2
    lr_decay_final: float = 0.1  # exponential decay: lr(end) = lr · lr_decay_final
    iterations: int = 300  # a full tile's steps; fusion.schedule scales them with the tile's content
    odom_init: bool = True  # start from each session's odometry chain rigidly fitted to its GPS poses
    # coarse registration (fusion.coarse): each session's odometry chain, as one rigid body, searched over
    # yaw × 3-D shift (±coarse_range_sigmas σ/√n: a chain of n submaps sits on n GPS fixes) against the
    # other sessions' surfaces before the field alignment: widens the pose basin beyond the coarsest field
    # level's ~2 m
    coarse_register: bool = True
    coarse_voxel_m: float = 1.0  # first stage's voxel (second: half of it)
    coarse_points_per_m2: float = 8.0  # reference surface samples per m² (capped per submap below)
    coarse_max_points: int = 30_000
    coarse_match_points: int = 2000  # moving samples scored per candidate
    coarse_range_sigmas: float = 3.0
    coarse_max_shift_m: float = 12.0
    coarse_max_yaw_deg: float = 15.0
    # of the candidates within max(coarse_tie_min, coarse_tie × the best's gain over the start) of the best
    # score, the one moving the session least wins: along a straight road the GPS start keeps the direction
    # the data leave open
    coarse_tie: float = 0.15
    coarse_tie_min: float = 0.01
    coarse_min_gain: float = 0.02  # keep a correction only if it raises the score this much over the start
    # fine registration (fusion.register): every submap registered onto the others by joint point-to-plane ICP
    # (robust, with the odometry and GPS terms) after the coarse stage, before the field alignment. Alignment
    # only, 3x3 camera bench seed 0 (share of the uploads within 0.2 m of the truth; 0.83 at the true poses):
    # 0.36 -> 0.65 (planar coarse phase, below) -> 0.72 (both); exact 0.96 -> 0.97
    fine_register: bool = True
    fine_samples: int = 2000  # surface samples per submap
    fine_vertical_weight: float = 4.0  # non-ground faces this × more likely to be sampled
    # non-ground samples spread over the horizontal directions their normals face (normal-space sampling,
    # fusion.register.surface_samples; 0: by area): facades along a street leave the direction of travel open
    fine_normal_balance: float = 1.0
    # match samples to the own session's other submaps too, pooled with the other sessions' (superseded by
    # fine_own_overlap below, which weighs them by how well they fit; kept for the method log's runs). Off, each session's chain
    # between the places other sessions pin it was shaped by odometry alone; on, its consecutive submaps'
    # overlaps hold it. Start poses, 3x3 exact bench seed 0, with fine_noise_max_gain 20: 0.104 -> 0.071 m; but
    # fused camera seed 0 geo F 0.801 -> 0.746 (monocular submaps of one session share their biases): off
    fine_same_session: bool = False
    # with fine_same_session: ground-like samples (normal within ~45° of up) match the own session too (off:
    # only walls, poles and other upright surfaces do)
    fine_same_session_ground: bool = True
    # a session's consecutive submaps match each other too, as data of their own beside the other sessions'
    # matches, per session (fusion.match_weights.own_gains): weighted by the gain their residuals earn at the
    # finest radius over fine_noise_max_gain (exact overlaps, cm apart after a rigid fit, count nearly fully; a
    # monocular session's, whose scale and bend leave dm a rigid fit cannot remove, ~1/20: matching them stiffly
    # hands the distortion on to the chain, fine_same_session above); ground-like matches weighted up by their
    # spread only as far as the session's walls fit tighter than the finest Cauchy scale (a monocular road
    # fits tight while its scale error lifts it). Whole pipeline, 3x3 bench, GPS 1.5 m, one run each, off -> on
    # (geo F / sem F / pose m / deg; 2026-12-05, twenty-first session): exact 0 0.983/0.803/0.124/0.161 ->
    # 0.984/0.817/0.105/0.127, exact 1 0.982/0.774/0.091/0.152 -> 0.982/0.760/0.073/0.118, exact 2
    # 0.978/0.785/0.100/0.136 -> 0.985/0.800/0.078/0.103; camera 0 0.799/0.346/0.485 -> 0.780/0.352/0.477,
    # camera 1 0.900/0.401/0.281 -> 0.919/0.420/0.283, camera 2 0.852/0.365/0.346 -> 0.859/0.384/0.332. Poses
    # better on every exact seed, camera 0 loses ~0.02 geo F (camera 0's fused geo F varies 0.80-0.82 between
    # runs). Judged by the residuals after a rigid re-fit of each pair instead, camera 0 lost 0.055: a monocular
    # pair's small overlap fits rigidly (reverted). docs/METHOD_LOG.md, "A session's own overlaps by default"
    fine_own_overlap: bool = True
    # the Cauchy scale (m) at which a session's own overlaps earn their trust (above): fine_min_dist_m / 2 until
    # the finest radius was widened, kept where it was measured
    fine_own_trust_m: float = 0.125
    # each free submap's monocular drift (one scale, a slow yaw and pitch bend about its local origin,
    # fusion.drift) estimated with its pose in every round of the fine registration, then held: the field
    # alignment, the reconstruction and the service's later jobs see the corrected submap. Gauss-Newton
    # solver only. Priors: scale σ and bend-rate σ (wide against a monocular mapper's ~1 % / ~0.02°/m) ...
    fine_drift: bool = True
    fine_drift_scale_sigma: float = 0.02
    fine_drift_bend_deg_per_m: float = 0.04
    # ... as ceilings: the priors' σ fitted to the fleet's own drift, one EM update per round (empirical Bayes,
    # fusion.drift_fit.fit_prior), so submaps that carry no drift keep almost none (with the fixed priors exact
    # submaps took 0.1-0.2 % of scale and lost pose; on by default since: camera 0 geo F 0.772 -> 0.799, pose
    # 0.469 -> 0.417 m, exact 0 0.984 -> 0.984, 0.083 -> 0.095 m; docs/METHOD_LOG.md, "The drift prior fitted to
    # the fleet"). Needs this many free submaps with a drift step, else the ceilings hold
    fine_drift_prior_fit: bool = True
    fine_drift_prior_min_submaps: int = 8
    fine_rounds: int = 8  # correspondence rounds, radius shrinking geometrically ...
    fine_max_dist_m: float = 2.0  # ... from this ...
    fine_basin_sigmas: float = 1.25  # ... or this × the submaps' median GPS σ where wider (fusion.match_weights.match_radii)
    # ... to this, ...
    fine_min_dist_m: float = 0.25
    # ... but not narrower than this × the robust spread of the other sessions' wall residuals after the previous
    # round, up to fine_polish_max_m (fusion.match_weights.spread_floor; 0: off): the first round so raised is the last.
    # A monocular camera's walls disagree between sessions by decimetres along the viewing rays, and a last round at
    # 0.25 m (Cauchy σ 0.125 m; a match needs a sample of the other surface that near, samples ~0.5 m apart) kept
    # mostly the patches that happened to agree, fitting each submap to them; exact surfaces, cm apart, register
    # best there. Registration alone, camera seeds 3/0/1/2, surface offset horizontal / height m, last radius
    # 0.25 -> 0.75 m: 0.380/0.146 -> 0.367/0.109, 0.455/0.162 -> 0.386/0.127, 0.220/0.132 -> 0.231/0.130,
    # 0.349/0.150 -> 0.328/0.122; exact seed 0 pose 0.111 -> 0.156 m (docs/METHOD_LOG.md, "The finest radius",
    # "The finest radius from the data")
    fine_spread_radius: float = 5.0
    fine_normal_dot: float = 0.7  # a match's normals must agree this well
    fine_weight: float = 20.0  # each submap's matches count as this many observations (σ units) ...
    # ... × (σ / the residuals' robust spread)², up to this (fusion.match_weights.noise_gain; 1: off). Start poses,
    # 3x3 bench seeds 0/1/2, GPS 1.5 m (with fine_same_session): exact 0.175/0.174/0.126 -> 0.071/0.044/0.049 m
    fine_noise_max_gain: float = 20.0
    fine_noise_floor_m: float = 0.02
    # the gain on ground-like matches too. Off: a monocular road surface is biased in height by the submap's
    # scale error (camera 1.6 m above it) while its residuals stay tight, and on it the camera starts' height
    # error grew 0.150 -> 0.235 m (seed 0); exact 0.071 -> 0.092 m with it off
    fine_noise_ground: bool = False
    # after the field alignment, the fine registration once more over this many rounds from fine_polish_max_m
    # (fusion.align._polish; 0: off): the field's stochastic pose steps took the exact map from 0.07 m back to
    # 0.195 m (seed 0); polished 0.073 m
    fine_polish_rounds: int = 3
    fine_polish_max_m: float = 0.75
    # the polish's matches count fine_weight × the first registration's data gain in its last round (the mean of
    # the per-match gains of fine_noise_max_gain: how much tighter than the radius' scale the matches agreed), up to
    # this × (1: as the first registration). The polish starts within decimetres of the optimum, where matches
    # on exact surfaces (gain ~4) are true ones and may outweigh the odometry and GPS priors that bent the map a
    # few cm per submap link; monocular matches (gain ~1) carry depth error along each viewing ray, which more
    # weight would let bend the map instead, so they keep the registration's weight. The 3x3 bench's field
    # alignment poses polished with weight 20 / 40 / 80: exact 0 0.105 / 0.089 / 0.083 m, exact 1 0.073 / 0.045 /
    # 0.041 m, camera 0 0.481 / 0.411 / 0.353 m, camera 1 0.286 / 0.282 / 0.297 m, camera 2 0.315 / 0.341 / 0.362 m
    # (docs/METHOD_LOG.md, "The polish trusts tight matches more"). An alignment without field steps (an addition,
    # a re-alignment) is polished too where this weight exceeds fine_weight: registration alone from GPS, exact
    # seeds 0 / 1 / 2 0.094 / 0.053 / 0.071 -> 0.085 / 0.042 / 0.064 m ("Additions polished too")
    fine_polish_gain_max: float = 4.0
    # accepted steps per round at most (lbfgs: iterations). Odometry makes the problem stiff (cm between
    # neighbours): L-BFGS, 3x3 bench seed 0, exact / camera start: 30 steps 0.489 / 0.917 m, 150 0.169 / 0.584 m,
    # 400 0.155 / 0.553 m; exact with fine_weight 400 and same-session matches 150 0.168 m, 600 0.084 m (165 s). gn:
    # Levenberg-Marquardt on the normal equations (fusion.register._gauss_newton), 5-15 steps per round: 0.071 m
    # in 15 s
    fine_steps: int = 150
    # ... and a round stops once a step moved no point of any free submap farther than this (m; 0: only when the
    # objective stops falling, by 1e-9 of itself): the next round matches again from wherever this one ends, and
    # the last steps of a round moved submaps by µm (3x3 exact bench, seed 1, a re-alignment: rounds of 4-8
    # steps, whose last 2-4 each moved every submap < 0.1 mm)
    fine_converged_m: float = 1e-4
    fine_solver: str = "gn"
    pose_warmup: int = 10  # iterations with frozen poses so the field first takes a rough shape
    surface_samples: int = 4096
    space_samples: int = 4096
    normal_fraction: float = 0.25  # fraction of samples with numerical normals / eikonal
    normal_eps_cells: float = 1.0  # central-difference step in cells of the finest active level
    # progressive level of detail
    lod_start_levels: int = 3  # coarse start (~2 m cells) widens the pose basin: 6 let sessions ~1 m apart fit as two surfaces
    lod_full_fraction: float = 0.6  # all levels active after this fraction of the iterations
    # region alignment (fusion.align): one pose per submap across the region's tiles. The one-tile bench
    # (seed 0) put poses at 0.275 m / 0.38° with a cap of 8 levels and 150 steps per tile, and at
    # 0.085 m / 0.16° (the old joint per-tile fusion: 0.086 m / 0.17°) with every level and 300 steps:
    # the last ~0.2 m come from the finest levels, so the alignment runs the reconstruction's schedule.
    align_iterations_per_tile: int = 300  # alignment steps = this × the region's content in full tiles (below)
    # while the finest active level's cells are coarser than this, the alignment moves poses only in x, y and
    # yaw (0: never). The coarse levels smooth road, kerb and walls into one blob: their pull on height and
    # tilt depends on what each submap saw, and on forward-camera submaps (strips of road ahead, facades seen
    # obliquely) it bent the sessions' chains apart in height (3x3 camera bench, seed 0: height RMS 0.26 m at
    # the start, 0.35 m after the alignment; 0.19 m with this hold, i.e. until 8 of the cpu preset's 12 levels)
    align_planar_cell_m: float = 0.6
    align_max_levels: int = 16  # LOD cap while aligning (capped at num_levels): every level by default
    # all levels active after this fraction of the alignment's steps (reconstruction: lod_full_fraction). With
    # lr_pose_trans 0.1 (was 3e-2 with 0.6): the coarse, wide-basin phase is longer and moves 2-3 m GPS errors
    # there. Alignment only, 2x2 camera world, 3 sessions, default steps, pose RMSE seeds 0/1/2: 0.589/0.248/1.244
    # -> 0.435/0.226/1.176 m; exact seed 0 0.175 -> 0.173 m
    align_lod_full_fraction: float = 0.8
    # reconstruction from the region alignment's field of the tile (trained on the same data; the poses
    # have moved little since): this fraction of a cold start's steps, every level at once (0: cold start).
    # 2x2 bench, 3 sessions, same data, cold -> warm (geo F / sem F / recon s per tile): camera seeds 0/1/2
    # 0.908/0.381/20 -> 0.916/0.415/11, 0.801/0.413/24 -> 0.800/0.432/12, 0.758/0.233/21 -> 0.774/0.246/12;
    # exact seed 0 0.963/0.726/24 -> 0.966/0.772/12 (transient 43 -> 6 %)
    recon_warm_fraction: float = 1 / 3
    # a re-fusion of a tile from its previous reconstruction's field (the held submaps at the poses it was
    # trained at; a new session's submaps added by an incremental alignment): this fraction of a cold start's
    # steps, every level at once (0: from the alignment's field as above). Fewer steps lost the new session's
    # surface and the consensus' changes (a fresh Adam's first steps jolt a trained field; at the true poses,
    # exact seed 1, tile 1_0 geo / sem F: 1/3 0.994 / 0.928, 1/6 0.987 / 0.861, 1/12 0.962 / 0.758, the
    # four-session map 0.962 / 0.838; a lower field rate could not build the new surface). docs/METHOD_LOG.md, "Adding a
    # session ... from the tile's own field".
    refusion_warm_fraction: float = 1 / 3
    # a tile is fused again for a new submap only where the submap's surface, at its aligned pose, comes
    # within this of the tile's square (``fusion.tiles.surface_tiles``; the service's reconstruction
    # fingerprint, the bench's add_session): a submap whose GPS uncertainty or bounding box reaches the
    # tile but whose faces stay farther out only shapes the field in the margin, which the mesh is not cut
    # from (the border is pinned by the neighbour it lies in). Exact seed 1, fifth session: 7 tiles touched
    # by GPS box, 4 by surface within 2 m (the others 0, 0 and 765 vertices within 8 m)
    refusion_band_m: float = 2.0
    # an incremental alignment with tracking steps (align_incremental_iterations_per_tile > 0; none by default)
    # tracks new submaps against each tile's last reconstruction field where it has
    # one (trained on every submap held so far, the full schedule) rather than its alignment field (the
    # sessions of the tile's first alignment, a short schedule); false: always the alignment field
    align_track_reconstruction: bool = True
    # an alignment that adds sessions to a region re-aligns the region jointly instead (every submap free,
    # from its refined pose; every tile reconstructed from the new alignment's field) once at least this
    # share of the region's sessions, the arriving one included, were aligned incrementally: an incremental
    # alignment never moves the held map, so a map grown session by session keeps the poses of the few
    # sessions it was first aligned from (exact seed 1, three sessions then two added: pose RMSE 0.159 m,
    # sem F 0.66, against 0.091 m / 0.79 aligned jointly). The share makes the re-alignments geometric (the
    # jointly aligned part grows by 1 / (1 - share) each time): a third re-aligns a five-session map at its
    # second added session, not at its first. > 1: never (``fusion.regions.needs_realignment``)
    realign_share: float = 1 / 3
    # a joint re-alignment starts from refined poses: this fraction of ``align_iterations_per_tile`` (the
    # registration stages do the same work either way). 0 (default since 2026-12-05, twenty-fifth session):
    # registration alone, no field trained, every tile re-fused from its own last reconstruction. add_sessions,
    # map after the fifth session's re-alignment (geo F / sem F / pose m) against the joint fusion of the same
    # data: exact 0 0.983 / 0.825 / 0.094 vs 0.985 / 0.812 / 0.104, exact 1 0.981 / 0.761 / 0.053 vs 0.982 /
    # 0.771 / 0.072, camera 1 0.910 / 0.436 / 0.287 vs 0.918 / 0.428 / 0.284, camera 0 0.780 / 0.355 / 0.495 vs
    # 0.776 / 0.375 / 0.481; the re-alignment 32-44 % of a full fusion instead of 60-68 % with half the steps
    # (0.5, the default before: exact 1 0.980 / 0.787 / 0.091, camera 1 0.901 / 0.390 / 0.282). docs/METHOD_LOG.md,
    # "Additions by registration alone". In the twentieth session the same setting lost exact 0 sem F 0.054.
    realign_iterations_fraction: float = 0.0
    # a re-alignment by registration alone (no field trained) holds the map where it stood: its poses move
    # rigidly, all together, so that the submaps held before stand where they stood in least squares
    # (``fusion.placement``; not where a held submap reaching outside the region pins the map already). Off:
    # the data fix the submaps relative to each other, the GPS prior the whole map's place, and a re-alignment
    # with more sessions places it better; held, the placement freezes at the first alignment's estimate.
    # Add_sessions, the fifth session re-aligning (thirty-second session; geo F / sem F / abs geo F / tiles
    # re-fused): exact 1 off 0.984 / 0.766 / 0.971 / 8, on 0.984 / 0.759 / 0.582 / 5 (0.05 m); exact 0 off 0.982
    # / 0.817 / 0.739 / 8, on 0.981 / 0.816 / 0.709 / 8; camera 0 off 0.784 / 0.349 / 0.751 / 8, on 0.782 / 0.352
    # / 0.662 / 8 (the re-alignment reshapes those maps by 0.05-0.58 m per tile). docs/METHOD_LOG.md
    realign_hold: bool = False
    # a re-alignment by registration alone keeps a tile's mesh where no new submap comes within
    # ``refusion_band_m`` of it and no surface near it moved by this much or more (m; 0: every tile
    # reconstructed again): with the hold off, where submaps reaching outside the region pin the map. 0.05: a fifth of the
    # extraction voxel, a quarter of the evaluation's 0.2 m; keep 0.05 vs 0 with the hold on, exact 1: sem F
    # 0.759 vs 0.761, geo F 0.984 vs 0.985, the re-aligning addition 78 vs 91 s
    realign_keep_m: float = 0.05
    # a re-alignment by registration alone moves each tile's surface by decimetres (mostly the map's
    # placement: ``realign_hold``) and reshapes it by centimetres; on: the tile's re-fusion starts from its last
    # field carried by the tile's rigid motion (``fusion.placement.tile_carry``, ``fusion.field.moved_state``),
    # centimetres from its surface instead of decimetres; off: from the field where it was trained. Alone (the
    # default 1/3 of the steps) within run-to-run spread (add_sessions, the re-aligned map, geo F / sem F /
    # single-session objects, off → on: exact 0 0.978 / 0.813 / 3.0 % → 0.982 / 0.820 / 3.0 %, exact 1 0.983 / 0.773
    # / 11.7 % → 0.984 / 0.758 / 4.2 %, camera 0 0.781 / 0.362 / 0.9 % → 0.779 / 0.351 / 3.9 %); what it buys is the
    # fewer steps below: uncarried, an eighth of the steps lost exact 0 0.024 sem F and let 16 % of the
    # single-session objects back, carried 0.819 / 6.8 %. docs/METHOD_LOG.md, thirty-third and thirty-fourth sessions
    refusion_carry: bool = True
    # a re-fusion from a carried field (``refusion_carry``) of a tile no new submap reaches (its surface only
    # moved, by centimetres after the carry): this fraction of a cold start's steps instead of
    # ``refusion_warm_fraction`` (``WarmKind`` "carried"; in the service ``Tile.recon_field_carried``); a tile a
    # new submap reaches keeps that, the new surface has to be built. The re-aligning addition, 1/3 → 1/6 on 3-4
    # of 8 tiles: exact 0 66-69 → 62 s (32 % of the same run's full fusion), exact 1 72-76 → 66 s (40 %), camera 0
    # 54-55 → 40 s (33 %), camera 1 46 s (32 %); the re-aligned map's figures within run-to-run spread
    refusion_carried_fraction: float = 1 / 6
    # the same × the new submaps' content, fields frozen (steps are cheap: no field gradients). 0 (default since
    # the twenty-fifth session): the new submaps placed by the registrations alone (the held submaps fixed), no
    # frozen field tracked; a tile new to the map then starts cold. add_sessions, fourth session added, 240 -> 0
    # (alignment s; map after the fifth): exact 1 45 -> 12 s (0.981 / 0.756 / 0.053 -> 0.981 / 0.761 / 0.053),
    # camera 1 29 -> 8 s (0.903 / 0.431 / 0.288 -> 0.910 / 0.436 / 0.287), camera 0 23 -> 6 s (0.776 / 0.359 /
    # 0.495 -> 0.780 / 0.355 / 0.495). Before the fine registration, 2x2 bench, 3 sessions, camera seeds 0/1:
    # 60/tile 0.280/0.334 m, 240/tile 0.171/0.243 m
    align_incremental_iterations_per_tile: int = 0
    # incremental tracking: a new submap's samples track a frozen tile only within this of the held submaps' surface
    # (at the starting poses: ~2 GPS sigma); elsewhere the frozen field holds no data (0: every sample)
    align_track_support_m: float = 3.0
    # content-proportional schedule (fusion.schedule): a tile's steps, and its part of a region's alignment
    # steps, scale with the surface it holds (a tile grazed by one submap needs few steps for the same
    # samples per m²); full once the surface, counted in voxels so overlapping sessions count once,
    # reaches schedule_full_cover × the tile box's ground area (bench tile (0, 0): 1.9×), at least
    # schedule_min_fraction of one tile's steps: a grazed tile of the bench's world (3 sessions, 10 %
    # content) had 49 k faces after 300 steps, 98 k after 100, 171 k after 60 and 705 k after 30 (an
    # untrained field is confident everywhere); geo F 0.06 after 300 steps, 0.11 after 100 (low either way)
    schedule_voxel_m: float = 2.0  # ~GPS σ: sessions not aligned yet count once (1 m: the demo's tiles 0.57-0.88 on GPS poses, 0.44-0.63 aligned; 2 m: 0.46-0.79, 0.43-0.66)
    schedule_full_cover: float = 1.0
    schedule_min_fraction: float = 1 / 3
    # confidence
    c_th: float = 0.7
    consensus: bool = True
    consensus_radius_m: float = 0.5  # a session "saw" a surface point if it has one within this
    consensus_cover_m: float = 2.5  # ... and "saw its neighbourhood" if it has one within this ("cover")
    # which sessions count against a surface they did not see: "cover" every session with a point within
    # consensus_cover_m; "free_space" only one that saw through it (the first surface it has below, within
    # consensus_column_m, faces up: bare road where a parked car stood), not one that looked elsewhere.
    # cover -> free_space (2026-12-02, 2x2 tiles, 3 sessions, same data; geo F / sem F / transient): camera seeds
    # 0/1/2 0.847/0.372/9.6 % -> 0.912/0.400/5.1 %, 0.795/0.407/20.2 % -> 0.816/0.419/23.5 %, 0.738/0.234/26.2 %
    # -> 0.764/0.236/31.2 %; exact seed 0 0.933/0.708/36.6 % -> 0.962/0.733/35.5 % (consensus off: 0.963/0.723/53.2 %)
    consensus_evidence: str = "free_space"
    consensus_column_m: float = 3.0
    # free-space evidence ignores a surface whose own session saw open ground this far beneath it (0: off):
    # sign plates and tree crowns, under which the other sessions' rays passed (fusion.sampling._overhangs).
    # Off: the simulated worlds do not have the case (targets unchanged on 4 traced tiles; 3x3 bench, 1 m, exact
    # seeds 0/1 and camera 1: geo F / sem F within run-to-run noise; docs/METHOD_LOG.md, "The default ... in the same run")
    consensus_overhang_m: float = 0.0
    # consensus fraction mapped to c_th (kept from here up): 2 of 3 and 3 of 5 observing sessions keep a surface
    # (the raw fraction dropped both), 1 of 2, 1 of 3 and 2 of 5 do not. With 2 sessions a surface one of them
    # missed (a hole, its field of view's edge) cannot be told from a parked car the other saw: dropped. 2x2
    # camera bench, 3 sessions, seed 0: raw geo F 0.767 / transient 0.053, 0.4: 0.791 / 0.16, 0.55: 0.795 / 0.06
    consensus_keep: float = 0.55
    # consensus off (2026-12-02, same bench, seeds 0/1/2): geo F 0.852/0.774/0.745 -> 0.922/0.806/0.755, transient
    # 2.5/22.2/27.8 % -> 6.2/20.9/36.2 %; the exact fleet not measured without it yet (docs/METHOD_LOG.md, ablation)
    # movable classes need a second witness (``fusion.sampling.consensus_targets``): kept only where at least
    # this many sessions saw them, once the tile holds that many sessions (0 or 1: off). Free-space evidence
    # cannot drop a car parked where one session drove: no other session saw through it (docs/METHOD_LOG.md, "Camera fleets")
    # A witness is any surface within consensus_radius_m; counting only another session's movable surface within
    # 1 m (2026-12-03, camera seeds 0/1/2) kept no more vehicles (F 0.15/0.06/0.00 vs 0.13/0.06/0.00): the cars
    # lost are those one session alone saw, not ones the sessions' depth errors put apart. Removed again.
    # Counting only another session's movable surface within consensus_radius_m (so the road under a lone car's
    # lower body is no witness; 2026-12-04, true poses, share of vehicle pool points kept, static / transient):
    # exact 1 0.54/0.40 -> 0.31/0.16, exact 0 0.77/0.05 -> 0.61/0.02: parked cars' flanks seen from different
    # sides lose their witnesses as fast as transients. Removed again.
    consensus_movable_sessions: int = 2
    # ... asked only where that many sessions were there (any surface within this, m; 0: wherever the tile holds
    # that many sessions): a car parked on a street one session alone drove is kept, nothing says it was gone
    consensus_movable_cover_m: float = 0.0
    # ... and a witness of a movable point lies at most this far below it (m; within consensus_radius_m above
    # and to the sides): the road another session saw under a car one session saw is evidence against the car
    # (that session saw through it), not a witness of its lower body (fusion.sampling.consensus_targets;
    # >= consensus_radius_m: the plain cube). At the true poses, share of movable pool points kept (static /
    # transient), 0.5 -> 0.25: exact 1 0.724/0.251 -> 0.724/0.029, exact 0 0.749/0.023 -> 0.748/0.003, camera 0
    # 0.509/0.018 -> 0.501/0.001, camera 1 0.594/0.021 -> 0.591/0.000. 3x3 bench, same data (geo F / sem F /
    # transient): exact 1 0.985/0.778/13.5 % -> 0.985/0.789/3.9 %, exact 0 0.985/0.828/1.7 % -> 0.985/0.821/1.4 %,
    # camera 0 0.775/0.357/0.8 % -> 0.775/0.375/1.3 %, camera 1 0.924/0.426/0.3 % both (docs/METHOD_LOG.md,
    # "The road beneath a car is no witness")
    consensus_movable_below_m: float = 0.25
    consensus_movable: tuple[str, ...] = ("vehicle", "obstacle")
    # minimum thickness (reconstruction only): surface samples of thin upright classes sit this far out along
    # their normal, so a pole, sign plate or fence thinner than ~2 of the finest cells keeps a negative
    # interior the field and the extraction lattice can hold, instead of vanishing (0: off). 3x3 bench, 0 -> 0.1
    # (geo F / sem F): exact seeds 0/1/2 0.975/0.737 -> 0.980/0.759, 0.974/0.712 -> 0.977/0.711, 0.972/0.713 ->
    # 0.973/0.731; camera seeds 0/1 0.811/0.355 -> 0.815/0.375, 0.899/0.398 -> 0.899/0.411 (poses unchanged).
    # 0.15 since the faces move back in (below): a 0.05 m sign plate then spans 0.35 m, two of the cpu preset's
    # 0.156 m finest cells; at the true poses, sem F exact 0/1/2 0.809/0.747/0.795 -> 0.840/0.760/0.798, camera 1
    # 0.413 -> 0.420 (docs/METHOD_LOG.md, "Thin structures")
    thin_inflate_m: float = 0.15
    thin_classes: tuple[str, ...] = ("pole", "traffic_sign", "fence")
    # ... and the extracted faces of those classes move back in by thin_inflate_m (fusion.extract.deflate_faces):
    # the field held the inflated surface, the map reports the one the uploads saw. The same fields at the true
    # poses extracted both ways (3x3, inflation 0.1): exact sem F seeds 0/1/2 0.793/0.729/0.772 -> 0.809/0.747/0.795
    # (poles +0.07 to +0.09, fences +0.07), camera seed 1 0.412 -> 0.413
    thin_deflate: bool = True
    # fractions of training at which targets are recomputed from the moving poses (1 before the first); a
    # reconstruction holds every pose, so its targets are computed once, at the first (fusion.reconstruct._train)
    consensus_at: tuple[float, ...] = (0.4, 0.7)
    pool_points: int = 300_000  # surface points pre-sampled per tile (area-weighted)
    class_balance: float = 0.5  # pool faces weighted by area × (mean class share / class share)^this
    class_weight_max: float = 4.0  # ... clipped to [1, this] (1: plain area weighting)
    # tile geometry and extraction
    tile_margin_m: float = 8.0
    slab_pad_m: float = 2.0  # height slab = data z-range ± this
    slab_max_m: float = 40.0
    extract_voxel_m: float = 0.25
    extract_block: int = 4  # coarse narrow-band block, in voxels (halved down to 2: fusion.band.narrow_band_sdf)
    extract_band: float = 0.75  # refine blocks with a corner |s| below this × block diagonal (or a sign change)
    extract_chunk: int = 65536
    # confidence 0 farther than this from every posed input point (0: off); the narrow band also leaves out the
    # blocks farther than this (+ a cube diagonal) from them, where the untrained field sits near zero
    extract_support_m: float = 1.0
    # upload faces farther than this from the field's extracted surface, where the field is confident, join the
    # tile's mesh as measured (0: off; fusion.extract.add_detail): poles, signs and small obstacles the field
    # cannot hold (one-sided, smeared by depth error, mislabelled so not inflated) keep the uploads' surface.
    # Only faces the cross-session consensus kept are offered (fusion.reconstruct._posed_uploads): the field's
    # confidence alone let single-session cars in beside another session's car in the same slot
    detail_m: float = 0.4
    # "centroid": semantic head at each face's centroid; "vertices": majority of the vertex labels; "vote": the
    # majority label of the posed input points within 0.3 m of the centroid (head's label where none): 2x2
    # camera bench, seeds 0/1/2, sem F 0.367/0.388/0.232 (centroid) -> 0.396/0.408/0.226 (vote), traffic signs
    # 0.00 -> 0.32/0.13 on seeds 0/1; within run-to-run noise (geo F moves ±0.02 between runs) on the mean, so
    # not the default yet
    face_labels: str = "centroid"
    # faces on a class boundary (vertex and centroid labels disagree) split in four, each quarter labelled at its
    # centroid (``fusion.extract.split_label_boundaries``): class edges and lane markings at half the voxel. 3x3
    # bench at the true poses, the same fields extracted both ways: exact seed 1 sem F 0.757 -> 0.762 (marking,
    # fence, pole, sign +0.01-0.02), camera seed 1 0.421 -> 0.418; faces +16 % / +28 %. Off: not worth the faces
    face_label_split: bool = False
    # a face whose label contradicts its geometry takes the head's best label that does not
    # (``fusion.extract.relabel_by_geometry``): a ground class on a steep face raised above the ground beside
    # it (a pole or sign the segmenter missed and took for the pavement, a class bled up a wall's foot or a
    # car's flank), any other class on level ground at ground height (bled onto the pavement around the
    # object). Kept fields relabelled offline (3x3, seed's default -> on, sem F): camera 0 0.398 -> 0.430,
    # camera 1 0.407 -> 0.439, camera 3 0.336 -> 0.352, exact 0 0.814 -> 0.860 (docs/METHOD_LOG.md, "Labels
    # that contradict the geometry")
    label_geometry: bool = True
    ground_classes: tuple[str, ...] = ("road", "sidewalk", "lane_marking", "terrain")
    # run
    seed: int = 0
    device: str = "auto"  # "auto" → CUDA when available, else CPU

    def __post_init__(self) -> None:
        if self.grid_type not in GRID_TYPES:
            raise ValueError(f"grid_type must be one of {GRID_TYPES}, got {self.grid_type!r}")
        if self.consensus_evidence not in CONSENSUS_EVIDENCE:
            raise ValueError(f"consensus_evidence must be one of {CONSENSUS_EVIDENCE}, got {self.consensus_evidence!r}")
        if self.fine_solver not in FINE_SOLVERS:
            raise ValueError(f"fine_solver must be one of {FINE_SOLVERS}, got {self.fine_solver!r}")
        if self.consensus_movable_cover_m < 0:
            raise ValueError(f"consensus_movable_cover_m must be >= 0 (0: off), got {self.consensus_movable_cover_m}")
        if self.consensus_movable_below_m < 0:
            raise ValueError(f"consensus_movable_below_m must be >= 0, got {self.consensus_movable_below_m}")
        if self.consensus_overhang_m < 0:
            raise ValueError(f"consensus_overhang_m must be >= 0 (0: off), got {self.consensus_overhang_m}")
        if self.thin_inflate_m < 0:
            raise ValueError(f"thin_inflate_m must be >= 0 (0: off), got {self.thin_inflate_m}")
        if not self.realign_share > 0:
            raise ValueError(f"realign_share must be > 0 (> 1: never), got {self.realign_share}")
        if self.fine_same_session and self.fine_own_overlap:
            raise ValueError("fine_same_session and fine_own_overlap both match a session's own submaps: "
                             "set fine_own_overlap=false to use fine_same_session")
        if self.fine_drift and self.fine_solver != "gn":
            raise ValueError("fine_drift needs fine_solver=gn (the drift is solved with the normal equations)")
        if self.fine_drift and not (self.fine_drift_scale_sigma > 0 and self.fine_drift_bend_deg_per_m > 0):
            raise ValueError("fine_drift_scale_sigma and fine_drift_bend_deg_per_m must be > 0")
        if self.fine_drift_prior_min_submaps < 1:
            raise ValueError(f"fine_drift_prior_min_submaps must be >= 1, got {self.fine_drift_prior_min_submaps}")
        if self.detail_m < 0:
            raise ValueError(f"detail_m must be >= 0 (0: off), got {self.detail_m}")
        if not 0 <= self.realign_keep_m < math.inf:
            raise ValueError(f"realign_keep_m must be a finite number of metres >= 0, got {self.realign_keep_m}")
        for fraction in ("realign_iterations_fraction", "recon_warm_fraction", "refusion_warm_fraction",
                         "refusion_carried_fraction"):
            if not 0 <= getattr(self, fraction) <= 1:
                raise ValueError(f"{fraction} must be in [0, 1], got {getattr(self, fraction)}")
        if self.fine_polish_gain_max < 1:
            raise ValueError(f"fine_polish_gain_max must be >= 1 (1: the registration's weight), got "
                             f"{self.fine_polish_gain_max}")
        if not self.fine_spread_radius >= 0:
            raise ValueError(f"fine_spread_radius must be >= 0 (0: off), got {self.fine_spread_radius}")
        if not self.fine_own_trust_m > 0:
            raise ValueError(f"fine_own_trust_m must be > 0 (m), got {self.fine_own_trust_m}")
        if self.fine_converged_m < 0:
            raise ValueError(f"fine_converged_m must be >= 0, got {self.fine_converged_m}")
        if self.align_iterations_per_tile < 0:
            raise ValueError(f"align_iterations_per_tile must be >= 0 (0: registration only), "
                             f"got {self.align_iterations_per_tile}")
        if self.align_incremental_iterations_per_tile < 0:
            raise ValueError(f"align_incremental_iterations_per_tile must be >= 0 (0: registration only), "
                             f"got {self.align_incremental_iterations_per_tile}")
        if not self.refusion_band_m >= 0:
            raise ValueError(f"refusion_band_m must be >= 0, got {self.refusion_band_m}")
        for option in ("consensus_movable", "thin_classes", "ground_classes"):
            unknown = [name for name in getattr(self, option) if name not in LABEL_BY_NAME]
            if unknown:
                raise ValueError(f"{option} names unknown labels: {', '.join(unknown)}")
        if self.lod_start_levels > self.num_levels:
            raise ValueError("lod_start_levels must not exceed num_levels")

    def thin_label_ids(self) -> list[int]:
        """Label ids of ``thin_classes``."""
        return [LABEL_BY_NAME[name].id for name in self.thin_classes]

    def ground_label_ids(self) -> list[int]:
        """Label ids of ``ground_classes``."""
        return [LABEL_BY_NAME[name].id for name in self.ground_classes]

    def movable_label_ids(self) -> list[int]:
        """Label ids of ``consensus_movable``."""
        return [LABEL_BY_NAME[name].id for name in self.consensus_movable]

    @staticmethod
    def preset(name: str = "cpu") -> FusionConfig:
        """``"cpu"``: 64 m tiles on 2 CPU cores in about a minute; ``"paper"``: the paper's sizes (GPU);
        ``"tiny"``: a few iterations and a coarse lattice, for tests and smoke runs (seconds on 2 cores)."""
        if name == "cpu":
            return FusionConfig()
        # the presets are declarative tables of overrides; their similar shapes are deliberate (duplicates)
        if name == "tiny":
            return FusionConfig(
                iterations=25,
                pose_warmup=5,
                surface_samples=512,
                space_samples=512,
                num_levels=6,
                lod_start_levels=4,
                log2_table_size=14,
                max_resolution=64,
                geo_hidden=32,
                sem_hidden=32,
                pool_points=20_000,
                consensus=False,
                c_th=0.5,  # a few iterations leave confidences lower than a full schedule does
                extract_voxel_m=1.0,
                extract_support_m=2.0,  # two of its 1 m voxels
                detail_m=1.5,  # a voxel and a half, as 0.4 m is of the cpu preset's 0.25 m
                tile_margin_m=2.0,
                align_iterations_per_tile=10,
                # its alignment's 10 steps per tile leave too rough a field to start from: a warm third of
                # the steps gave the add_session test's map geo F 0.30
                recon_warm_fraction=0.0,
                align_planar_cell_m=0.0,  # its finest cells are ~1 m: the poses would never leave the plane
                fine_steps=30,
            )
        if name == "paper":
            return FusionConfig(
                num_levels=16,
                features_per_level=2,
                log2_table_size=16,
                base_resolution=16,
                max_resolution=2048,
                geo_hidden=128,
                sem_hidden=128,
                iterations=500,
                surface_samples=125_000,
                space_samples=125_000,
                normal_fraction=0.1,
                lod_start_levels=5,  # ~2.5 m cells on a 128 m tile, as the cpu preset's 3 on 64 m
                pool_points=2_000_000,
                extract_voxel_m=0.2,  # the paper's evaluation distance d; 0.1 m: 8x the lattice, 4x the faces
                extract_block=4,
                extract_chunk=262_144,
            )
        raise ValueError(f"unknown preset {name!r} ({', '.join(PRESETS)})")

    def with_overrides(self, items: list[str]) -> FusionConfig:
        """This config with ``KEY=VALUE`` overrides (the bench's ``--set``), each value parsed as the
        field's type; raises ``ValueError`` naming an unknown key or a value that does not parse."""
        return with_overrides(self, items)

    def with_(self, **changes: Any) -> FusionConfig:
        return replace(self, **changes)

    def for_realignment(self) -> FusionConfig:
        """The config of a joint re-alignment (``realign_share``): ``realign_iterations_fraction`` of the
        alignment steps, the poses starting where earlier alignments left them."""
        fraction = self.realign_iterations_fraction
        steps = max(1, round(self.align_iterations_per_tile * fraction)) if fraction > 0 else 0
        return self.with_(align_iterations_per_tile=steps)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> FusionConfig:
        """Inverse of ``to_dict``; unknown keys are rejected so typos do not pass silently."""
        known = {f.name for f in fields(FusionConfig)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown FusionConfig keys: {sorted(unknown)}")
        data = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return FusionConfig(**data)

