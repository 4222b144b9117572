"""The monitoring files of the compose deployment agree with the code: Prometheus scrapes the port
the workers serve on, and every series the Grafana dashboard queries is one the API or a worker exports.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import yaml

from service import telemetry
from worker import metrics

REPO = Path(__file__).resolve().parents[2]


def _exported_names() -> set[str]:
    names = set()
    for registry in (telemetry.REGISTRY, metrics._get().registry):
        for family in registry.collect():
            names.add(family.name)
            names |= {family.name + suffix for suffix in ("_total", "_bucket", "_count", "_sum")}
    return names


def test_prometheus_scrapes_the_api_and_the_workers_metrics_port() -> None:
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    worker = compose["services"]["worker"]
    port = int(worker["environment"]["FLEETMAP_WORKER_METRICS_PORT"])
    assert str(port) in [str(p) for p in worker["expose"]]
    config = yaml.safe_load((REPO / "deploy" / "prometheus.yml").read_text())
    jobs = {job["job_name"]: job for job in config["scrape_configs"]}
    assert jobs["fleetmap-api"]["static_configs"][0]["targets"] == ["api:8000"]
    discovery = jobs["fleetmap-worker"]["dns_sd_configs"][0]
    assert (discovery["names"], discovery["port"]) == (["worker"], port)
    for service in ("prometheus", "grafana"):
        for volume in compose["services"][service]["volumes"]:
            source = volume.split(":")[0]
            if source.startswith("./"):
                assert (REPO / source).exists(), volume


def test_the_dashboard_queries_only_exported_series() -> None:
    dashboard = json.loads((REPO / "deploy" / "grafana" / "dashboards" / "fleetmap.json").read_text())
    exprs = [t["expr"] for panel in dashboard["panels"] for t in panel["targets"]]
    used = {name for expr in exprs for name in re.findall(r"\bfleetmap_[a-z_]+", expr)}
    assert used and used <= _exported_names(), used - _exported_names()
    assert {"fleetmap_tiles", "fleetmap_fusion_queue_depth", "fleetmap_worker_job_duration_seconds_bucket",
            "fleetmap_worker_queue_wait_seconds_bucket", "fleetmap_worker_upload_to_fused_seconds_bucket",
            "fleetmap_worker_job_failures_total"} <= used
