"""The 3D viewer at ``/`` in a real browser (headless Chromium, WebGL by SwiftShader).

One real server for the module (uvicorn on a free loopback port, SQLite, auth on) holds three fused
tiles stored the way a fusion stores them (no torch): (0, 0) and (1, 0) side by side, where the page
opens (``#view=``), and (6, 0) far east, out of that view; and three sessions. Each test opens the
page, connects with a token typed into the token box and reads the page through its test hook
``window.fleetmapViewer`` and the canvas' pixels.
"""

from __future__ import annotations

import base64
import contextlib
import io
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import uvicorn
from fastapi.testclient import TestClient
from PIL import Image

from fusion.labels import LABEL_BY_NAME
from fusion.meshio import filter_confidence, write_fused_ply
from fusion.types import FusedMesh
from service.api.app import create_app
from service.settings import Settings
from service.store.models import Submap, Tile
from tests.browser.conftest import console_errors
from tests.conftest import issue_token, publish_version, upload_at

TILE = 64.0
CELL = 2.0  # metres per grid cell of the test meshes
ROAD = LABEL_BY_NAME["road"]
SESSIONS = {
    "veh-042/a": [(8.0, 30.0), (40.0, 31.0), (72.0, 32.0), (104.0, 33.0)],
    "veh-042/b": [(20.0, 40.0), (90.0, 38.0)],
    "veh-042/c": [(400.0, 32.0)],  # in the far tile (6, 0)
}
HOME = "#view=64,32,128"  # centre and span (metres) of tiles (0, 0) and (1, 0)
FAR = "#view=416,32,128"  # tile (6, 0)


def street(i: int, j: int, *, cell: float = CELL) -> FusedMesh:
    """A flat street across tile (i, j) (map frame, metres): a road along x (y in [24, 40)) with
    sidewalks either side and terrain beyond; vertices are confident (0.9) except the north rim
    (y ≥ 56: 0.4) and the south rim (y < 8: 0.6), so the default threshold 0.7 hides both."""
    n = int(TILE / cell)
    xs, ys = np.meshgrid(np.arange(n + 1) * cell, np.arange(n + 1) * cell)
    vertices = np.stack([xs.ravel() + i * TILE, ys.ravel() + j * TILE, np.zeros(xs.size)], 1).astype(np.float32)
    local_y = ys.ravel()
    confidence = np.where(local_y >= 56, 0.4, np.where(local_y < 8, 0.6, 0.9)).astype(np.float32)
    faces, labels = [], []
    for r in range(n):
        for c in range(n):
            a, b, d, e = r * (n + 1) + c, r * (n + 1) + c + 1, (r + 1) * (n + 1) + c, (r + 1) * (n + 1) + c + 1
            y = (r + 0.5) * cell
            label = ROAD.id if 24 <= y < 40 else (LABEL_BY_NAME["sidewalk"].id if 18 <= y < 46 else 4)
            faces += [[a, b, e], [a, e, d]]
            labels += [label, label]
    face_labels = np.array(labels, np.uint8)
    vertex_labels = np.full(len(vertices), 4, np.uint8)
    return FusedMesh(vertices, np.array(faces, np.int32), vertex_labels, confidence, face_labels)


def drawn(mesh: FusedMesh, min_confidence: float, hidden: tuple[int, ...] = ()) -> int:
    """Triangles the viewer should draw: the API's own confidence filter, then the hidden labels."""
    kept = filter_confidence(mesh, min_confidence)
    return int(np.isin(kept.face_labels, hidden, invert=True).sum())


class MeshRequests:
    """ASGI wrapper recording the status of every mesh request the server answers."""

    def __init__(self, app: Any) -> None:
        self.app = app
        self.seen: list[tuple[str, int]] = []

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or not scope["path"].endswith("/mesh"):
            await self.app(scope, receive, send)
            return

        async def record(message: Any) -> None:
            if message["type"] == "http.response.start":
                self.seen.append((scope["path"], message["status"]))
            await send(message)

        await self.app(scope, receive, record)


