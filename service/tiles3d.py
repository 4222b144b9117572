"""OGC 3D Tiles 1.1 of the fused map (torch-free): the tileset document and each tile's glTF content.

Frames. Content is in the map frame (ENU metres at ``FLEETMAP_ORIGIN``); the root tile's ``transform``
(column-major) takes the map frame to ECEF (``fusion.geo.enu_to_ecef``). glTF is y-up: the content's
node turns the map frame's z-up into y-up (``fusion.meshio.MAP_TO_GLTF``) and a 3D Tiles runtime turns
glTF content back to z-up (3D Tiles 1.1, "glTF y-up to z-up": a +90° rotation about x, applied before
the tile transforms), so every vertex lands at its own map-frame point. Positions are stored relative
to the tile's centre, which the node adds back, so float32 keeps sub-millimetre precision far from the
origin.

Bounding volumes come from each stored mesh's own extent (computed once per mesh blob, cached): a
``box`` in the root's (map) frame and a ``region`` (radians, metres above the WGS84 ellipsoid). One
child per fused tile, at its latest version; a content URI names the version, so a new version is a
new URI and ``refine: REPLACE`` swaps it in.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import pymap3d

from fusion.geo import Origin, enu_to_ecef
from fusion.meshio import write_glb
from fusion.types import FusedMesh

# Bump when the tileset or content encoding changes: every ETag changes with it.
FORMAT = "3dtiles-1"
# Margins around a mesh's extent: float32 rounding of the stored positions, and room for the
# curvature of straight map-frame edges between the points a region is sampled at.
PAD_M = 0.05
PAD_RAD = 1e-8  # about 6 cm on the ground


@dataclass(frozen=True)
class FusedTile:
    """A tile's fused version as the tileset names it."""

    i: int
    j: int
    version: int
    mesh_sha256: str


@dataclass(frozen=True)
class Extent:
    """An axis-aligned box of the map frame, metres."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    @staticmethod
    def of(mesh: FusedMesh) -> Extent | None:
        """The mesh's vertices' extent (map frame), grown by ``PAD_M``; None for an empty mesh."""
        if len(mesh.faces) == 0:
            return None
        used = np.asarray(mesh.vertices, dtype=np.float64)[np.unique(np.asarray(mesh.faces))]
        lower, upper = used.min(axis=0) - PAD_M, used.max(axis=0) + PAD_M
        return Extent(_triple(lower), _triple(upper))

    def union(self, other: Extent) -> Extent:
        return Extent(
            _triple(np.minimum(self.lower, other.lower)), _triple(np.maximum(self.upper, other.upper))
        )

    def centre(self) -> np.ndarray:
        return (np.asarray(self.lower) + np.asarray(self.upper)) / 2

    def diagonal(self) -> float:
        return float(np.linalg.norm(np.asarray(self.upper) - np.asarray(self.lower)))

    def box(self) -> list[float]:
        """3D Tiles ``box`` in the map frame: centre, then the x, y, z half-axes."""
        half = (np.asarray(self.upper) - np.asarray(self.lower)) / 2
        return [*self.centre().tolist(), half[0], 0.0, 0.0, 0.0, half[1], 0.0, 0.0, 0.0, half[2]]


@dataclass(frozen=True)
class Region:
    """A geodetic box: longitudes relative to the origin's (radians, so that a region across the
    antimeridian stays one interval), latitudes (radians), heights above the ellipsoid (metres)."""

    dlon: tuple[float, float]
    lat: tuple[float, float]
    height: tuple[float, float]

    @staticmethod
    def around(extent: Extent, origin: Origin) -> Region:
        """A region holding every point of ``extent``: its corners, edge midpoints and the point nearest
        the origin's vertical (where a straight map-frame face sinks lowest), padded by ``PAD_RAD`` /
        ``PAD_M``."""
        (x0, y0, z0), (x1, y1, z1) = extent.lower, extent.upper
        xs, ys, zs = np.meshgrid([x0, (x0 + x1) / 2, x1], [y0, (y0 + y1) / 2, y1], [z0, z1], indexing="ij")
        points = np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)
        nearest = [min(max(0.0, x0), x1), min(max(0.0, y0), y1), z0]
        points = np.vstack([points, nearest])
        lat, lon, alt = pymap3d.enu2geodetic(points[:, 0], points[:, 1], points[:, 2], *origin)
        dlon = (np.radians(np.asarray(lon) - origin[1]) + math.pi) % (2 * math.pi) - math.pi
        lat_r = np.radians(np.asarray(lat))
        alt = np.asarray(alt)
        return Region(
            (float(dlon.min()) - PAD_RAD, float(dlon.max()) + PAD_RAD),
            (float(lat_r.min()) - PAD_RAD, float(lat_r.max()) + PAD_RAD),
            (float(alt.min()) - PAD_M, float(alt.max()) + PAD_M),
        )

    def union(self, other: Region) -> Region:
        def hull(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
            return min(a[0], b[0]), max(a[1], b[1])

        return Region(hull(self.dlon, other.dlon), hull(self.lat, other.lat), hull(self.height, other.height))

    def volume(self, origin: Origin) -> list[float]:
        """3D Tiles ``region``: [west, south, east, north, min height, max height] (radians, metres);
        west > east where it crosses the antimeridian."""

        def wrap(angle: float) -> float:
            return (angle + math.pi) % (2 * math.pi) - math.pi

        lon0 = math.radians(origin[1])
        south, north = max(self.lat[0], -math.pi / 2), min(self.lat[1], math.pi / 2)
        return [wrap(lon0 + self.dlon[0]), south, wrap(lon0 + self.dlon[1]), north, *self.height]


def _triple(values: Any) -> tuple[float, float, float]:
    x, y, z = (float(v) for v in values)
    return x, y, z


def tile_centre(i: int, j: int, tile_size: float) -> np.ndarray:
    """The centre of tile (i, j) on the map frame's z = 0 plane, metres."""
    return np.array([(i + 0.5) * tile_size, (j + 0.5) * tile_size, 0.0])


