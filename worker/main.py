"""``fleetmap worker``: a Celery fusion worker, or the embedded database-polling worker.

fleetmap worker --queues fusion --concurrency 1      # Celery, broker FLEETMAP_BROKER_URL
fleetmap worker --queues gpu                          # GPU hosts (FLEETMAP_FUSION_QUEUE=gpu on the API)
fleetmap worker --embedded                            # no broker: poll the database for queued jobs
fleetmap worker --metrics-port 9100                   # serve Prometheus metrics (FLEETMAP_WORKER_METRICS_PORT)
"""

from __future__ import annotations

import argparse
import logging
import sys

from service.settings import get_settings
from worker import metrics


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """The ``worker`` command's options (the service CLI reuses this for its subcommand)."""
    parser = parser or argparse.ArgumentParser(prog="fleetmap worker", description=__doc__.splitlines()[0])
    parser.add_argument("--embedded", action="store_true", help="poll the database instead of a broker")
    parser.add_argument(
        "--queues", default=None, help="comma-separated queues (default FLEETMAP_FUSION_QUEUE)"
    )
    parser.add_argument("--concurrency", type=int, default=1, help="fusion processes (one per GPU)")
    parser.add_argument("--pool", default="prefork", help="Celery pool (prefork, solo, threads)")
    parser.add_argument("--loglevel", default=None, help="log level (default FLEETMAP_LOG_LEVEL)")
    parser.add_argument(
        "--metrics-port",
        type=int,
        default=None,
        help="serve this worker's Prometheus metrics on 0.0.0.0:PORT/metrics "
        "(default FLEETMAP_WORKER_METRICS_PORT; 0: off)",
    )
    parser.add_argument("--max-jobs", type=int, default=None, help=argparse.SUPPRESS)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run the worker selected by parsed ``args``; returns the exit code."""
    settings = get_settings()
    level = (args.loglevel or settings.log_level).upper()
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    port = settings.worker_metrics_port if args.metrics_port is None else args.metrics_port
    if args.embedded:
        from worker.embedded import run_embedded

        if port:
            metrics.serve(port)
        return run_embedded(settings, max_jobs=args.max_jobs)
    if not settings.broker_url:
        print("FLEETMAP_BROKER_URL is not set: start a broker, or use --embedded", file=sys.stderr)
        return 2
    if port:
        # prefork: the jobs run in pool children, so they share a private multiprocess folder that
        # this (parent) process serves; solo/threads: the jobs run here.
        if args.pool == "prefork":
            metrics.enable_multiprocess()
        metrics.serve(port)
    from worker.celery_app import app

    queues = args.queues or settings.fusion_queue
    argv = ["worker", "-Q", queues, "--concurrency", str(args.concurrency), "--pool", args.pool]
    argv += ["--loglevel", level, "--without-gossip", "--without-mingle"]
    app.worker_main(argv)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fleetmap worker`` and ``python -m worker.main``."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
