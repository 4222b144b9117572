"""The browser fixture itself: headless Chromium renders WebGL (the viewer and CesiumJS need it)."""

from __future__ import annotations

from typing import Any

from tests.browser.conftest import console_errors

PAGE = """data:text/html,<canvas id=c width=64 height=64></canvas><script>
const gl = document.getElementById('c').getContext('webgl2');
window.ok = !!gl;
if (gl) {
  gl.clearColor(1, 0, 0, 1); gl.clear(gl.COLOR_BUFFER_BIT);
  const p = new Uint8Array(4); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, p); window.pixel = Array.from(p);
}
</script>"""


def test_headless_chromium_has_webgl2(chromium_driver: Any) -> None:
    chromium_driver.get(PAGE)
    assert chromium_driver.execute_script("return window.ok") is True
    assert chromium_driver.execute_script("return window.pixel") == [255, 0, 0, 255]
    assert console_errors(chromium_driver) == []
