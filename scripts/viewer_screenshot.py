"""Screenshot of the web viewer, for the README: ``fleetmap demo --serve --port 8799`` in one shell, then
``python scripts/viewer_screenshot.py http://127.0.0.1:8799/ docs/img/viewer.png``.

Drives Debian's ``chromium`` + ``chromium-driver`` headless (WebGL through SwiftShader) with Selenium (the
test extra), as the browser tests do; waits until every tile in view is drawn. ``--token`` for a service
with auth on; ``--view cx,cy,span`` (map frame, metres) frames another part of the map.
"""

from __future__ import annotations

import argparse
import sys
import time

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("url", help="the viewer's URL, e.g. http://127.0.0.1:8799/")
    p.add_argument("out", help="PNG file to write")
    p.add_argument("--token", default="", help="bearer token (a reader's) when the service has auth on")
    p.add_argument("--view", default="", help="cx,cy,span in metres (default: the fused tiles)")
    p.add_argument("--size", default="1400,900", help="window size in pixels (default 1400,900)")
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait for the tiles (default 60)")
    args = p.parse_args()
    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={args.size}",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
    try:
        driver.get(args.url + (f"#view={args.view}" if args.view else ""))
        if args.token:
            driver.find_element(By.ID, "token").send_keys(args.token)
            driver.find_element(By.ID, "connect").click()
        deadline = time.monotonic() + args.timeout
        script = ("const v = window.fleetmapViewer; return Boolean(v && v.ready && v.tilesLoaded > 0 && "
                  "v.tilesLoaded === v.tiles().filter((t) => t.version > 0).length)")
        while not driver.execute_script(script):
            if time.monotonic() > deadline:
                print(f"viewer_screenshot: no fused tile drawn within {args.timeout:.0f} s "
                      f"({driver.find_element(By.ID, 'msg').text})", file=sys.stderr)
                return 1
            time.sleep(0.2)
        time.sleep(1.0)  # the last mesh's first frames
        driver.save_screenshot(args.out)
    finally:
        driver.quit()
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
