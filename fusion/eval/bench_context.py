"""What the one-tile bench (``fusion.eval.bench``), the multi-tile bench (``fusion.eval.bench_region``)
and the ablation harness share: the loaded simulation (``BenchContext``, ``prepare``) and the report's
small helpers. Its own module so that the two benches import it, not each other."""

from __future__ import annotations

import resource
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fusion.eval import metrics
from fusion.eval.scoring import TruthPoints, sample_truth
from fusion.eval.synth.simulate import GroundTruth, load_ground_truth
from fusion.offline import LoadedSubmap, load_directory
from fusion.tiles import tile_bounds

TILE = (0, 0)
TILE_SIZE = 64.0


@dataclass
class BenchContext:
    """Everything a row needs: the simulated uploads, the truth (``points``: as point sets, map frame) and
    the config."""

    config: Any
    submaps: list[LoadedSubmap]
    truth: GroundTruth
    points: TruthPoints
    rows: dict[str, dict[str, Any]] = field(default_factory=dict)
    tile_size: float = TILE_SIZE

    @property
    def home(self) -> list[LoadedSubmap]:
        return [s for s in self.submaps if s.home == TILE]


def prepare(sim_dir: Path, config: Any, density: float = metrics.DEFAULT_DENSITY,
            tile_size: float = TILE_SIZE, region: metrics.Region | None = None) -> BenchContext:
    """Load the uploads the way the offline path does, and the truth cropped to ``region`` (default the
    benchmark tile (0, 0), ``tile_size`` metres)."""
    submaps = load_directory(sim_dir, tile_size)
    truth = load_ground_truth(sim_dir)
    region = region or tile_bounds(TILE[0], TILE[1], tile_size)
    return BenchContext(config, submaps, truth, sample_truth(truth, region, density), tile_size=tile_size)


def peak_memory() -> dict[str, float | None]:
    """Peak resident memory of this process and peak allocated GPU memory (if torch runs on CUDA), MiB."""
    rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    gpu = None
    if "torch" in sys.modules:
        import torch

        if torch.cuda.is_available():
            gpu = torch.cuda.max_memory_allocated() / 2**20
    return {"peak_rss_mib": rss_mib, "peak_gpu_mib": gpu}


def fmt(v: Any, spec: str = ".3f") -> str:
    """A table cell: ``-`` for a missing figure."""
    return "-" if v is None else format(v, spec)
