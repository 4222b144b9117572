"""Ablation studies produce rows and plots (a fake harness stands in for the bench)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fusion.config import FusionConfig
from fusion.eval.ablations import (
    STUDIES,
    Harness,
    add_bench_arguments,
    format_table,
    run_extras,
    wants_extras,
)
from fusion.types import FusedMesh, Pose, SubmapInput, TileSpec


class _FakeHarness:
    """Stands in for ``fusion.eval.harness.BenchHarness``: scenarios are the simulate overrides."""

    base_config = FusionConfig()

    def simulate(self, **overrides: Any) -> dict:
        return dict(overrides)

    def fuse(self, scenario: dict, cfg: FusionConfig) -> tuple[FusedMesh, dict[str, Pose], float]:
        v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        mesh = FusedMesh(
            v,
            np.array([[0, 1, 2]], np.int32),
            np.ones(3, np.uint8),
            np.array([0.2, 0.8, 0.9], np.float32),
            np.ones(1, np.uint8),
        )
        return mesh, {"a": Pose.identity()}, 0.01

    def evaluate(self, scenario: dict, mesh: FusedMesh, poses: dict[str, Pose]) -> dict[str, float]:
        f = 0.1 * len(mesh.faces) + 0.01 * scenario.get("sessions", 1)
        return {"geo_p": f, "geo_r": f, "geo_f": f, "sem_f": f / 2, "trans_m": 0.5, "rot_deg": 0.4}

    def submaps(self, scenario: dict) -> list[SubmapInput]:
        return []

    def tile(self, scenario: dict) -> TileSpec:
        return TileSpec(0, 0, 64.0)

    def uploaded_mb_per_km(self, scenario: dict) -> float:
        return 10.0 / scenario.get("submap_length", 1.0)

    def field_mb_per_km(self, scenario: dict, cfg: FusionConfig) -> float:
        return float(2**cfg.log2_table_size) / 1e4


def _fake_harness() -> Harness:
    return _FakeHarness()


@pytest.mark.parametrize("name", [n for n in STUDIES if n != "baseline"])
def test_each_study_returns_rows_and_writes_a_plot(name: str, tmp_path: Path) -> None:
    rows = STUDIES[name](_fake_harness(), plots=tmp_path)
    assert rows and all("geo_f" in r for r in rows)
    assert len(list(tmp_path.glob("*.png"))) == 1
    assert "geo_f" in format_table(rows)


def test_cli_options_select_studies(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    add_bench_arguments(parser)
    assert not wants_extras(parser.parse_args([]))
    args = parser.parse_args(["--ablation", "sessions"])
    out = run_extras(args, harness=_fake_harness())
    assert list(out) == ["sessions"] and len(out["sessions"]) == 7
    assert "== sessions ==" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        run_extras(parser.parse_args(["--ablation", "nope"]), harness=_fake_harness())
