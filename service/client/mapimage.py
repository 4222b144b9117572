"""``fleetmap map-image``: a top-down semantic picture of the served map (PNG).

Built only from what the HTTP API serves: the label set (``GET /v1/labels``), every fused tile's mesh
(``GET /v1/tiles/{i}/{j}/mesh``, PLY, map frame) and sessions' poses (``GET
/v1/sessions/{id}/poses``). Faces are coloured by their label, the highest surface on top (painter's
order by height: a roof hides the road under it), with the tile grid and, per session, its GPS
trajectory (dashed) and its refined one (solid). ``fleetmap demo`` draws its ``map.png`` with it.

Rasterisation is numpy (a few samples per face, the highest sample per pixel wins), the figure
matplotlib (Agg); torch-free, so the demo's client process stays small.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
import numpy as np

from fusion.meshio import read_fused_ply
from fusion.types import FusedMesh

TileKey = tuple[int, int]
BACKGROUND = (236, 236, 232)  # no data; unlike every default label colour (lane markings are white)
MAX_PIXELS = 1600  # raster size along the longer side
# barycentric sample points per face: the centroid and one towards each corner (a face a pixel or two
# wide covers the pixels under it)
SAMPLES = np.array([[1 / 3, 1 / 3, 1 / 3], [2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])


class MapImageError(Exception):
    """A user-facing failure (server unreachable, an HTTP error, nothing to draw): one line."""


@dataclass
class MapData:
    """What the picture is drawn from, all map frame (metres). ``tiles``: the fused tiles (an empty
    mesh for a tile fused empty); ``labels``: id → (name, RGB); ``poses``: session id → the rows of
    ``GET /v1/sessions/{id}/poses`` (``seq``, ``pose_gps``, ``pose_refined``)."""

    tile_size: float
    labels: dict[int, tuple[str, tuple[int, int, int]]]
    tiles: dict[TileKey, FusedMesh]
    poses: dict[str, list[dict[str, Any]]] = field(default_factory=dict)


def labels_from_json(rows: list[dict[str, Any]]) -> dict[int, tuple[str, tuple[int, int, int]]]:
    """``GET /v1/labels`` → id → (name, RGB)."""
    return {int(r["id"]): (str(r["name"]), (int(r["color"][0]), int(r["color"][1]), int(r["color"][2]))) for r in rows}


def fetch(client: httpx.Client, sessions: Sequence[str] = ()) -> MapData:
    """Download the label set, every fused tile's mesh and ``sessions``' poses from the service."""
    labels = labels_from_json(_get(client, "/v1/labels").json())
    tile_size = float(_get(client, "/v1/capabilities").json()["tile_size_m"])
    meshes: dict[TileKey, FusedMesh] = {}
    cursor: str | None = None
    while True:
        page = _get(client, "/v1/tiles", {"limit": 1000, **({"cursor": cursor} if cursor else {})}).json()
        for t in page["items"]:
            if t["version"]:
                meshes[(t["i"], t["j"])] = read_fused_ply(_get(client, f"/v1/tiles/{t['i']}/{t['j']}/mesh").content)
        cursor = page.get("next_cursor")
        if not cursor:
            break
    poses = {s: _get(client, f"/v1/sessions/{quote(s, safe='')}/poses").json() for s in sessions}
    return MapData(tile_size, labels, meshes, poses)


def _get(client: httpx.Client, path: str, params: dict[str, Any] | None = None) -> httpx.Response:
    try:
        response = client.get(path, params=params)
    except httpx.HTTPError as exc:
        raise MapImageError(f"cannot reach {client.base_url}: {exc}") from exc
    if response.status_code != 200:
        try:
            detail = response.json().get("detail") or response.json().get("title")
        except ValueError:
            detail = response.text[:200]
        raise MapImageError(f"GET {path}: {response.status_code} {detail}")
    return response


def map_bounds(data: MapData) -> tuple[float, float, float, float]:
    """``(xmin, ymin, xmax, ymax)``: the fused tiles' squares (metres, map frame)."""
    if not data.tiles:
        raise MapImageError("no fused tile to draw")
    s = data.tile_size
    i = [k[0] for k in data.tiles]
    j = [k[1] for k in data.tiles]
    return min(i) * s, min(j) * s, (max(i) + 1) * s, (max(j) + 1) * s


def rasterise(
    meshes: Sequence[FusedMesh],
    colours: dict[int, tuple[int, int, int]],
    bounds: tuple[float, float, float, float],
    pixel_m: float,
) -> np.ndarray:
    """Top-down picture (H, W, 3) uint8 of ``meshes`` over ``bounds`` (map frame, metres) at ``pixel_m``
    metres per pixel; row 0 is the south edge (``ymin``). Each pixel shows the label colour of the
    highest face sample above it (painter's order by height), ``BACKGROUND`` where there is none."""
    x0, y0, x1, y1 = bounds
    width, height = max(1, int(np.ceil((x1 - x0) / pixel_m))), max(1, int(np.ceil((y1 - y0) / pixel_m)))
    image = np.empty((height * width, 3), np.uint8)
    image[:] = BACKGROUND
    palette = np.tile(np.array(BACKGROUND, np.uint8), (256, 1))
    for label, rgb in colours.items():
        palette[label] = rgb
    pix, z, lab = [], [], []
    for mesh in meshes:
        if not len(mesh.faces):
            continue
        corners = mesh.vertices[mesh.faces].astype(np.float64)  # (m, 3 corners, 3)
        pts = np.einsum("sc,mcd->msd", SAMPLES, corners).reshape(-1, 3)  # (m·4, 3)
        col = np.floor((pts[:, 0] - x0) / pixel_m).astype(np.int64)
        row = np.floor((pts[:, 1] - y0) / pixel_m).astype(np.int64)
        inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
        pix.append((row * width + col)[inside])
        z.append(pts[inside, 2])
        lab.append(np.repeat(mesh.face_labels, len(SAMPLES))[inside])
    if pix:
        p, h, lb = np.concatenate(pix), np.concatenate(z), np.concatenate(lab)
        order = np.lexsort((h, p))  # by pixel, then height: the last of each pixel is the highest
        p, lb = p[order], lb[order]
        top = np.flatnonzero(np.r_[p[1:] != p[:-1], True])
        image[p[top]] = palette[lb[top]]
    return image.reshape(height, width, 3)


