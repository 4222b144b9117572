"""Placement of the world's objects along the roads (map frame, metres).

Objects are placed in a road's frame (station ``s`` along the centre line, lateral offset to one
side), checked against the ground class they need below them and against an occupancy raster so
that nothing overlaps, then turned into labelled ``Part`` meshes.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from scipy.spatial import cKDTree

from fusion.eval.synth import shapes
from fusion.eval.synth.shapes import Part
from fusion.labels import LABEL_BY_NAME


class World(Protocol):
    """What placement needs of the world it furnishes (``fusion.eval.synth.world.World``)."""

    params: Any  # WorldParams
    roads: list[np.ndarray]
    sidewalk_width: float
    occupancy: Occupancy

    def ground_height(self, xy: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray: ...

    def ground_label(self, xy: np.ndarray) -> np.ndarray: ...

L = {name: label.id for name, label in LABEL_BY_NAME.items()}
RASTER = 0.5  # occupancy raster cell (m)


class Occupancy:
    """2D occupancy raster over the world extent."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.lo, hi = world.params.extent
        self.shape = tuple(np.ceil((hi - self.lo) / RASTER).astype(int) + 1)
        self.grid = np.zeros(self.shape, bool)

    def _cells(self, rect: tuple[float, float, float, float, float], pad: float) -> np.ndarray:
        cx, cy, hl, hw, yaw = rect
        u, w = np.meshgrid(np.arange(-hl - pad, hl + pad + 1e-6, RASTER / 2), np.arange(-hw - pad, hw + pad + 1e-6, RASTER / 2))
        c, s = np.cos(yaw), np.sin(yaw)
        return np.column_stack([cx + c * u.ravel() - s * w.ravel(), cy + s * u.ravel() + c * w.ravel()])

    def fits(self, rect: tuple[float, float, float, float, float], ground: set[int], pad: float = 0.3) -> bool:
        """Inside the world, on allowed ground classes, and not overlapping anything placed."""
        xy = self._cells(rect, pad)
        idx = np.floor((xy - self.lo) / RASTER).astype(int)
        if np.any(idx < 0) or np.any(idx >= np.asarray(self.shape)):
            return False
        if self.grid[idx[:, 0], idx[:, 1]].any():
            return False
        return bool(np.isin(self.world.ground_label(self._cells(rect, 0.0)), list(ground)).all())

    def occupy(self, rect: tuple[float, float, float, float, float], pad: float = 0.3) -> None:
        idx = np.floor((self._cells(rect, pad) - self.lo) / RASTER).astype(int)
        self.grid[idx[:, 0], idx[:, 1]] = True


def road_frame(road: np.ndarray, s_idx: int, side: int, lateral: float) -> tuple[np.ndarray, float]:
    """Point at ``lateral`` metres to ``side`` (+1 left, -1 right) of centre-line point ``s_idx``; heading."""
    a, b = road[max(s_idx - 1, 0)], road[min(s_idx + 1, len(road) - 1)]
    d = (b - a) / (np.linalg.norm(b - a) + 1e-12)
    left = np.array([-d[1], d[0]])
    return road[s_idx] + side * lateral * left, float(np.arctan2(d[1], d[0]))


def _min_ground(world: World, rect: tuple[float, float, float, float, float]) -> float:
    cx, cy, hl, hw, yaw = rect
    c, s = np.cos(yaw), np.sin(yaw)
    corners = np.array([[cx + c * u - s * w, cy + s * u + c * w] for u in (-hl, hl) for w in (-hw, hw)])
    return float(world.ground_height(np.vstack([corners, [[cx, cy]]])).min())


def _part(mesh: shapes.Mesh, label: str, kind: str, rect=None, occluder: bool = False, session=None) -> Part:

    v, f = mesh
    return Part(v, f, np.full(len(f), L[label]), kind, session, rect, occluder)


