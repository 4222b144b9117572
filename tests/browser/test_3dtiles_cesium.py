"""CesiumJS (pinned in tests/browser/js, installed by .ci/run) renders /v1/3dtiles headless.

The API runs on one origin (uvicorn on 127.0.0.1), the viewer page and the Cesium build on another, so
the page loads the tileset as a user's own viewer would: cross-origin, with a reader token in the
``Authorization`` header. The map lies where ``FLEETMAP_ORIGIN`` (not the default one) says: the
tileset's bounding sphere and each loaded glTF's own bounding sphere, converted to cartographic by
Cesium, match the tiles' map-frame positions converted by pymap3d; Cesium reads the label names from
the content's metadata; the tiles draw pixels; nothing fails. Screenshot: ``artifacts_dir/cesium.png``.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import socket
import threading
import time
from collections.abc import Iterator
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np
import pymap3d
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient

from fusion.labels import LABELS
from tests.browser.conftest import console_errors
from tests.conftest import issue_token
from tests.js_support import require_package
from tests.service.test_api_3dtiles import SIZE, _fuse, _tile_mesh

pytestmark = pytest.mark.slow

ORIGIN = (35.6812, 139.7671, 40.0)
PAGE = Path(__file__).with_name("cesium_3dtiles.html")
TILES = [(0, 0), (-2, 1)]


@pytest.fixture
def database_url(tmp_path: Path) -> str:
    """One database is enough here (the API tests cover both)."""
    return f"sqlite:///{tmp_path / 'fleetmap.db'}"


@pytest.fixture
def api(make_client: Any) -> TestClient:
    return make_client(origin=",".join(map(str, ORIGIN)), tile_size=SIZE)


@contextlib.contextmanager
def _serve_app(app: FastAPI) -> Iterator[str]:
    """The app on 127.0.0.1 (its lifespan already entered by the test client)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, lifespan="off", log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert server.started, "uvicorn did not start"
    try:
        yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    finally:
        server.should_exit = True
        thread.join(10)


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base class's name)
        pass


@contextlib.contextmanager
def _serve_page(site: Path) -> Iterator[str]:
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(site)))
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def _expected(points: np.ndarray) -> np.ndarray:
    """Longitude, latitude (radians) and height of the centre of a map-frame box of points."""
    centre = (points.min(axis=0) + points.max(axis=0)) / 2
    lat, lon, alt = pymap3d.enu2geodetic(*centre.astype(np.float64), *ORIGIN)
    return np.array([np.radians(lon), np.radians(lat), alt])


def test_cesium_renders_the_fused_map_where_the_origin_says(
    chromium_driver: Any, api: TestClient, tmp_path: Path, artifacts_dir: Path
) -> None:
    cesium = require_package("cesium") / "Build" / "Cesium"
    auth = {"vehicle": issue_token(api, "vehicle", "veh-042"), "reader": issue_token(api, "reader", "viewer")}
    meshes = {(i, j): _tile_mesh(i, j) for i, j in TILES}
    for (i, j), mesh in meshes.items():
        _fuse(api, auth, i, j, 1, mesh)
    token = auth["reader"]["Authorization"].removeprefix("Bearer ")

    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_bytes(PAGE.read_bytes())
    (site / "cesium").symlink_to(cesium, target_is_directory=True)
    with _serve_app(api.app) as api_url, _serve_page(site) as page_url:
        chromium_driver.set_script_timeout(90)
        chromium_driver.get(f"{page_url}/index.html")
        result = chromium_driver.execute_async_script(
            "const done = arguments[arguments.length - 1];"
            "loadTileset(arguments[0], arguments[1]).then(done, (e) => done({failed: String(e && e.stack || e)}));",
            f"{api_url}/v1/3dtiles/tileset.json",
            token,
        )
        severe = console_errors(chromium_driver)
    if result.get("png"):
        (artifacts_dir / "cesium.png").write_bytes(base64.b64decode(result["png"].split(",", 1)[1]))

    assert "failed" not in result, result.get("failed")
    assert result["errors"] == [] and severe == [], (result["errors"], severe)
    # the tileset's bounding sphere: the centre of all tiles' meshes
    everything = np.vstack([m.vertices for m in meshes.values()])
    centre = np.array(result["centre"])
    np.testing.assert_allclose(centre[:2], _expected(everything)[:2], rtol=0, atol=1e-8)
    assert abs(centre[2] - _expected(everything)[2]) < 0.1
    # each tile's glTF, placed by Cesium (y-up → z-up, node, root transform), sits on its mesh
    assert sorted(tuple(t["extras"]["tile"]) for t in result["tiles"]) == sorted(meshes)
    for tile in result["tiles"]:
        mesh = meshes[tuple(tile["extras"]["tile"])]
        got, want = np.array(tile["contentCentre"]), _expected(mesh.vertices)
        np.testing.assert_allclose(got[:2], want[:2], rtol=0, atol=1e-8)  # ~6 cm
        assert abs(got[2] - want[2]) < 0.05
        assert tile["triangles"] == len(mesh.faces)
        assert tile["names"] == [label.name for label in LABELS]  # EXT_structural_metadata, read by Cesium
    # the tiles drew pixels of their own
    assert result["drawn"] > 0.01 * result["pixels"], result["drawn"]
