"""Procedural driving world: ground-truth triangle meshes with face labels (map frame, metres).

The world is a smooth, sloped terrain crossed by curved roads that meet at junctions; roads carry
dashed centre lines and are lined by raised sidewalks (kerbs), then buildings, fences, trees, bushes,
street lights, traffic signs, parked vehicles and obstacles. Every label of ``fusion.labels`` except
``unlabeled`` occurs. Everything is drawn from ``WorldParams`` and its seed, so curves, slopes,
junction types, sidewalk widths and the class mix vary between seeds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from fusion.eval.synth import placement, shapes
from fusion.eval.synth.shapes import Part
from fusion.labels import LABEL_BY_NAME
from fusion.overrides import with_overrides

ROAD, SIDEWALK, LANE, TERRAIN = (LABEL_BY_NAME[n].id for n in ("road", "sidewalk", "lane_marking", "terrain"))

DEFAULT_CLASS_MIX = {
    "building": 1.0,
    "fence": 1.0,
    "pole": 1.0,
    "traffic_sign": 1.0,
    "vegetation": 1.0,
    "vehicle": 1.0,
    "obstacle": 1.0,
}


@dataclass
class WorldParams:
    """Generator parameters. ``core_*``: the region vehicles drive through (map frame x/y, metres);
    the geometry extends ``margin`` metres beyond it so that vehicles at the core's edge see a world."""

    seed: int = 0
    core_min: tuple[float, float] = (0.0, 0.0)
    core_max: tuple[float, float] = (64.0, 64.0)
    margin: float = 30.0
    ground_res: float = 0.25
    road_half_width: float = 5.5
    sidewalk_width: tuple[float, float] = (2.0, 3.5)
    kerb_height: float = 0.15
    max_grade: float = 0.05
    max_curvature: float = 1.0 / 60.0
    junction: str = "random"  # JUNCTIONS: "cross" | "t" | "random"
    n_roads: int | None = None  # None: 2 per 64 m × 64 m of core, at least 2
    class_mix: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_CLASS_MIX))
    max_edge: float = 0.7
    marking_width: float = 0.2
    marking_dash: tuple[float, float] = (3.0, 6.0)
    marking_raise: float = 0.02

    @property
    def extent(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.asarray(self.core_min, float) - self.margin
        hi = np.asarray(self.core_max, float) + self.margin
        return lo, hi


JUNCTIONS = ("cross", "t", "random")
CALLERS_FIELDS = ("seed", "core_min", "core_max")  # set by --seed and the bench's tiles, not by --world


def world_overrides(params: WorldParams, items: Sequence[str]) -> WorldParams:
    """``params`` with ``KEY=VALUE`` overrides of its fields (``--world``: e.g. ``max_grade=0.1``,
    ``max_curvature=0.033``, ``junction=t``, ``class_mix=vehicle:2,vegetation:0.5``). Raises ``ValueError``
    on an unknown field, a bad value, or one of ``CALLERS_FIELDS``."""
    taken = [i for i in items if i.partition("=")[0].strip() in CALLERS_FIELDS]
    if taken:
        raise ValueError(f"{taken[0]!r}: {', '.join(CALLERS_FIELDS)} are set by the command (--seed, --tiles, "
                         "--tile-size), not by --world")
    out = with_overrides(params, list(items))
    if out.junction not in JUNCTIONS:
        raise ValueError(f"junction={out.junction!r}: expected one of {', '.join(JUNCTIONS)}")
    return out


class World:
    """Ground height/label functions, road centre lines and the labelled parts (map frame)."""

    occupancy: placement.Occupancy  # set by ``placement.place_static`` during ``__init__``

    def __init__(self, params: WorldParams) -> None:
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        rng = self.rng
        self.sidewalk_width = float(rng.uniform(*params.sidewalk_width))
        self.grade = rng.normal(size=2)
        self.grade *= rng.uniform(0.2, 1.0) * params.max_grade / np.linalg.norm(self.grade)
        self.waves = [
            (rng.uniform(0.2, 0.8), rng.uniform(0, np.pi), rng.uniform(60, 140), rng.uniform(0, 2 * np.pi))
            for _ in range(2)
        ]
        self.bump_phase = rng.uniform(0, 2 * np.pi, size=2)
        self.roads: list[np.ndarray] = _make_roads(params, rng)
        pts = np.concatenate(self.roads)
        self._road_tree = cKDTree(pts)
        self._road_id = np.concatenate([np.full(len(r), k) for k, r in enumerate(self.roads)])
        self._road_index = np.concatenate([np.arange(len(r)) for r in self.roads])
        self.parts: list[Part] = []
        self.parts += _lane_markings(self)
        self.parts += placement.place_static(self, rng)

    # -- ground -----------------------------------------------------------------------------
    def base_height(self, xy: np.ndarray) -> np.ndarray:
        """Road-level ground height (m) at map-frame xy (n, 2)."""
        z = xy @ self.grade
        for amp, phi, lam, psi in self.waves:
            z = z + amp * np.sin(2 * np.pi * (xy[:, 0] * np.cos(phi) + xy[:, 1] * np.sin(phi)) / lam + psi)
        return z

    def road_distance(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (m) to the nearest road centre line and that road's index."""
        d, i = self._road_tree.query(xy)
        return d, self._road_id[i]

    def road_point(self, xy: np.ndarray) -> tuple[int, int]:
        """(road index, centre-line point index) nearest to one map-frame point xy (2,)."""
        i = int(self._road_tree.query(np.asarray(xy, float))[1])
        return int(self._road_id[i]), int(self._road_index[i])

    def ground_label(self, xy: np.ndarray) -> np.ndarray:
        """Ground class at xy: road, sidewalk or terrain."""
        d, _ = self.road_distance(xy)
        p = self.params
        return np.where(d <= p.road_half_width, ROAD, np.where(d <= p.road_half_width + self.sidewalk_width, SIDEWALK, TERRAIN))

    def ground_height(self, xy: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        """Surface height (m) at xy: sidewalks are raised by the kerb, terrain is a bit bumpy."""
        labels = self.ground_label(xy) if labels is None else labels
        k = self.params.kerb_height
        bumps = 0.06 * np.sin(xy[:, 0] * 1.7 + self.bump_phase[0]) * np.sin(xy[:, 1] * 1.3 + self.bump_phase[1])
        offset = np.where(labels == SIDEWALK, k, np.where(labels == TERRAIN, k + 0.05 + bumps, 0.0))
        return self.base_height(xy) + offset

    def ground_mesh(self, xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height-field mesh over the axes xs, ys (map frame): vertices, faces, face labels."""
        xy, faces = shapes.grid(xs, ys)
        v = np.column_stack([xy, self.ground_height(xy)])
        centroid = v[faces].mean(axis=1)[:, :2]
        return v, faces, self.ground_label(centroid)

    # -- ground truth -----------------------------------------------------------------------
    def static_parts(self) -> list[Part]:
        return [p for p in self.parts if p.session is None]

    def transient_parts(self) -> list[Part]:
        return [p for p in self.parts if p.session is not None]

    def gt_ground(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo, hi = self.params.extent
        r = self.params.ground_res
        return self.ground_mesh(np.arange(lo[0], hi[0] + r / 2, r), np.arange(lo[1], hi[1] + r / 2, r))


def _road_polyline(p0: np.ndarray, theta0: float, kappa: float, dkappa: float, s_lo: float, s_hi: float,
                   step: float = 0.25) -> np.ndarray:
    """Centre line (k, 2) with heading θ(s) = θ0 + κ s + ½ κ' s², s from s_lo to s_hi (m)."""
    s = np.arange(s_lo, s_hi + step / 2, step)
    theta = theta0 + kappa * s + 0.5 * dkappa * s**2
    d = np.stack([np.cos(theta), np.sin(theta)], 1) * step
    i0 = int(np.argmin(np.abs(s)))
    pts = np.cumsum(d, axis=0)
    return pts - pts[i0] + p0


def _make_roads(params: WorldParams, rng: np.random.Generator) -> list[np.ndarray]:
    """Curved roads: two meet at a cross or T junction near the core centre, more cross elsewhere."""
    cmin, cmax = np.asarray(params.core_min, float), np.asarray(params.core_max, float)
    lo, hi = params.extent
    reach = float(np.linalg.norm(hi - lo))
    core_area = float(np.prod(cmax - cmin))
    n_roads = params.n_roads or max(2, round(2 * core_area / 64.0**2))
    junction = params.junction if params.junction != "random" else ("cross" if rng.random() < 0.5 else "t")

    def curv() -> tuple[float, float]:
        return rng.uniform(-1, 1) * params.max_curvature, rng.uniform(-1, 1) * params.max_curvature / 80.0

    centre = (cmin + cmax) / 2 + rng.uniform(-0.15, 0.15, 2) * (cmax - cmin)
    theta_a = rng.uniform(0, np.pi)
    roads = [_road_polyline(centre, theta_a, *curv(), -reach, reach)]
    theta_b = theta_a + rng.uniform(np.radians(65), np.radians(115)) * rng.choice([-1, 1])
    roads.append(_road_polyline(centre, theta_b, *curv(), 0.0 if junction == "t" else -reach, reach))
    for _ in range(n_roads - 2):
        p = rng.uniform(cmin, cmax)
        roads.append(_road_polyline(p, rng.uniform(0, np.pi), *curv(), -reach, reach))
    pad = 5.0
    out = []
    for r in roads:
        keep = np.all((r >= lo - pad) & (r <= hi + pad), axis=1)
        idx = np.flatnonzero(keep)
        if len(idx) > 8:
            out.append(r[idx[0] : idx[-1] + 1])
    return out


def _lane_markings(world: World) -> list[Part]:
    """Dashed centre lines and solid lane edge lines (between the lanes and the parking strips): thin
    strips raised a little above the road, interrupted inside junctions."""
    p = world.params
    dash, gap = p.marking_dash
    edge = p.road_half_width - 2.0
    parts = []
    for k, road in enumerate(world.roads):
        others = [r for j, r in enumerate(world.roads) if j != k]
        other_tree = cKDTree(np.concatenate(others)) if others else None
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(road, axis=0), axis=1))])
        tangent = np.gradient(road, axis=0)
        left = np.column_stack([-tangent[:, 1], tangent[:, 0]]) / np.linalg.norm(tangent, axis=1, keepdims=True)
        phase = world.rng.uniform(0, dash + gap)
        for offset in (0.0, edge, -edge):
            line = road + offset * left
            on = ((s + phase) % (dash + gap)) < dash if offset == 0.0 else np.ones(len(road), bool)
            if other_tree is not None:
                on &= other_tree.query(line)[0] > p.road_half_width + world.sidewalk_width + 1.0
            runs = np.diff(np.concatenate([[0], on.astype(int), [0]]))
            for a, b in zip(np.flatnonzero(runs == 1), np.flatnonzero(runs == -1), strict=True):
                idx = np.arange(a, b, 2)
                if len(idx) < 3:
                    continue
                xy = line[idx]
                centre = np.column_stack([xy, world.base_height(xy) + p.marking_raise])
                v, f = shapes.ribbon(centre, p.marking_width)
                parts.append(Part(v, f, np.full(len(f), LANE), "lane_marking"))
    return parts