def make_object(world: World, kind: str, xy: np.ndarray, yaw: float, rng: np.random.Generator,
                occ: Occupancy, session: int | None = None) -> list[Part]:
    """Try to place one object of ``kind`` centred at xy (map frame); returns its parts or []."""
    rect, ground, size = _footprint(kind, xy, yaw, rng)
    if not occ.fits(rect, ground):
        return []
    occ.occupy(rect)
    parts = _object_parts(world, kind, np.asarray(xy, float), yaw, rect, size, rng)
    for p in parts:
        p.session = session
    return parts


# The two functions below are declarative tables of the object kinds (one branch per kind: its
# footprint and allowed ground, then its shapes); they stay one branch per kind, whatever their length.
def _footprint(kind: str, xy: np.ndarray, yaw: float, rng: np.random.Generator,
               ) -> tuple[tuple[float, float, float, float, float], set[int], tuple[float, ...]]:
    """Footprint rectangle (x, y, half length, half width, yaw; map frame, metres), the ground labels it
    may stand on, and its drawn size (length, width, height; trees and bushes: (radius,))."""
    walk = {L["sidewalk"], L["terrain"]}
    size: tuple[float, ...] = ()
    if kind == "building":
        size = (rng.uniform(8, 18), rng.uniform(6, 12), rng.uniform(5, 14))
        rect, ground = (xy[0], xy[1], size[0] / 2, size[1] / 2, yaw), {L["terrain"]}
    elif kind == "fence":
        size = (rng.uniform(5, 12), 0.1, rng.uniform(1.0, 1.8))
        rect, ground = (xy[0], xy[1], size[0] / 2, 0.05, yaw), {L["terrain"]}
    elif kind in ("tree", "bush"):
        r = rng.uniform(1.4, 2.6) if kind == "tree" else rng.uniform(0.8, 1.6)
        size = (r,)
        rect, ground = (xy[0], xy[1], r, r, 0.0), {L["terrain"]}
    elif kind in ("pole", "sign"):
        rect, ground = (xy[0], xy[1], 0.35, 0.35, yaw), walk
    elif kind == "vehicle":
        size = (rng.uniform(3.8, 4.9), rng.uniform(1.7, 1.9), rng.uniform(1.3, 1.7))
        rect, ground = (xy[0], xy[1], size[0] / 2, size[1] / 2, yaw), {L["road"]}
    elif kind == "obstacle":
        size = (rng.uniform(0.5, 1.8), rng.uniform(0.3, 0.7), rng.uniform(0.6, 1.1))
        rect, ground = (xy[0], xy[1], size[0] / 2, size[1] / 2, yaw), {L["road"], L["sidewalk"]}
    else:
        raise ValueError(f"unknown object kind {kind!r}")
    return rect, ground, size