@dataclass
class Server:
    url: str
    app: Any
    tokens: dict[str, str]
    meshes: MeshRequests
    fused: dict[tuple[int, int], FusedMesh] = field(default_factory=dict)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    tmp = tmp_path_factory.mktemp("viewer")
    settings = Settings(
        data_dir=tmp / "data", database_url=f"sqlite:///{tmp / 'fleetmap.db'}", broker_url="", auth="on"
    )
    setup = create_app(settings, migrate=True, background=False)
    fused = {(0, 0): street(0, 0), (1, 0): street(1, 0), (6, 0): street(6, 0)}
    with TestClient(setup) as client:
        vehicle = issue_token(client, "vehicle", "veh-042")
        tokens = {
            role: issue_token(client, role, f"viewer-{role}")["Authorization"].removeprefix("Bearer ")
            for role in ("reader", "operator")
        }
        for session, points in SESSIONS.items():
            for seq, (x, y) in enumerate(points):
                upload_at(client, vehicle, x, y, seq, session)
        with setup.state.session_factory() as db:
            for row in db.query(Submap).filter(Submap.session_id == "veh-042/a"):
                x, y, z = row.pose_gps["t"]
                row.pose_refined = {"t": [x + 1.0, y - 1.5, z], "q": [1.0, 0.0, 0.0, 0.0]}
            db.commit()
        for (i, j), mesh in fused.items():
            publish_version(setup, i, j, 1, mesh, metrics={"faces": len(mesh.faces), "vertices": len(mesh.vertices)})

    app = create_app(settings, migrate=False, background=False)
    meshes = MeshRequests(app)
    with serving(meshes) as url:
        yield Server(url, app, tokens, meshes, fused)


