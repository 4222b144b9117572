"""The viewer's files: served without a token from the package, every module it imports resolvable
on this server alone (offline, no CDN), the vendored three.js intact, all of it in the wheel.

The viewer's behaviour in a browser: tests/browser/test_viewer.py."""

from __future__ import annotations

import glob
import hashlib
import json
import re
import tomllib
from pathlib import Path
from urllib.parse import urljoin, urlparse

from fastapi.testclient import TestClient

STATIC = Path(__file__).resolve().parents[2] / "service" / "api" / "static"
PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"
IMPORT = re.compile(r"""(?:^|[\s;}])(?:import|export)\s*(?:[^'";]*?\sfrom\s*)?["']([^"']+)["']""", re.M)
JS_TYPES = ("text/javascript", "application/javascript")


def _import_map(page: str) -> dict[str, str]:
    match = re.search(r'<script type="importmap">(.*?)</script>', page, re.S)
    assert match, "the page has no import map"
    imports: dict[str, str] = json.loads(match.group(1))["imports"]
    return imports


def _resolve(specifier: str, base: str, imports: dict[str, str]) -> str:
    """A module specifier as the browser resolves it (import map for bare names, else relative)."""
    if specifier.startswith(("./", "../", "/")):
        return urljoin(base, specifier)
    if specifier in imports:
        return urljoin("http://testserver/", imports[specifier])
    prefix = max((k for k in imports if k.endswith("/") and specifier.startswith(k)), key=len, default=None)
    assert prefix is not None, f"bare specifier {specifier!r} is not in the import map"
    return urljoin("http://testserver/", imports[prefix] + specifier[len(prefix):])


def test_every_module_the_page_imports_is_served_here(client: TestClient) -> None:
    page = client.get("/").text
    imports = _import_map(page)
    entry = re.findall(r'<script type="module" src="([^"]+)"', page)
    assert entry == ["./static/viewer/main.js"]
    todo, seen = [urljoin("http://testserver/", e) for e in entry], set()
    while todo:
        url = todo.pop()
        if url in seen:
            continue
        seen.add(url)
        assert urlparse(url).netloc == "testserver", f"{url} is not on this server"
        resp = client.get(urlparse(url).path)  # no token: static files are public
        assert resp.status_code == 200, url
        assert resp.headers["content-type"].startswith(JS_TYPES), (url, resp.headers["content-type"])
        todo += [_resolve(spec, url, imports) for spec in IMPORT.findall(resp.text)]
    paths = {urlparse(u).path for u in seen}
    assert {
        "/static/viewer/main.js",
        "/static/viewer/map.js",
        "/static/vendor/three/build/three.module.js",
        "/static/vendor/three/build/three.core.js",
        "/static/vendor/three/examples/jsm/controls/OrbitControls.js",
    } <= paths
    for text in [page, *(p.read_text() for p in (STATIC / "viewer").glob("*.js"))]:
        assert not re.search(r"https?://", text), "the viewer must not load anything from another host"


def test_the_import_walker_resolves_like_a_browser() -> None:
    imports = {"three": "./static/three.js", "three/addons/": "./static/addons/"}
    base = "http://testserver/static/viewer/map.js"
    assert _resolve("three", base, imports) == "http://testserver/static/three.js"
    assert _resolve("three/addons/controls/O.js", base, imports) == "http://testserver/static/addons/controls/O.js"
    assert _resolve("./api.js", base, imports) == "http://testserver/static/viewer/api.js"
    source = 'import * as T from "three";\nimport { a } from \'./a.js\';\nexport * from "./b.js";\nimport "./c.js";'
    assert IMPORT.findall(source) == ["three", "./a.js", "./b.js", "./c.js"]


def test_static_files_are_public_and_outside_the_schema(client: TestClient) -> None:
    assert client.get("/static/viewer/main.js").status_code == 200
    for path in ("/static/nope.js", "/static/../app.py", "/static/"):
        resp = client.get(path)
        assert resp.status_code == 404 and resp.headers["content-type"].startswith("application/problem+json")
    assert not [p for p in client.get("/openapi.json").json()["paths"] if p.startswith("/static")]


def test_vendored_three_is_what_its_readme_says() -> None:
    root = STATIC / "vendor" / "three"
    version = (root / "VERSION").read_text().strip()
    readme = (root / "README.md").read_text()
    assert re.fullmatch(r"\d+\.\d+\.\d+", version) and f"`three@{version}`" in readme
    assert re.search(r"integrity: `sha512-[A-Za-z0-9+/=]{88}`", readme)
    listed = dict(re.findall(r"^\| `([^`]+)` \| `([0-9a-f]{64})` \|$", readme, re.M))
    assert "LICENSE" in listed and "build/three.module.js" in listed
    for name, digest in listed.items():
        assert hashlib.sha256((root / name).read_bytes()).hexdigest() == digest, f"{name} was changed by hand"
    vendored = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
    assert vendored == set(listed) | {"README.md", "VERSION"}
    assert "MIT License" in (root / "LICENSE").read_text()


def test_every_static_file_ships_in_the_wheel() -> None:
    patterns = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-data"]["service.api"]
    package = STATIC.parent
    packaged = {f for pattern in patterns for f in glob.glob(pattern, root_dir=package, recursive=True)}
    files = {p.relative_to(package).as_posix() for p in STATIC.rglob("*") if p.is_file()}
    assert files and files <= packaged, sorted(files - packaged)