def _object_parts(world: World, kind: str, c: np.ndarray, yaw: float, rect: tuple[float, float, float, float, float],
                  size: tuple[float, ...], rng: np.random.Generator) -> list[Part]:
    """The parts (meshes, map frame) of an object of ``kind`` at ``c`` standing on the ground under ``rect``."""
    me = world.params.max_edge
    z0 = _min_ground(world, rect)
    r = size[0] if kind in ("tree", "bush") else 0.0
    if kind == "building":
        parts = [_part(shapes.box(c, z0 - 0.3, (size[0], size[1], size[2] + 0.3), yaw, me), "building", kind, rect, True)]
    elif kind == "fence":
        parts = [_part(shapes.box(c, z0 - 0.1, (size[0], size[1], size[2] + 0.1), yaw, me), "fence", kind, rect)]
    elif kind == "tree":
        h = rng.uniform(2.0, 3.2)
        trunk = shapes.cylinder(c, z0 - 0.1, 0.15, h + 0.1, me, sections=8)
        crown = shapes.ellipsoid(np.array([c[0], c[1], z0 + h + 0.6 * r]), (r, r, 0.9 * r), me)
        parts = [_part(shapes.merge([trunk, crown]), "vegetation", kind, (c[0], c[1], 0.2, 0.2, 0.0))]
    elif kind == "bush":
        rz = rng.uniform(0.5, 0.9)
        parts = [_part(shapes.ellipsoid(np.array([c[0], c[1], z0 + 0.6 * rz]), (r, r * 0.8, rz), me), "vegetation", kind, rect)]
    elif kind == "pole":
        parts = [_part(shapes.cylinder(c, z0 - 0.1, 0.12, rng.uniform(6, 8), me), "pole", kind, (c[0], c[1], 0.12, 0.12, 0.0))]
    elif kind == "sign":
        h = rng.uniform(2.2, 2.8)
        post = shapes.cylinder(c, z0 - 0.1, 0.05, h + 0.1, me, sections=8)
        plate_size = rng.uniform(0.6, 0.9)
        # the plate faces oncoming traffic: its thin side is along the road heading
        plate = shapes.box(c, z0 + h, (0.05, plate_size, plate_size), yaw, 0.3)
        parts = [_part(post, "pole", kind, (c[0], c[1], 0.05, 0.05, 0.0)), _part(plate, "traffic_sign", kind)]
    elif kind == "vehicle":
        body = shapes.box(c, z0 + 0.25, (size[0], size[1], 0.7 * size[2] - 0.25), yaw, me)
        cab_h = 0.3 * size[2]
        cab = shapes.box(c - 0.1 * size[0] * np.array([np.cos(yaw), np.sin(yaw)]), z0 + 0.7 * size[2],
                         (0.55 * size[0], 0.9 * size[1], cab_h), yaw, me)
        # wheels: four short cylinders so the body does not float
        wheels = []
        for u in (-0.32, 0.32):
            for w in (-0.4, 0.4):
                wxy = c + u * size[0] * np.array([np.cos(yaw), np.sin(yaw)]) + w * size[1] * np.array([-np.sin(yaw), np.cos(yaw)])
                wheels.append(shapes.cylinder(wxy, z0, 0.3, 0.3, me, sections=8))
        parts = [_part(shapes.merge([body, cab, *wheels]), "vehicle", kind, rect)]
    else:  # obstacle: a barrier block, a bin or a cone
        shape = rng.choice(["block", "cone"], p=[0.7, 0.3])
        mesh = shapes.box(c, z0, (size[0], size[1], size[2]), yaw, me) if shape == "block" else shapes.cone(c, z0, 0.25, 0.75, me)
        parts = [_part(mesh, "obstacle", kind, rect)]
    return parts