def _pixel_size(meshes: Sequence[FusedMesh], bounds: tuple[float, float, float, float]) -> float:
    """Metres per pixel: about a face's size (finer leaves holes between the samples), at most
    ``MAX_PIXELS`` along the longer side."""
    edges = [np.linalg.norm(m.vertices[m.faces[:2000, 1]] - m.vertices[m.faces[:2000, 0]], axis=1)
             for m in meshes if len(m.faces)]
    face = float(np.median(np.concatenate(edges))) if edges else 0.0
    return max((max(bounds[2] - bounds[0], bounds[3] - bounds[1])) / MAX_PIXELS, 0.7 * face)


def _trajectory(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    """(n, 2) map-frame x/y of the poses ``key`` (``pose_gps``/``pose_refined``) in ``seq`` order."""
    pts = [r[key]["t"][:2] for r in sorted(rows, key=lambda r: r["seq"]) if r.get(key)]
    return np.asarray(pts, float).reshape(-1, 2)


def render(data: MapData, out: Path, title: str | None = None) -> Path:
    """Draw ``data`` into the PNG ``out``: the semantic raster, tile grid and names, GPS (dashed) and
    refined (solid) trajectories per session, a legend of the labels drawn and the sessions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patheffects as effects
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    bounds = map_bounds(data)
    meshes = list(data.tiles.values())
    image = rasterise(meshes, {k: v[1] for k, v in data.labels.items()}, bounds, _pixel_size(meshes, bounds))
    x0, y0, x1, y1 = bounds
    fig, ax = plt.subplots(figsize=(10.5, 8.0), dpi=100)
    ax.imshow(image, origin="lower", extent=(x0, x1, y0, y1), interpolation="nearest")
    s = data.tile_size
    for x in np.arange(x0, x1 + s / 2, s):
        ax.axvline(x, color="0.35", lw=0.6, zorder=2)
    for y in np.arange(y0, y1 + s / 2, s):
        ax.axhline(y, color="0.35", lw=0.6, zorder=2)
    for i, j in data.tiles:
        ax.text(i * s + 1.5, j * s + 1.5, f"({i},{j})", fontsize=7, color="0.2", zorder=3,
                bbox={"facecolor": "white", "alpha": 0.75, "linewidth": 0, "pad": 1.0})
    halo = [effects.withStroke(linewidth=3.0, foreground="white")]
    handles: list[Any] = []
    colours = [plt.get_cmap("tab10")(k) for k in range(10)]
    for k, (session, rows) in enumerate(sorted(data.poses.items())):
        colour = colours[k % len(colours)]
        gps, refined = _trajectory(rows, "pose_gps"), _trajectory(rows, "pose_refined")
        ax.plot(gps[:, 0], gps[:, 1], "--", color=colour, lw=1.4, marker=".", ms=5, path_effects=halo, zorder=4)
        if len(refined):
            ax.plot(refined[:, 0], refined[:, 1], "-", color=colour, lw=1.8, marker="o", ms=3.5, path_effects=halo,
                    zorder=5)
        handles.append(Line2D([], [], color=colour, lw=1.8, label=session))
    if handles:
        handles += [Line2D([], [], color="0.2", ls="--", label="GPS poses"),
                    Line2D([], [], color="0.2", ls="-", label="refined poses")]
    drawn = set(np.unique(np.concatenate([m.face_labels for m in meshes])).tolist()) if meshes else set()
    handles += [Patch(facecolor=(rgb[0] / 255, rgb[1] / 255, rgb[2] / 255), edgecolor="0.5", label=name)
                for label, (name, rgb) in sorted(data.labels.items()) if label in drawn]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("x east (m, map frame)")
    ax.set_ylabel("y north (m)")
    ax.set_title(title or f"fleetmap: {len(data.tiles)} fused tiles, {len(data.poses)} session(s)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fleetmap map-image", description=__doc__.splitlines()[0])
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="the service's base URL")
    parser.add_argument("--out", type=Path, default=Path("map.png"), help="PNG to write (default map.png)")
    parser.add_argument("--session", action="append", default=[], metavar="ID",
                        help="draw this session's GPS and refined trajectories (repeatable)")
    parser.add_argument("--token", default=None, help="bearer token (a reader's), unless auth is off")
    args = parser.parse_args(argv)
    try:
        if not args.out.parent.resolve().is_dir():
            raise MapImageError(f"{args.out.parent} is not a directory")
        headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
        with httpx.Client(base_url=args.url, headers=headers, timeout=60) as client:
            data = fetch(client, args.session)
        render(data, args.out)
    except httpx.InvalidURL as exc:
        print(f"fleetmap map-image: error: invalid --url {args.url!r}: {exc}", file=sys.stderr)
        return 2
    except MapImageError as exc:
        print(f"fleetmap map-image: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({len(data.tiles)} tiles, {len(data.poses)} sessions)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