@contextlib.contextmanager
def serving(app: Any) -> Iterator[str]:
    """``app`` under uvicorn on a free loopback port (a thread); yields its base URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    uv = uvicorn.Server(uvicorn.Config(app, log_level="warning", lifespan="on"))
    thread = threading.Thread(target=uv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not uv.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}/"
    finally:
        uv.should_exit = True
        thread.join(timeout=10)
        sock.close()


def wait_for(driver: Any, script: str, timeout: float = 15.0) -> Any:
    """Poll ``return <script>`` until it is truthy; its value."""
    deadline = time.monotonic() + timeout
    while True:
        value = driver.execute_script(f"return {script}")
        if value:
            return value
        if time.monotonic() > deadline:
            errors = driver.execute_script("return window.fleetmapViewer && window.fleetmapViewer.errors")
            raise AssertionError(f"timed out waiting for {script!r}; page errors: {errors}; console: {console_errors(driver)}")
        time.sleep(0.1)


def settle(driver: Any) -> None:
    """Wait until the page has rendered what it holds now (two animation frames)."""
    driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "requestAnimationFrame(() => requestAnimationFrame(() => done(true)));"
    )


def open_viewer(driver: Any, server: Server, role: str = "reader", view: str = HOME) -> None:
    """Open the page at ``view``, type the token, connect, and wait for the two tiles in view."""
    from selenium.webdriver.common.by import By

    driver.get(server.url + view)
    wait_for(driver, "window.fleetmapViewer && document.getElementById('connect')")
    box = driver.find_element(By.ID, "token")
    box.clear()
    box.send_keys(server.tokens[role])
    driver.find_element(By.ID, "connect").click()
    wait_for(driver, "window.fleetmapViewer.ready && window.fleetmapViewer.tilesLoaded === 2")
    settle(driver)


def canvas_pixels(driver: Any) -> np.ndarray:
    from selenium.webdriver.common.by import By

    png = driver.find_element(By.ID, "view").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def count_colour(pixels: np.ndarray, rgb: tuple[int, int, int], tolerance: int = 6) -> int:
    return int((np.abs(pixels - np.array(rgb)).max(axis=2) <= tolerance).sum())


def set_slider(driver: Any, value: float) -> None:
    driver.execute_script(
        "const s = document.getElementById('confidence'); s.value = arguments[0];"
        "s.dispatchEvent(new Event('input', {bubbles: true}));",
        str(value),
    )


def test_viewer_draws_fused_tiles_in_label_colours(
    chromium_driver: Any, server: Server, artifacts_dir: Path
) -> None:
    open_viewer(chromium_driver, server)
    try:
        pixels = canvas_pixels(chromium_driver)
        assert pixels.std() > 10, "the canvas is blank"
        assert count_colour(pixels, ROAD.color) > 2000, "no road-coloured pixels on the canvas"
        expected = drawn(server.fused[(0, 0)], 0.7) + drawn(server.fused[(1, 0)], 0.7)
        assert chromium_driver.execute_script("return window.fleetmapViewer.triangleCount()") == expected
        states = chromium_driver.execute_script("return window.fleetmapViewer.tiles()")
        assert {(t["i"], t["j"]): t["state"] for t in states} == {(0, 0): "fused", (1, 0): "fused"}
        legend = chromium_driver.execute_script(
            "return [...document.querySelectorAll('#legend label')].map(l => l.textContent.trim())"
        )
        assert legend[:3] == ["unlabeled", "road", "sidewalk"]
        sessions = chromium_driver.execute_script(
            "return [...document.querySelectorAll('#sessions label')].map(l => l.textContent.trim())"
        )
        assert sessions == ["veh-042/a", "veh-042/b"]
        assert console_errors(chromium_driver) == []
        assert chromium_driver.execute_script("return window.fleetmapViewer.errors") == []
    finally:
        chromium_driver.save_screenshot(str(artifacts_dir / "viewer.png"))


def test_confidence_slider_and_label_toggle(chromium_driver: Any, server: Server) -> None:
    open_viewer(chromium_driver, server)
    meshes = [server.fused[(0, 0)], server.fused[(1, 0)]]
    count: Callable[[], int] = lambda: chromium_driver.execute_script("return window.fleetmapViewer.triangleCount()")  # noqa: E731
    at_default = count()
    assert at_default == sum(drawn(m, 0.7) for m in meshes)
    for threshold in (0.0, 0.5, 0.95):
        set_slider(chromium_driver, threshold)
        assert count() == sum(drawn(m, threshold) for m in meshes), threshold
    assert count() == 0  # nothing is that confident
    set_slider(chromium_driver, 0.7)
    assert count() == at_default

    settle(chromium_driver)
    assert count_colour(canvas_pixels(chromium_driver), ROAD.color) > 2000
    chromium_driver.execute_script(f"document.querySelector('#legend input[data-label=\"{ROAD.id}\"]').click()")
    assert count() == sum(drawn(m, 0.7, hidden=(ROAD.id,)) for m in meshes) < at_default
    settle(chromium_driver)
    assert count_colour(canvas_pixels(chromium_driver), ROAD.color) == 0, "road still drawn after hiding it"
    assert console_errors(chromium_driver) == []


def test_unchanged_tiles_are_not_downloaded_again(chromium_driver: Any, server: Server) -> None:
    server.meshes.seen.clear()
    open_viewer(chromium_driver, server)
    assert sorted(server.meshes.seen) == [("/v1/tiles/0/0/mesh", 200), ("/v1/tiles/1/0/mesh", 200)]
    triangles = chromium_driver.execute_script("return window.fleetmapViewer.triangleCount()")

    # revalidating (same version): If-None-Match → 304, nothing downloaded
    chromium_driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "window.fleetmapViewer.refresh({revalidate: true}).then(() => done(true), e => done(String(e)));"
    )
    assert sorted(server.meshes.seen[2:]) == [("/v1/tiles/0/0/mesh", 304), ("/v1/tiles/1/0/mesh", 304)]

    # a reload of the page: the ETags and bodies come from the browser's cache storage → 304 again
    chromium_driver.refresh()
    wait_for(chromium_driver, "window.fleetmapViewer.ready && window.fleetmapViewer.tilesLoaded === 2")
    assert sorted(server.meshes.seen[4:]) == [("/v1/tiles/0/0/mesh", 304), ("/v1/tiles/1/0/mesh", 304)]
    assert chromium_driver.execute_script("return window.fleetmapViewer.triangleCount()") == triangles
    statuses = chromium_driver.execute_script("return window.fleetmapViewer.meshRequests.map(r => r.status)")
    assert statuses == [304, 304]
    assert console_errors(chromium_driver) == []


def click_map(driver: Any, x: float, y: float) -> None:
    """Click the canvas where map-frame point (x, y, 0) is drawn."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    canvas = driver.find_element(By.ID, "view")
    at = driver.execute_script("return window.fleetmapViewer.screenOf(arguments[0], arguments[1], 0)", x, y)
    size = canvas.size
    ActionChains(driver).move_to_element_with_offset(
        canvas, int(at["x"] - size["width"] / 2), int(at["y"] - size["height"] / 2)
    ).click().perform()


