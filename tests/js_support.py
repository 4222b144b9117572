"""The test-only JavaScript packages (``tests/browser/js``: CesiumJS, the Khronos glTF validator).

``.ci/run`` installs them with ``npm ci`` from the committed lock file into the gitignored
``tests/browser/js/node_modules``. Without them a test is skipped on a developer machine and fails
under CI (``CI=true``), so a broken install cannot pass as green.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

JS_DIR = Path(__file__).resolve().parent / "browser" / "js"
NODE_MODULES = JS_DIR / "node_modules"


def require_package(name: str) -> Path:
    """The installed package's folder (and ``node`` on the PATH), else skip (fail under CI)."""
    folder = NODE_MODULES / name
    reason = None
    if shutil.which("node") is None:
        reason = "node is not installed"
    elif not (folder / "package.json").is_file():
        reason = f"{folder} is missing (npm ci --prefix tests/browser/js)"
    if reason:
        if os.environ.get("CI"):
            pytest.fail(f"JavaScript test dependencies are needed under CI: {reason}")
        pytest.skip(reason)
    return folder
