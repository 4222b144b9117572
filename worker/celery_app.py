"""The Celery application of the fusion workers, configured from the service settings.

``celery -A worker.celery_app worker`` (or ``fleetmap worker``) runs it. This module is torch-free:
the fusion library is imported inside the task, in the pool's child process, so the parent never
initialises CUDA before it forks.

Delivery guarantees (see DESIGN.md, "Semantics of state"): a task is acknowledged only after it
finished (``task_acks_late``) and is handed back when its process dies (``task_reject_on_worker_lost``);
Redis re-delivers an unacknowledged task after ``visibility_timeout``, which therefore exceeds the
hard time limit. The tile lease and the idempotent job runner make a second delivery harmless, and the
scheduler's sweeper re-enqueues jobs whose message was lost.
"""

from __future__ import annotations

import os
from typing import Any

from celery import Celery
from celery.signals import worker_process_init

from service.settings import Settings, get_settings

TASK_FUSE_TILE = "fleetmap.fuse_tile"
# Seconds. A fusion with the cpu preset takes minutes; the paper preset on a GPU about 1.5 min per tile.
DEFAULT_SOFT_TIME_LIMIT_S = 3600.0
HARD_LIMIT_GRACE_S = 300.0
VISIBILITY_MARGIN_S = 600.0
# Environment variable listing the GPUs one worker host may use, e.g. "0,1": pool child k gets GPU k mod n.
GPU_DEVICES_ENV = "FLEETMAP_GPU_DEVICES"


def time_limits(settings: Settings) -> tuple[float, float, float]:
    """``(soft, hard, visibility_timeout)`` in seconds for fusion tasks."""
    soft = float(getattr(settings, "fusion_time_limit_s", DEFAULT_SOFT_TIME_LIMIT_S))
    hard = soft + HARD_LIMIT_GRACE_S
    return soft, hard, hard + VISIBILITY_MARGIN_S


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration shared by producers (the API) and consumers (workers)."""
    soft, hard, visibility = time_limits(settings)
    transport = {"visibility_timeout": int(visibility)}
    return {
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_ignore_result": True,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        "task_soft_time_limit": soft,
        "task_time_limit": hard,
        "task_default_queue": settings.fusion_queue,
        "task_routes": {TASK_FUSE_TILE: {"queue": settings.fusion_queue}},
        "broker_transport_options": transport,
        "result_backend_transport_options": transport,
        "broker_connection_retry_on_startup": True,
        # torch keeps allocator caches; recycle the child now and then so memory stays bounded.
        "worker_max_tasks_per_child": 50,
        "worker_hijack_root_logger": False,
    }


def make_celery(settings: Settings) -> Celery:
    """A Celery app for ``settings`` (broker ``FLEETMAP_BROKER_URL``; ``memory://`` when unset)."""
    celery = Celery("fleetmap", broker=settings.broker_url or "memory://", set_as_current=False)
    celery.conf.update(celery_config(settings))
    return celery


def _pin_gpu(**_: Any) -> None:
    """Give each pool child its own GPU (one process per GPU) before anything touches CUDA."""
    devices = [d.strip() for d in os.environ.get(GPU_DEVICES_ENV, "").split(",") if d.strip()]
    if not devices:
        return
    from billiard.process import current_process

    index = getattr(current_process(), "index", 0) or 0
    os.environ["CUDA_VISIBLE_DEVICES"] = devices[index % len(devices)]


worker_process_init.connect(_pin_gpu, weak=False)

app = make_celery(get_settings())
app.conf.include = ["worker.tasks"]