def tileset(
    tiles: Sequence[tuple[FusedTile, Extent]],
    origin: Origin,
    tile_size: float,
    content_uri: Callable[[FusedTile], str],
) -> dict[str, Any]:
    """The tileset document: a root without content that holds one child per fused tile.

    ``tiles``: the fused tiles with their meshes' extents (tiles with empty meshes left out);
    ``content_uri``: the (relative) URI of a tile version's content. The root's geometric error is the
    size of the whole map, so a viewer refines into the tiles as soon as the map is on screen; tiles
    are full detail (geometric error 0)."""
    children = []
    for tile, extent in tiles:
        children.append(
            {
                "boundingVolume": {
                    "region": Region.around(extent, origin).volume(origin),
                    "box": extent.box(),
                },
                "geometricError": 0.0,
                "content": {"uri": content_uri(tile)},
                "extras": {"tile": [tile.i, tile.j], "version": tile.version},
            }
        )
    if tiles:
        extent = tiles[0][1]
        region = Region.around(extent, origin)
        for _, other in tiles[1:]:
            extent, region = extent.union(other), region.union(Region.around(other, origin))
        error = max(extent.diagonal(), tile_size)
    else:  # an empty map: a valid tileset with nothing to show, placed at the origin
        extent = Extent((-PAD_M, -PAD_M, -PAD_M), (PAD_M, PAD_M, PAD_M))
        region, error = Region.around(extent, origin), 0.0
    root: dict[str, Any] = {
        "transform": enu_to_ecef(origin).flatten(order="F").tolist(),
        "boundingVolume": {"region": region.volume(origin), "box": extent.box()},
        "geometricError": error,
        "refine": "REPLACE",
    }
    if children:
        root["children"] = children
    return {"asset": {"version": "1.1", "generator": "fleetmap"}, "geometricError": error, "root": root}


def tileset_etag(tiles: Sequence[FusedTile], origin: Origin, tile_size: float) -> str:
    """A strong ETag of the tileset: its format, frame and the set of (tile, version, mesh)."""
    key = json.dumps(
        [FORMAT, list(origin), tile_size, sorted((t.i, t.j, t.version, t.mesh_sha256) for t in tiles)]
    )
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


def content_etag(tile: FusedTile, tile_size: float) -> str:
    """A strong ETag of a tile version's content (its mesh blob, its centre, the encoding)."""
    key = f"{FORMAT}:{tile.mesh_sha256}:{tile.i}:{tile.j}:{tile_size!r}"
    return '"' + hashlib.sha256(key.encode()).hexdigest()[:32] + '"'


def content_glb(mesh: FusedMesh, i: int, j: int, tile_size: float) -> bytes:
    """The tile's glTF content: per-face classes as feature ids into the label table, positions
    relative to the tile's centre (see the module docstring for the frames)."""
    return write_glb(mesh, centre=tile_centre(i, j, tile_size), features=True)


K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class LRU(Generic[K, V]):
    """A thread-safe least-recently-used cache bounded by the total ``weight`` of its values."""

    def __init__(self, capacity: float, weight: Callable[[V], float] = lambda _: 1) -> None:
        self.capacity, self.weight = capacity, weight
        self._items: OrderedDict[K, V] = OrderedDict()
        self._total = 0.0
        self._lock = threading.Lock()

    def get(self, key: K, compute: Callable[[], V]) -> V:
        """The cached value of ``key``, else ``compute()`` (outside the lock), cached."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = compute()
        self.put(key, value)
        return value

    def put(self, key: K, value: V) -> None:
        size = self.weight(value)
        if size > self.capacity:
            return
        with self._lock:
            if key in self._items:
                self._total -= self.weight(self._items.pop(key))
            self._items[key] = value
            self._total += size
            while self._total > self.capacity:
                _, old = self._items.popitem(last=False)
                self._total -= self.weight(old)


# Per API process, keyed by content hashes (so shared safely by every app in the process).
EXTENTS: LRU[str, Extent | None] = LRU(100_000)
CONTENT: LRU[tuple[str, int, int, float], bytes] = LRU(64 * 1024 * 1024, weight=len)