def place_static(world: World, rng: np.random.Generator) -> list[Part]:
    """Line every road with buildings/fences/vegetation, poles/signs and parked vehicles/obstacles."""
    p = world.params
    mix = p.class_mix
    occ = Occupancy(world)
    world.occupancy = occ
    parts: list[Part] = []
    edge = p.road_half_width + world.sidewalk_width
    roadside = {"building": 1.2 * mix.get("building", 1), "fence": 0.8 * mix.get("fence", 1),
                "tree": 0.9 * mix.get("vegetation", 1), "bush": 0.5 * mix.get("vegetation", 1)}
    names, weights = list(roadside), np.array(list(roadside.values()))
    for k, road in enumerate(world.roads):
        others = [r for j, r in enumerate(world.roads) if j != k]
        other_d = cKDTree(np.concatenate(others)).query(road)[0] if others else np.full(len(road), np.inf)
        n = len(road)
        step = float(np.linalg.norm(road[1] - road[0]))
        for side in (-1, 1):
            # beyond the sidewalk
            i = int(rng.uniform(0, 8) / step)
            while i < n:
                kind = names[rng.choice(len(names), p=weights / weights.sum())] if weights.sum() > 0 else "gap"
                depth = {"building": rng.uniform(2, 6) + 5, "fence": 0.8, "tree": rng.uniform(2, 4), "bush": 1.6}[kind]
                xy, yaw = road_frame(road, i, side, edge + depth)
                placed = make_object(world, kind, xy, yaw, rng, occ)
                parts += placed
                length = {"building": 14, "fence": 10, "tree": 5, "bush": 3}[kind] if placed else 3
                i += int((length + rng.uniform(1, 4)) / step)
            # on the sidewalk: street lights and signs near the kerb
            for kind, spacing, weight in (("pole", 24, mix.get("pole", 1)), ("sign", 40, mix.get("traffic_sign", 1))):
                if weight <= 0:
                    continue
                i = int(rng.uniform(0, spacing) / step)
                while i < n:
                    xy, yaw = road_frame(road, i, side, p.road_half_width + 0.6)
                    parts += make_object(world, kind, xy, yaw, rng, occ)
                    i += int(rng.uniform(0.7, 1.3) * spacing / max(weight, 0.1) / step)
            # street furniture (bins, bollards, barriers) at the sidewalk's outer edge
            if mix.get("obstacle", 1) > 0:
                i = int(rng.uniform(0, 15) / step)
                while i < n:
                    xy, yaw = road_frame(road, i, side, edge - 0.6)
                    parts += make_object(world, "obstacle", xy, yaw, rng, occ)
                    i += int(rng.uniform(0.7, 1.3) * 15 / mix.get("obstacle", 1) / step)
            # in the parking strip: parked vehicles and the odd obstacle
            i = int(rng.uniform(0, 6) / step)
            while i < n:
                u = rng.random()
                pv, po = 0.35 * mix.get("vehicle", 1), 0.06 * mix.get("obstacle", 1)
                parked = "vehicle" if u < pv else ("obstacle" if u < pv + po else None)
                if parked is not None and other_d[i] > edge + 4.0:
                    lateral = p.road_half_width - 1.0 if parked == "vehicle" else p.road_half_width - 0.5
                    xy, yaw = road_frame(road, i, side, lateral)
                    parts += make_object(world, parked, xy, yaw, rng, occ)
                i += int(rng.uniform(5.5, 7.0) / step)
    parts += _ensure_classes(world, parts, rng, occ)
    return parts


# lateral offset from the centre line: (relative to the kerb line "road" or the sidewalk's outer edge "edge", m)
KIND_LATERAL = {"building": ("edge", 8.0), "fence": ("edge", 0.8), "tree": ("edge", 3.0), "pole": ("road", 0.6),
                "sign": ("road", 0.6), "vehicle": ("road", -1.0), "obstacle": ("road", -0.5)}
KIND_LABEL = {"building": "building", "fence": "fence", "tree": "vegetation", "pole": "pole", "sign": "traffic_sign",
              "vehicle": "vehicle", "obstacle": "obstacle"}


def _ensure_classes(world: World, parts: list[Part], rng: np.random.Generator, occ: Occupancy) -> list[Part]:
    """Place one object of every class the random placement missed (class mix weight > 0), near the core."""
    p = world.params
    present = {int(lab) for part in parts for lab in np.unique(part.labels)}
    cmin, cmax = np.asarray(p.core_min), np.asarray(p.core_max)
    extra: list[Part] = []
    for kind, label in KIND_LABEL.items():
        if L[label] in present or p.class_mix.get(label, 1.0) <= 0:
            continue
        for attempt in range(600):
            road = world.roads[rng.integers(len(world.roads))]
            i = int(rng.integers(len(road)))
            if attempt < 300 and not np.all((road[i] > cmin) & (road[i] < cmax)):
                continue
            ref, off = KIND_LATERAL[kind]
            lateral = p.road_half_width + off + (world.sidewalk_width if ref == "edge" else 0.0)
            xy, yaw = road_frame(road, i, int(rng.choice([-1, 1])), lateral)
            placed = make_object(world, kind, xy, yaw, rng, occ)
            if placed:
                extra += placed
                break
    return extra