def test_tile_panel_for_a_reader(chromium_driver: Any, server: Server) -> None:
    open_viewer(chromium_driver, server)
    click_map(chromium_driver, 96.0, 32.0)  # tile (1, 0), on the road
    wait_for(chromium_driver, "document.querySelector('#versions tbody tr') && document.querySelector('#submaps tbody tr')")
    panel = chromium_driver.execute_script("return document.getElementById('panel').innerText")
    assert "Tile (1, 0)" in panel and "fused" in panel and "2048" in panel
    submaps = chromium_driver.execute_script(
        "return [...document.querySelectorAll('#submaps tbody tr')].map(r => r.cells[0].textContent + '#' + r.cells[1].textContent)"
    )
    assert submaps == ["veh-042/a#2", "veh-042/a#3", "veh-042/b#1"]
    assert console_errors(chromium_driver) == []

    chromium_driver.execute_script("document.getElementById('refuse').click()")
    message = wait_for(chromium_driver, "document.getElementById('panel-msg').textContent")
    assert message == "role 'reader' may not do this (needs operator)"
    # the browser reports the refused request itself; nothing else went wrong
    errors = console_errors(chromium_driver)
    assert len(errors) == 1 and "/v1/tiles/1/0/fuse" in errors[0] and "403" in errors[0], errors


def test_tile_panel_for_an_operator(chromium_driver: Any, server: Server, artifacts_dir: Path) -> None:
    open_viewer(chromium_driver, server, role="operator")
    click_map(chromium_driver, 20.0, 30.0)  # tile (0, 0)
    wait_for(chromium_driver, "document.querySelector('#versions tbody tr')")
    chromium_driver.execute_script("document.getElementById('refuse').click()")
    status = wait_for(chromium_driver, "document.getElementById('refuse-status') && document.getElementById('refuse-status').textContent.includes('queued') && document.getElementById('refuse-status').textContent")
    assert "align" in status  # the tile holds submaps not aligned yet: its region is aligned first
    chromium_driver.execute_script("document.getElementById('show-jobs').click()")
    jobs = wait_for(chromium_driver, "document.querySelector('#jobs tbody') && [...document.querySelectorAll('#jobs tbody tr')].map(r => r.cells[2].textContent)")
    assert jobs == ["queued"]
    chromium_driver.save_screenshot(str(artifacts_dir / "viewer-panel.png"))
    assert console_errors(chromium_driver) == []


def test_an_invalid_token_is_shown_not_thrown(chromium_driver: Any, server: Server) -> None:
    from selenium.webdriver.common.by import By

    chromium_driver.get(server.url + HOME)
    wait_for(chromium_driver, "window.fleetmapViewer && document.getElementById('connect')")
    chromium_driver.find_element(By.ID, "token").send_keys("fm_not-a-token")
    chromium_driver.find_element(By.ID, "connect").click()
    message = wait_for(chromium_driver, "document.querySelector('#msg.problem') && document.getElementById('msg').textContent")
    assert message == "the bearer token is invalid or revoked (HTTP 401)"
    assert chromium_driver.execute_script("return window.fleetmapViewer.ready") is False
    # only the browser's own notes of the refused requests: no uncaught error
    errors = console_errors(chromium_driver)
    assert errors and all("status of 401" in e for e in errors), errors


def test_ply_reader_matches_the_api_writer(chromium_driver: Any, server: Server) -> None:
    chromium_driver.get(server.url)  # no token yet: the page asks for one and loads nothing
    mesh = street(0, 0, cell=16.0)
    quad = (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
        b"property double z\nproperty uchar label\nelement face 1\nproperty list uchar uint vertex_indices\n"
        b"end_header\n"
        + np.array([(0, 0, 0, 1), (1, 0, 0, 1), (1, 1, 0, 1), (0, 1, 0, 2)], dtype="<f8,<f8,<f8,u1").tobytes()
        + bytes([4]) + np.array([0, 1, 2, 3], "<u4").tobytes()
    )
    script = """
    const [fused, quad, done] = arguments;
    const bytes = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0)).buffer;
    import(new URL("/static/viewer/ply.js", location.href).href).then(({ parsePly }) => {
      const a = parsePly(bytes(fused)), b = parsePly(bytes(quad));
      let ascii = null;
      try { parsePly(new TextEncoder().encode("ply\\nformat ascii 1.0\\nend_header\\n").buffer); }
      catch (e) { ascii = e.message; }
      done({positions: Array.from(a.positions), faces: Array.from(a.faces), faceLabel: Array.from(a.faceLabel),
            confidence: Array.from(a.confidence), quadFaces: Array.from(b.faces),
            quadLabels: Array.from(b.faceLabel), quadConfidence: Array.from(b.confidence), ascii});
    }, (e) => done({error: String(e)}));
    """
    got = chromium_driver.execute_async_script(
        script, base64.b64encode(write_fused_ply(mesh)).decode(), base64.b64encode(quad).decode()
    )
    assert "error" not in got, got
    assert np.allclose(got["positions"], mesh.vertices.ravel())
    assert got["faces"] == mesh.faces.ravel().tolist()
    assert got["faceLabel"] == mesh.face_labels.tolist()
    assert np.allclose(got["confidence"], mesh.vertex_confidence)
    assert got["quadFaces"] == [0, 1, 2, 0, 2, 3]  # a polygon is fanned
    assert got["quadLabels"] == [1, 1]  # no face label: the first vertex's
    assert got["quadConfidence"] == [1, 1, 1, 1]
    assert got["ascii"] == "PLY: format ascii is not binary_little_endian"
    assert console_errors(chromium_driver) == []


