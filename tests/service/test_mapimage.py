"""``fleetmap map-image``: label colours land where the faces are, highest on top; a valid PNG."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fusion.labels import LABELS
from fusion.types import FusedMesh
from service.client.mapimage import BACKGROUND, MapData, main, rasterise, render
from tests.scene import ground

ROAD, SIDEWALK, BUILDING = LABELS[1], LABELS[2], LABELS[5]
COLOURS = {label.id: label.color for label in LABELS}


def _square(x: float, y: float, size: float, z: float, label: int) -> FusedMesh:
    """A flat square of 0.5 m faces at height ``z`` (map frame), all labelled ``label``."""
    g = ground(size, 0.5, z)
    v = np.asarray(g.vertices, np.float32) + np.array([x, y, 0.0], np.float32)
    f = np.asarray(g.faces, np.int32)
    return FusedMesh(v, f, np.full(len(v), label, np.uint8), np.ones(len(v), np.float32), np.full(len(f), label, np.uint8))


def _scene() -> list[FusedMesh]:
    # the roof comes first: painter's order is by height, not by the order of the meshes
    return [_square(4, 4, 2, 5.0, BUILDING.id), _square(0, 0, 10, 0.0, ROAD.id), _square(20, 20, 10, 0.2, SIDEWALK.id)]


def _at(image: np.ndarray, x: float, y: float, pixel_m: float) -> tuple[int, ...]:
    return tuple(int(c) for c in image[int(y / pixel_m), int(x / pixel_m)])


def test_label_colours_land_under_their_faces_highest_on_top() -> None:
    image = rasterise(_scene(), COLOURS, (0.0, 0.0, 32.0, 32.0), 0.5)
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert _at(image, 1.2, 1.3, 0.5) == ROAD.color == _at(image, 9.7, 2.2, 0.5)
    assert _at(image, 5.0, 5.0, 0.5) == BUILDING.color  # the roof hides the road under it
    assert _at(image, 25.3, 24.1, 0.5) == SIDEWALK.color
    assert _at(image, 15.0, 15.0, 0.5) == BACKGROUND == _at(image, 5.0, 25.0, 0.5)
    # no holes between the samples: every pixel under the road square is drawn
    assert np.all(np.any(image[1:19, 1:19] != BACKGROUND, axis=-1))
    # row 0 is the south edge: the road (south-west) is in the first rows, the sidewalk in the last
    assert _at(image, 1.0, 1.0, 0.5) == tuple(int(c) for c in image[2, 2])


def _pose(x: float, y: float) -> dict:
    return {"t": [x, y, 0.0], "q": [1.0, 0.0, 0.0, 0.0]}


def test_render_writes_a_png_with_the_map_and_trajectories(tmp_path: Path) -> None:
    rows = [{"seq": k, "id": str(k), "pose_gps": _pose(2 + 3 * k, 3 + k), "pose_refined": _pose(1 + 3 * k, 2 + k)}
            for k in range(4)]
    data = MapData(32.0, {label.id: (label.name, label.color) for label in LABELS}, {(0, 0): _scene()[1],
                   (1, 1): FusedMesh.empty(), (0, 1): _scene()[0]}, {"veh-1/run": rows})
    out = render(data, tmp_path / "map.png")
    raw = out.read_bytes()
    assert raw.startswith(b"\x89PNG\r\n\x1a\n")
    pixels = np.asarray(Image.open(io.BytesIO(raw)).convert("RGB")).reshape(-1, 3)
    colours = {tuple(int(c) for c in p) for p in np.unique(pixels, axis=0)}
    assert ROAD.color in colours and BUILDING.color in colours
    assert SIDEWALK.color not in colours  # no sidewalk face in this map (the legend lists only labels drawn)


def test_cli_reports_an_unreachable_service_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--url", "http://127.0.0.1:9", "--out", str(tmp_path / "m.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fleetmap map-image: error: cannot reach") and "\n" not in err
    assert main(["--url", "http://127.0.0.1:9", "--out", str(tmp_path / "missing" / "m.png")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    assert not (tmp_path / "m.png").exists()
