"""A job's progress: an alignment spans [0, 1]; a reconstruction's training [0, 0.9], its extraction the rest."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from fusion.types import ProgressEvent
from worker import lease
from worker.lease import LeaseKeeper


@pytest.mark.parametrize(
    ("stage", "iteration", "expected"),
    [("align", 50, 0.5), ("align", 100, 1.0), ("train", 50, 0.45), ("extract", 50, 0.95)],
)
def test_progress_by_stage(monkeypatch: pytest.MonkeyPatch, stage: str, iteration: int, expected: float) -> None:
    monkeypatch.setattr(lease, "PROGRESS_INTERVAL_S", 0.0)
    keeper = LeaseKeeper(None, SimpleNamespace(job_id="j", tiles=[(0, 0)], lease_s=60))  # type: ignore[arg-type]
    written: list[Any] = []
    monkeypatch.setattr(keeper, "renew", written.append)
    keeper(ProgressEvent(iteration, 100, {}, stage))
    assert written == [pytest.approx(expected)]