def test_only_the_tiles_in_view_are_loaded(chromium_driver: Any, server: Server) -> None:
    server.meshes.seen.clear()
    open_viewer(chromium_driver, server)
    assert sorted(server.meshes.seen) == [("/v1/tiles/0/0/mesh", 200), ("/v1/tiles/1/0/mesh", 200)]
    assert {(t["i"], t["j"]) for t in chromium_driver.execute_script("return window.fleetmapViewer.tiles()")} == {
        (0, 0), (1, 0)
    }
    chromium_driver.execute_script(f"window.location.hash = '{FAR}'")  # a shared link, or panning there
    wait_for(chromium_driver, "window.fleetmapViewer.tilesLoaded === 3")
    assert server.meshes.seen[2:] == [("/v1/tiles/6/0/mesh", 200)]
    # the tiles left behind are kept (hidden), the far one is drawn alone
    wait_for(chromium_driver, f"window.fleetmapViewer.triangleCount() === {drawn(server.fused[(6, 0)], 0.7)}")
    assert console_errors(chromium_driver) == []


def test_live_refresh_shows_a_new_version(chromium_driver: Any, server: Server) -> None:
    open_viewer(chromium_driver, server)
    before = chromium_driver.execute_script("return window.fleetmapViewer.triangleCount()")
    coarse = street(1, 0, cell=4.0)
    publish_version(server.app, 1, 0, 2, coarse)
    with server.app.state.session_factory() as db:
        tile = db.get(Tile, (0, 0))
        assert tile is not None
        tile.state = "fusing"
        db.commit()
    expected = drawn(server.fused[(0, 0)], 0.7) + drawn(coarse, 0.7)
    # the page polls every few seconds: no reload, no click
    wait_for(chromium_driver, f"window.fleetmapViewer.triangleCount() === {expected}", timeout=15)
    assert expected != before
    states = chromium_driver.execute_script("return window.fleetmapViewer.tiles()")
    assert {(t["i"], t["j"]): (t["state"], t["version"]) for t in states} == {
        (0, 0): ("fusing", 1), (1, 0): ("fused", 2)
    }
    assert ("/v1/tiles/1/0/mesh", 200) in server.meshes.seen[-1:]
    assert console_errors(chromium_driver) == []


def test_without_auth_the_viewer_connects_with_no_token(chromium_driver: Any, tmp_path: Path) -> None:
    """``FLEETMAP_AUTH=off`` (``fleetmap demo``): the page says so and the viewer shows the map at once."""
    settings = Settings(data_dir=tmp_path / "data", database_url=f"sqlite:///{tmp_path / 'f.db'}", broker_url="",
                        auth="off")
    setup = create_app(settings, migrate=True, background=False)
    with TestClient(setup) as client:
        upload_at(client, {}, 20.0, 30.0, 0, "veh-042/a")
        publish_version(setup, 0, 0, 1, street(0, 0))
    with serving(create_app(settings, migrate=False, background=False)) as url:
        chromium_driver.get(url + "#view=32,32,80")
        chromium_driver.execute_script("localStorage.clear()")
        chromium_driver.refresh()
        wait_for(chromium_driver, "window.fleetmapViewer && window.fleetmapViewer.ready && window.fleetmapViewer.tilesLoaded === 1")
        settle(chromium_driver)
        assert count_colour(canvas_pixels(chromium_driver), ROAD.color) > 2000
        assert console_errors(chromium_driver) == []
