"""The Celery application of the fusion workers, configured from the service settings.

``celery -A worker.celery_app worker`` (or ``fleetmap worker``) runs it. This module is torch-free:
the fusion library is imported inside the task, in the pool's child process, so the parent never
initialises CUDA before it forks.

Its configuration and task names are the broker contract in ``service.broker`` (shared with the API,
which sends jobs by name).
"""

from __future__ import annotations

import os
from typing import Any

from celery.signals import worker_process_init, worker_process_shutdown

from service.broker import make_celery
from service.settings import get_settings
from worker import metrics

# Environment variable listing the GPUs one worker host may use, e.g. "0,1": pool child k gets GPU k mod n.
GPU_DEVICES_ENV = "FLEETMAP_GPU_DEVICES"


def _pin_gpu(**_: Any) -> None:
    """Give each pool child its own GPU (one process per GPU) before anything touches CUDA."""
    devices = [d.strip() for d in os.environ.get(GPU_DEVICES_ENV, "").split(",") if d.strip()]
    if not devices:
        return
    from billiard.process import current_process

    index = getattr(current_process(), "index", 0) or 0
    os.environ["CUDA_VISIBLE_DEVICES"] = devices[index % len(devices)]


def _metrics_process_exited(**_: Any) -> None:
    """A pool child exits: its live gauges leave the worker's multiprocess metrics (if enabled)."""
    metrics.process_exited()


worker_process_init.connect(_pin_gpu, weak=False)
worker_process_shutdown.connect(_metrics_process_exited, weak=False)

app = make_celery(get_settings())
app.conf.include = ["worker.tasks"]
