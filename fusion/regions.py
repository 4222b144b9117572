"""The region graph (torch-free): tiles linked by the submaps that overlap them.

A *region* is a connected set of tiles: two tiles are linked when one submap overlaps both (a submap
links all of its tiles). Regions are aligned independently (``fusion.align.align_region``): one pose
per submap for the whole region, so a submap's pose is refined against all of its data and sessions
crossing tile borders are aligned to each other. A far-away fleet forms its own region.

Ordering is deterministic: a region's tiles and submap ids are sorted, and regions are sorted by
their first tile, so results never depend on the order the inputs were listed in.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

Tile = tuple[int, int]


@dataclass(frozen=True)
class Region:
    """A connected set of tiles and every submap overlapping one of them (both sorted)."""

    tiles: tuple[Tile, ...]
    submaps: tuple[str, ...]

    @property
    def lower_corner(self) -> Tile:
        """(min i, min j) over the region's tiles: the region frame's origin is this tile's corner."""
        return min(i for i, _ in self.tiles), min(j for _, j in self.tiles)


def regions(tile_sets: Mapping[str, Iterable[Tile]], only: Iterable[Tile] | None = None) -> list[Region]:
    """Connected components of tiles linked by submaps (union-find over tiles).

    ``tile_sets``: submap id → the tiles it overlaps. ``only``: if given, tiles outside it are ignored
    (a submap then links only its tiles inside ``only``; a submap with none is left out). Submaps with
    no tiles are left out. Regions come sorted by their first tile.
    """
    keep = None if only is None else {(int(i), int(j)) for i, j in only}
    parent: dict[Tile, Tile] = {}

    def find(t: Tile) -> Tile:
        root = t
        while parent[root] != root:
            root = parent[root]
        while parent[t] != root:  # path compression
            parent[t], t = root, parent[t]
        return root

    def union(a: Tile, b: Tile) -> None:
        ra, rb = find(a), find(b)
        if ra != rb:  # the smaller tile becomes the root: independent of the union order
            lo, hi = (ra, rb) if ra < rb else (rb, ra)
            parent[hi] = lo

    members: dict[str, list[Tile]] = {}
    for sid in sorted(tile_sets):
        ts = sorted({(int(i), int(j)) for i, j in tile_sets[sid]})
        if keep is not None:
            ts = [t for t in ts if t in keep]
        if not ts:
            continue
        members[sid] = ts
        for t in ts:
            parent.setdefault(t, t)
        for t in ts[1:]:
            union(ts[0], t)
    tiles_of: dict[Tile, list[Tile]] = {}
    for t in sorted(parent):
        tiles_of.setdefault(find(t), []).append(t)
    subs_of: dict[Tile, list[str]] = {}
    for sid, ts in members.items():
        subs_of.setdefault(find(ts[0]), []).append(sid)
    out = [Region(tuple(sorted(ts)), tuple(sorted(subs_of.get(root, [])))) for root, ts in tiles_of.items()]
    return sorted(out, key=lambda r: r.tiles[0])


def region_of(regions_list: Iterable[Region], tile: Tile) -> Region | None:
    """The region holding ``tile`` (None if no region does)."""
    for r in regions_list:
        if tuple(tile) in r.tiles:
            return r
    return None


def needs_realignment(sessions: int, incremental: int, share: float) -> bool:
    """Whether an alignment adding sessions to a region should re-align the region jointly: the region's
    ``sessions`` (those with a submap in it, the arriving ones included) of which ``incremental`` were, or
    are about to be, aligned against a held map; at least ``share`` of them (``FusionConfig.realign_share``).
    A region of one session has nothing to re-align."""
    return sessions >= 2 and incremental > 0 and incremental >= share * sessions
