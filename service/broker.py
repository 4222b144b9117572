"""The broker contract between the API (producer) and the workers (consumers): task names and the
Celery configuration both sides share.

Torch-free and worker-free: the API sends jobs by task *name*, so it never imports ``worker/``.
Delivery guarantees (DESIGN.md, "Semantics of state"): a task is acknowledged only after it finished
(``task_acks_late``) and is handed back when its process dies (``task_reject_on_worker_lost``); Redis
re-delivers an unacknowledged task after ``visibility_timeout``, which therefore exceeds the hard time
limit. The tile lease and the idempotent job runner make a second delivery harmless.
"""

from __future__ import annotations

import logging
from functools import lru_cache
from typing import Any

from celery import Celery

from service.settings import Settings, get_settings

log = logging.getLogger(__name__)

TASK_FUSE_TILE = "fleetmap.fuse_tile"  # a reconstruct job: one tile
TASK_ALIGN_REGION = "fleetmap.align_region"  # an align job: a region's poses
TASKS = {"reconstruct": TASK_FUSE_TILE, "align": TASK_ALIGN_REGION}
# Seconds past the soft limit (FLEETMAP_FUSION_TIME_LIMIT_S) before the hard kill, and of the broker's
# redelivery beyond that.
HARD_LIMIT_GRACE_S = 300.0
VISIBILITY_MARGIN_S = 600.0


def time_limits(settings: Settings) -> tuple[float, float, float]:
    """``(soft, hard, visibility_timeout)`` in seconds for fusion tasks."""
    soft = float(settings.fusion_time_limit_s)
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
        "task_routes": {name: {"queue": settings.fusion_queue} for name in TASKS.values()},
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


@lru_cache(maxsize=4)
def _producer(broker_url: str, queue: str) -> Any:
    # The Celery app is built only when a broker is configured.
    return make_celery(get_settings().model_copy(update={"broker_url": broker_url, "fusion_queue": queue}))


def enqueue(job_id: str, settings: Settings | None = None, kind: str = "reconstruct") -> bool:
    """Hand job ``job_id`` (of ``kind``) to the workers; True when a broker message was sent.

    Embedded deployments (no broker) send nothing: the embedded worker polls for queued jobs. A broker
    error is logged, not raised: the job row is committed and the sweeper sends it again later.
    """
    settings = settings or get_settings()
    if settings.embedded:
        return False
    try:
        _producer(settings.broker_url, settings.fusion_queue).send_task(
            TASKS[kind],
            args=[job_id],
            queue=settings.fusion_queue,
            retry=True,
            retry_policy={"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5},
        )
    except Exception as exc:  # broker unreachable: the sweeper retries, the API must not fail
        log.warning("could not enqueue fusion job %s (%s); the sweeper will retry", job_id, exc)
        return False
    return True
