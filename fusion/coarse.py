"""Coarse registration of whole sessions before the field alignment: a wide pose basin.

Why: the field alignment is a local method. Its coarsest level (~2 m cells) pulls sessions together
from errors of about 1.5-2 m / 2°; from GPS σ of 3-4 m / 3-4° a session's odometry chain, placed on its
GPS fixes (``odometry_consistent_start``), can start several metres and degrees from the others, and
the field then learns two surfaces instead of moving the poses.

What: every session is one rigid body here (its odometry chain is already consistent: on the bench
the chains placed on GPS are off by a per-session rigid error, within-session residuals ≤ 0.15 m), moved
by a yaw about its centroid and a 3-D shift. Each free session is matched against the surfaces of
the *other* sessions by an exhaustive correlative search (as in 2-D scan matching): the reference
surface samples are splatted into a voxel grid per match group of labels (road and marking, sidewalk,
terrain and vegetation, building and fence, pole and sign, vehicle and obstacle: classes a segmenter
confuses share one), blurred and saturated (a soft occupancy in [0, 1]); a candidate's score is the
weighted mean occupancy of its own group at the session's moved samples. Vertical surfaces (walls,
poles, kerbs) weigh more than ground, which fixes only height and tilt. Two stages: ``coarse_voxel_m``
voxels over ±``coarse_range_sigmas`` σ of the session's placement, then half-size voxels (trilinear)
around the first's pick.

- Range: a chain placed on n independent GPS fixes of σ is about σ/√n off, and that is the search's σ.
  Searching ±3 σ of one fix instead (σ 4 m: ±12 m, ~10⁵ candidates) found peaks metres from the truth
  that beat the chance bar on a 3×3-tile world of 5 sessions: with the other sessions at their *true*
  poses the truth scored 0.17 and a candidate 17 m away 0.24 (camera, seed 0). Before the field, GPS
  4 m / 4°, exact seeds 0-2 / camera seeds 0-1: 2.28 / 1.02 / 0.31 / 4.93 / 3.50 m with ±3 σ of a fix,
  0.24 / 0.22 / 0.17 / 1.68 / 1.09 m with ±3 σ/√n (each with the σ-wide fine stage, ``fusion.register``).

- Significance: a correction is kept only if the best score beats the start's by more than chance
  reaches among that many candidates (from the samples' effective count) and ``coarse_min_gain``.
  Sessions that barely overlap, or data that do not decide (camera submaps with little overlap:
  most sessions on the camera bench), keep the start.
- Ambiguity: along a straight, featureless road many shifts score alike. Of the candidates within
  ``coarse_tie`` of the best, the one that moves the session least wins: the start keeps the
  direction the data leave open.
- Order: the first round grows the map from an anchor (the sessions holding fixed submaps, else the
  largest session), adding the session that overlaps the registered ones most; the second round
  re-registers the anchor and every session the first round moved against all the others (fine
  stage only).
- Gauge: with no fixed submap, the mean correction (yaw and centroid shift, weighted by submap count)
  is taken back out, so the map keeps the GPS fixes' average placement, as the GPS prior wants.

Torch on CPU or GPU; no Open3D. A whole-voxel shift is a constant offset of the flat grid index, so the
search's inner loop is one gather per candidate and sample (~10⁸ per session on the first stage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from fusion.config import FusionConfig
from fusion.sampling import face_geometry, on_triangles, uniform_barycentric
from fusion.types import SubmapInput

_CHUNK = 1 << 23  # grid lookups per batch
# a sample matches only surfaces of its own group: classes a camera segmenter confuses share one, and a
# road is not matched onto a wall. Labels beyond the table (deployments may append) share the last group.
_GROUPS = {0: -1, 1: 0, 3: 0, 2: 1, 4: 2, 9: 2, 5: 3, 6: 3, 7: 4, 8: 4, 10: 5, 11: 5}
_NUM_GROUPS = 7


def label_groups(labels: np.ndarray) -> np.ndarray:
    """Match group per label id (-1: unlabeled, not matched)."""
    table = np.full(max(int(labels.max(initial=0)) + 1, len(_GROUPS)), _NUM_GROUPS - 1)
    for label, group in _GROUPS.items():
        table[label] = group
    return table[labels]


@dataclass
class _Session:
    members: list[int]  # indices into the submap list
    local: np.ndarray  # (n, 3) sampled surface points, submap-local frame
    owner: np.ndarray  # (n,) index into ``members``
    group: np.ndarray  # (n,) match group of the sample's label (``label_groups``)
    weight: np.ndarray  # (n,) sample weight (vertical surfaces weigh more)
    free: bool  # may move: every member is free
    sigma_m: float
    sigma_deg: float


@dataclass
class CoarseResult:
    """``poses``: the moved start poses (4, 4) per submap; ``metrics``: per session the correction
    (metres, degrees), score before and after, and whether it was kept."""

    poses: list[np.ndarray]
    metrics: dict[str, dict[str, float]]


class _Occupancy:
    """Soft occupancy of surface samples (``density`` per m²) on a voxel grid from ``lo`` (``dims`` voxels).

    Lookups floor a point to its voxel, so a shift by whole voxels is a fixed offset of the flat index
    (``offsets``): the search's inner loop is one gather."""

    def __init__(self, points: torch.Tensor, group: torch.Tensor, lo: torch.Tensor, dims: torch.Tensor,
                 voxel: float, density: float) -> None:
        self.lo, self.voxel, self.dims = lo, voxel, dims
        nx, ny, nz = (int(d) for d in dims)
        self.strides = torch.tensor([ny * nz, nz, 1], device=points.device)
        self.cells = nx * ny * nz  # one grid per match group, stacked
        grid = torch.zeros(_NUM_GROUPS * self.cells, dtype=torch.float32, device=points.device)
        idx = ((points - lo) / voxel).floor().long()
        keep = torch.all((idx >= 0) & (idx < dims), dim=1) & (group >= 0)
        grid.index_add_(0, self.flat(idx[keep]) + group[keep] * self.cells,
                        torch.ones(int(keep.sum()), dtype=torch.float32, device=points.device))
        grid = grid.view(_NUM_GROUPS, nx, ny, nz)
        for axis in (1, 2, 3):  # separable [1 2 1] / 4 blur: a point counts half in the neighbouring voxels
            blurred = 0.5 * grid
            n = grid.shape[axis]
            blurred.narrow(axis, 1, n - 1).add_(grid.narrow(axis, 0, n - 1), alpha=0.25)
            blurred.narrow(axis, 0, n - 1).add_(grid.narrow(axis, 1, n - 1), alpha=0.25)
            grid = blurred
        # in units of one surface crossing a voxel (the blur keeps half of it in the voxel): a surface
        # voxel ~0.63, its neighbours across ~0.39; saturating, so dense or overlapping surfaces (ground,
        # several reference sessions) do not outweigh sparse structure
        self.values = (1.0 - torch.exp(-2.0 * grid.reshape(-1) / (density * voxel**2))).half()

    def flat(self, idx: torch.Tensor) -> torch.Tensor:
        """Flat offset of integer voxel coordinates (..., 3) (no integer matmul: CUDA has none)."""
        return (idx * self.strides).sum(-1)

    def index(self, points: torch.Tensor, group: torch.Tensor) -> torch.Tensor:
        """Flat voxel index of ``points`` (n, 3) in their groups' grids, clamped into the grid."""
        idx = ((points - self.lo) / self.voxel).floor().long()
        return self.flat(torch.minimum(torch.clamp(idx, min=0), self.dims - 1)) + group.clamp(min=0) * self.cells

    def taps(self, points: torch.Tensor, group: torch.Tensor, smooth: bool) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(flat index, weight) pairs whose weighted sum is the occupancy of each of ``points``' (n, 3)
        group at it: the voxel (``smooth`` False) or trilinear between voxel centres (8 taps). Whole-voxel
        shifts keep the weights and add a constant to the indices."""
        base_group = group.clamp(min=0) * self.cells
        if not smooth:
            return [(self.index(points, group), torch.ones(len(points), device=points.device))]
        f = (points - self.lo) / self.voxel - 0.5
        base = f.floor()
        t = f - base
        base = base.long()
        out = []
        for corner in range(8):
            bits = torch.tensor([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1], device=points.device)
            idx = torch.minimum(torch.clamp(base + bits, min=0), self.dims - 1)
            out.append((self.flat(idx) + base_group, torch.where(bits.bool(), t, 1 - t).prod(1)))
        return out


def _yaw(angle: torch.Tensor) -> torch.Tensor:
    """Rotations (k, 3, 3) about z by ``angle`` (k,) radians."""
    c, s = torch.cos(angle), torch.sin(angle)
    out = torch.zeros(len(angle), 3, 3, dtype=angle.dtype, device=angle.device)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1], out[:, 2, 2] = c, -s, s, c, 1.0
    return out


def _steps(radius: float, step: float) -> int:
    """Steps each side of zero covering ``radius``."""
    return max(0, int(math.ceil(radius / step - 1e-9)))


def _peak(values: torch.Tensor, at: tuple[int, ...]) -> list[float]:
    """Sub-step offset of a maximum of ``values`` at index ``at`` per axis (parabola through the
    neighbours; 0 at an edge or where the neighbours do not bracket a peak)."""
    out = []
    for axis, i in enumerate(at):
        if i == 0 or i == values.shape[axis] - 1:
            out.append(0.0)
            continue
        lo, mid, hi = (float(values[at[:axis] + (i + d,) + at[axis + 1:]]) for d in (-1, 0, 1))
        curv = lo - 2 * mid + hi
        out.append(float(np.clip(0.5 * (lo - hi) / curv, -0.5, 0.5)) if curv < 0 else 0.0)
    return out


def _search(
    target: tuple[torch.Tensor, torch.Tensor], source: tuple[torch.Tensor, torch.Tensor], w: torch.Tensor,
    yaws: torch.Tensor, voxel: float, n_xy: int, n_z: int, tie: tuple[float, float], density: float,
    smooth: bool,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The yaw (about the source points' centroid) and shift of ``source`` onto ``target``'s occupancy.

    Candidates: ``yaws`` × shifts of ±``n_xy`` (x, y) and ±``n_z`` (z) whole voxels, scored by the
    weighted mean occupancy of each sample's group. Of the candidates within ``max(tie[0], tie[1] × gain)``
    of the best score (gain: best − start), the one that moves the samples least is chosen: where the
    data leave a ridge (a straight road), the start keeps the direction they do not decide.
    ``target`` and ``source``: points (n, 3) and their match groups (n,).
    Returns the correction (4, 4) float64 (sub-voxel and sub-step by parabolic interpolation) and the
    scores ``score`` (the chosen), ``best``, ``start`` (no correction) and ``noise`` (a gain over the
    start that chance alone reaches among this many candidates)."""
    ref, ref_group = target
    moving, group = source
    dev = moving.device
    centre = moving.mean(0)
    rots = _yaw(yaws).to(moving.dtype)
    rotated = (moving - centre) @ rots.transpose(1, 2) + centre  # (k_yaw, n, 3)
    reach = torch.tensor([n_xy + 2, n_xy + 2, n_z + 2], device=dev) * voxel
    lo = rotated.reshape(-1, 3).min(0).values - reach
    dims = ((rotated.reshape(-1, 3).max(0).values + reach - lo) / voxel).ceil().long() + 1
    near = torch.all((ref >= lo) & (ref <= lo + dims * voxel), dim=1)
    occ = _Occupancy(ref[near].float(), ref_group[near], lo, dims, voxel, density)
    r_xy, r_z = torch.arange(-n_xy, n_xy + 1, device=dev), torch.arange(-n_z, n_z + 1, device=dev)
    gx, gy, gz = torch.meshgrid(r_xy, r_xy, r_z, indexing="ij")
    steps = torch.stack([gx.reshape(-1), gy.reshape(-1), gz.reshape(-1)], 1)
    offsets = occ.flat(steps)
    wn = (w / w.sum()).float()
    score = torch.empty(len(yaws), len(steps), dtype=torch.float64, device=dev)
    per = max(1, _CHUNK // max(1, len(moving)))
    for a in range(len(yaws)):
        taps = occ.taps(rotated[a], group, smooth)
        for s0 in range(0, len(steps), per):
            off = offsets[s0:s0 + per, None]
            chunk = torch.zeros(len(off), dtype=torch.float32, device=dev)
            for idx, tw in taps:
                chunk += occ.values[idx[None] + off].float() @ (wn * tw)
            score[a, s0:s0 + per] = chunk.double()
    start = float(score[int(torch.argmin(yaws.abs())), (steps.abs().sum(1) == 0).nonzero()[0, 0]])
    best = float(score.max())
    # displacement of the samples (RMS) by each candidate; the least-moving near-best one wins
    radius = float((moving[:, :2] - centre[:2]).pow(2).sum(1).mean().sqrt())
    moved = (yaws.double() * radius).pow(2)[:, None] + (steps.double() * voxel).pow(2).sum(1)[None]
    near_best = score >= best - max(tie[0], tie[1] * (best - start))
    choice = int(torch.argmin(torch.where(near_best, moved, torch.full_like(moved, math.inf))))
    grid = score.view(len(yaws), 2 * n_xy + 1, 2 * n_xy + 1, 2 * n_z + 1)
    at = tuple(int(v) for v in np.unravel_index(choice, grid.shape))
    d_yaw, dx, dy, dz = _peak(grid, at)
    step_yaw = float(yaws[1] - yaws[0]) if len(yaws) > 1 else 0.0
    yaw = float(yaws[at[0]]) + d_yaw * step_yaw
    shift = (torch.tensor([at[1] - n_xy + dx, at[2] - n_xy + dy, at[3] - n_z + dz], dtype=torch.float64) * voxel)
    rot = _yaw(torch.tensor([yaw], dtype=torch.float64))[0]
    c = centre.double().cpu()
    g = torch.eye(4, dtype=torch.float64)
    g[:3, :3], g[:3, 3] = rot, c - rot @ c + shift
    # a gain the best of K candidates reaches by chance: the score is a weighted mean of n_eff samples
    # (standard error √(p(1-p)/n_eff)); the maximum of K such errors, against the start's, ~2√(ln K) of it
    n_eff = 1.0 / float((wn.double() ** 2).sum())
    noise = 2.0 * math.sqrt(math.log(max(2, score.numel()))) * math.sqrt(max(best * (1 - best), 1e-6) / n_eff)
    return g, {"score": float(score.view(-1)[choice]), "best": best, "start": start, "noise": noise}


def _sessions(subs: list[SubmapInput], config: FusionConfig, rng: np.random.Generator) -> list[_Session]:
    """Each session's surface sample (area-weighted, ``coarse_points_per_m2``)."""
    by: dict[str, list[int]] = {}
    for k, s in enumerate(subs):
        by.setdefault(s.session_id, []).append(k)
    out = []
    for sid in sorted(by):
        members = by[sid]
        local, owner, group, weight = [], [], [], []
        for m, k in enumerate(members):
            mesh = subs[k].mesh
            area, normal = face_geometry(mesh.vertices, mesh.faces)
            total = float(area.sum())
            if total <= 0:
                continue
            n = int(min(config.coarse_max_points, max(50, total * config.coarse_points_per_m2)))
            face = rng.choice(len(area), size=n, p=area / total)
            local.append(on_triangles(mesh.vertices[mesh.faces[face]], *uniform_barycentric(n, rng)))
            owner.append(np.full(n, m))
            group.append(label_groups(np.asarray(mesh.face_labels)[face]))
            # local frames are z-up (vehicle): ground has |n_z| ~ 1 and fixes only height and tilt
            weight.append(0.25 + 0.75 * (1.0 - np.abs(normal[face, 2])))
        if not local:
            continue
        out.append(_Session(members, np.concatenate(local), np.concatenate(owner), np.concatenate(group),
                            np.concatenate(weight), all(subs[k].free for k in members),
                            float(np.median([subs[k].gps_sigma.trans_m for k in members])),
                            float(np.median([subs[k].gps_sigma.rot_deg for k in members]))))
    return out


class _Clouds:
    """The sessions' samples at their start poses and current corrections (``corr``, region frame)."""

    def __init__(self, sessions: list[_Session], start: list[np.ndarray]) -> None:
        self.sessions = sessions
        mats = [torch.tensor(np.stack([start[k] for k in s.members])) for s in sessions]
        self.start = []
        for s, m in zip(sessions, mats, strict=True):
            m = m[torch.from_numpy(s.owner)]
            self.start.append((m[:, :3, :3] @ torch.from_numpy(s.local)[:, :, None])[:, :, 0] + m[:, :3, 3])
        self.groups = [torch.from_numpy(s.group) for s in sessions]
        self.corr = [torch.eye(4, dtype=torch.float64) for _ in sessions]

    def points(self, i: int) -> torch.Tensor:
        c = self.corr[i]
        return self.start[i] @ c[:3, :3].T + c[:3, 3]

    def union(self, members: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.cat([self.points(j) for j in members]), torch.cat([self.groups[j] for j in members])


def coarse_register(
    subs: list[SubmapInput], start: list[np.ndarray], config: FusionConfig, device: torch.device | None = None
) -> CoarseResult:
    """Move each free session of ``subs`` (start poses ``start``, one frame for all) rigidly onto the
    surfaces of the others. Sessions that overlap no other, or whose best match is not clearly better
    than the start, keep their poses."""
    dev = device or torch.device("cpu")
    sessions = _sessions(subs, config, np.random.default_rng(config.seed))
    poses = [m.copy() for m in start]
    if len(sessions) < 2 or not any(s.free for s in sessions):
        return CoarseResult(poses, {})
    clouds = _Clouds(sessions, start)
    fixed = [i for i, s in enumerate(sessions) if not s.free]
    registered = list(fixed) if fixed else [max(range(len(sessions)), key=lambda i: len(sessions[i].local))]
    pending = [i for i in range(len(sessions)) if i not in registered and sessions[i].free]
    stats: dict[int, dict[str, float]] = {}
    while pending:  # round 1: grow from the anchor, most-overlapping session first
        ref = clouds.union(registered)
        overlaps = [_overlap(clouds.points(i), clouds.groups[i], ref, config) for i in pending]
        i = pending[int(np.argmax(overlaps))]
        if max(overlaps) > 0:
            stats[i] = _register(i, clouds, ref, config, dev, coarse=True)
        registered.append(i)
        pending.remove(i)
    anchor = None if fixed else registered[0]
    for i, s in enumerate(sessions):  # round 2: the anchor and the sessions round 1 moved, against all others
        # a session whose wide search found nothing significant has no evidence a local search could add
        # to (a narrower search has a lower chance bar: exact bench seed 2 moved a barely overlapping session
        # 1.5 m the wrong way here)
        if s.free and (i == anchor or stats.get(i, {}).get("kept")):
            st = _register(i, clouds, clouds.union([j for j in range(len(sessions)) if j != i]), config, dev,
                           coarse=False)
            stats[i] = {f"first_{k}": v for k, v in stats.get(i, {}).items()} | st
    if not fixed:
        moved = [i for i in range(len(sessions)) if i == anchor or stats.get(i, {}).get("first_kept")]
        if len(moved) > 1:
            _remove_mean(clouds, moved)
    metrics: dict[str, dict[str, float]] = {}
    for i, s in enumerate(sessions):
        if not s.free:
            continue
        c = clouds.corr[i].numpy()
        for k in s.members:
            poses[k] = c @ start[k]
        before = clouds.start[i].mean(0).numpy()
        metrics[subs[s.members[0]].session_id] = {
            "shift_m": round(float(np.linalg.norm(c[:3, :3] @ before + c[:3, 3] - before)), 3),
            "yaw_deg": round(math.degrees(math.atan2(c[1, 0], c[0, 0])), 3),
        } | {k: round(v, 4) for k, v in stats.get(i, {}).items()}
    return CoarseResult(poses, metrics)


def _overlap(pts: torch.Tensor, group: torch.Tensor, ref: tuple[torch.Tensor, torch.Tensor],
             config: FusionConfig) -> int:
    """Samples of ``pts`` on an occupied voxel of their group in ``ref`` (the growth order)."""
    voxel = config.coarse_voxel_m
    pts, (ref_pts, ref_group) = pts.float(), ref
    ref_pts = ref_pts.float()
    lo, hi = pts.min(0).values - 2 * voxel, pts.max(0).values + 2 * voxel
    near = torch.all((ref_pts >= lo) & (ref_pts <= hi), dim=1)
    if not bool(near.any()):
        return 0
    occ = _Occupancy(ref_pts[near], ref_group[near], lo, ((hi - lo) / voxel).ceil().long() + 1, voxel,
                     config.coarse_points_per_m2)
    return int(((occ.values[occ.index(pts, group)] > 0.5) & (group >= 0)).sum())


def _register(i: int, clouds: _Clouds, ref: tuple[torch.Tensor, torch.Tensor], config: FusionConfig,
              dev: torch.device, coarse: bool) -> dict[str, float]:
    """Search session ``i``'s yaw and shift against ``ref``; keep it (update ``clouds.corr[i]``) if it
    gains ``coarse_min_gain`` and more than chance (``_search``'s noise) over the start; ``_search``
    picks, of the near-best candidates, the one nearest the start.

    ``coarse``: a ``coarse_voxel_m`` stage over ±``coarse_range_sigmas`` σ/√n first (σ the GPS σ, n the
    session's submaps: the chain's placement error); then a stage on
    half the voxel over ±2 of them and ±2° (trilinear lookups)."""
    s = clouds.sessions[i]
    sub = torch.from_numpy(np.random.default_rng(config.seed + i).permutation(len(s.local))[:config.coarse_match_points])
    moving = (clouds.points(i)[sub].float().to(dev), clouds.groups[i][sub].to(dev))
    w = torch.tensor(s.weight, dtype=torch.float32)[sub].to(dev) * (moving[1] >= 0)
    if float(w.sum()) <= 0:
        return {"kept": 0.0}
    ref = (ref[0].float().to(dev), ref[1].to(dev))
    # the reference density grows with the sessions in it: more of them saturate sooner
    density = config.coarse_points_per_m2 * max(1.0, len(ref[0]) / max(1, len(s.local)) / 2)
    # the chain sits on the mean of its submaps' independent GPS fixes: it is ~σ/√n off, not σ (searching
    # ±3 σ of one fix, σ 4 m, scored wrong peaks metres away above the chance bar: see the module docstring)
    chain = math.sqrt(len(s.members))
    sig_m, sig_r = max(s.sigma_m / chain, 0.1), math.radians(max(s.sigma_deg / chain, 0.1))
    stages = []
    if coarse:
        v = config.coarse_voxel_m
        r_yaw = min(config.coarse_range_sigmas * sig_r, math.radians(config.coarse_max_yaw_deg))
        r_xy = min(config.coarse_range_sigmas * sig_m, config.coarse_max_shift_m)
        stages.append((v, math.radians(1.0), _steps(r_yaw, math.radians(1.0)), _steps(r_xy, v),
                       _steps(min(max(1.0, s.sigma_m), 3.0), v), False))
    v = config.coarse_voxel_m / 2
    stages.append((v, math.radians(0.25), 8, 4, 2, True))
    total = torch.eye(4, dtype=torch.float64)
    out: dict[str, float] = {}
    for k, (voxel, step_yaw, n_yaw, n_xy, n_z, smooth) in enumerate(stages):
        yaws = torch.arange(-n_yaw, n_yaw + 1, dtype=torch.float64, device=dev) * step_yaw
        n = len(w) // 2 if coarse and k == 0 else len(w)  # the wide stage: half the samples (a random half)
        g, sc = _search(ref, (moving[0][:n], moving[1][:n]), w[:n], yaws, voxel, n_xy, n_z,
                        (config.coarse_tie_min, config.coarse_tie), density, smooth)
        if k == 0:
            out = {"score_start": sc["start"], "score_noise": sc["noise"], "range_m": n_xy * voxel}
            if sc["best"] - sc["start"] < max(config.coarse_min_gain, sc["noise"]):  # not significant: keep
                return out | {"score": sc["start"], "score_best": sc["best"], "score_gain": 0.0, "kept": 0.0}
        out |= {"score": sc["score"], "score_best": sc["best"]}
        pts = torch.cat([moving[0].double().cpu(), torch.ones(len(moving[0]), 1, dtype=torch.float64)], 1) @ g.T
        moving = (pts[:, :3].float().to(dev), moving[1])
        total = g @ total
    out["score_gain"] = out["score"] - out["score_start"]
    kept = out["score_gain"] >= config.coarse_min_gain
    out["kept"] = float(kept)
    if kept:
        clouds.corr[i] = total @ clouds.corr[i]
    return out


def _remove_mean(clouds: _Clouds, members: list[int]) -> None:
    """Take the mean correction (yaw, centroid shift; sessions weighted by their submap count) of the
    sessions ``members`` (the anchor and those registered onto it) out of theirs: that group keeps its GPS
    fixes' average placement. Sessions outside it were not moved and keep their start (the gauge of
    the group does not concern them)."""
    w = np.array([len(clouds.sessions[i].members) for i in members], dtype=float)
    corr = [clouds.corr[i] for i in members]
    yaws = np.array([math.atan2(float(c[1, 0]), float(c[0, 0])) for c in corr])
    before = np.stack([clouds.start[i].mean(0).numpy() for i in members])
    after = np.stack([(c[:3, :3] @ torch.from_numpy(b) + c[:3, 3]).numpy() for c, b in zip(corr, before, strict=True)])
    rot = _yaw(torch.tensor([-float(np.average(yaws, weights=w))], dtype=torch.float64))[0].numpy()
    pivot = np.average(after, axis=0, weights=w)
    h = np.eye(4)
    h[:3, :3] = rot
    h[:3, 3] = np.average(before, axis=0, weights=w) - rot @ pivot
    for i in members:
        clouds.corr[i] = torch.tensor(h) @ clouds.corr[i]
