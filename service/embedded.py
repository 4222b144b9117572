"""The embedded fusion worker's supervisor: ``fleetmap serve`` without a broker is a complete service.

The API process starts the child by command, ``python -m worker.main --embedded`` (it never imports
``worker/``): the child polls the database for queued fusion jobs and runs them with the same job
runner as the Celery task, so fusion (torch) never runs in the API process. The child exits when asked
to (SIGTERM: the running job goes back to ``queued``) or when its parent dies.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time

from service.settings import Settings

log = logging.getLogger(__name__)

RESTART_BACKOFF_S = 5.0


def settings_env(settings: Settings) -> dict[str, str]:
    """``FLEETMAP_*`` variables that reproduce ``settings`` in a child process."""
    env = {}
    for name, value in settings.model_dump().items():
        if value is None:
            continue
        text = str(value).lower() if isinstance(value, bool) else str(value)
        env[f"FLEETMAP_{name.upper()}"] = text
    return env


class EmbeddedWorkerProcess:
    """Owns the embedded worker child process of one API process."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.process: subprocess.Popen[bytes] | None = None
        self._started_at = 0.0
        self._lock = threading.Lock()
        self._stopping = False

    def start(self) -> None:
        with self._lock:
            env = {**os.environ, **settings_env(self.settings)}
            self.process = subprocess.Popen([sys.executable, "-m", "worker.main", "--embedded"], env=env)
            self._started_at = time.monotonic()
            log.info("embedded fusion worker started (pid %d)", self.process.pid)

    def ensure_running(self) -> None:
        """Restart the child if it died (e.g. killed for memory); its job is reclaimed by the sweeper."""
        if self._stopping or self.process is None or self.process.poll() is None:
            return
        if time.monotonic() - self._started_at < RESTART_BACKOFF_S:
            return
        log.error("embedded fusion worker exited with %s; restarting it", self.process.returncode)
        self.start()

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM the child (its running job goes back to queued), SIGKILL after ``timeout``."""
        self._stopping = True
        with self._lock:
            process = self.process
        if process is None or process.poll() is not None:
            return
        process.terminate()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            log.warning("embedded fusion worker did not stop in %.0f s; killing it", timeout)
            process.kill()
            process.wait(10)
