"""What the one-tile bench (``fusion.eval.bench``), the multi-tile bench (``fusion.eval.bench_region``)
and the ablation harness share: the loaded simulation (``BenchContext``, ``prepare``) and the report's
small helpers. Its own module so that the two benches import it, not each other."""

from __future__ import annotations

import resource
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fusion.eval import metrics
from fusion.eval.scoring import TruthPoints, sample_truth
from fusion.eval.synth.simulate import GroundTruth, load_ground_truth
from fusion.offline import LoadedSubmap, load_directory
from fusion.tiles import tile_bounds
from fusion.types import FusedMesh, Pose

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
    uploads = {s.input.id: s.input.mesh.vertices for s in submaps}
    return BenchContext(config, submaps, truth, sample_truth(truth, region, density, uploads), tile_size=tile_size)


def concatenated(submaps: Sequence[LoadedSubmap], poses: dict[str, Pose], region: metrics.Region | None,
                 margin_m: float = 1.0) -> FusedMesh:
    """The ``submaps``' meshes carried into the map frame by ``poses`` (by submap id) and concatenated, no
    fusion: the faces whose centre lies within ``margin_m`` of ``region`` (all if None). What the
    ``concat`` rows score: the quality of the uploads themselves at those poses."""
    verts, faces, labels, offset = [], [], [], 0
    for s in submaps:
        mesh = s.input.mesh
        v = poses[s.input.id].apply(np.asarray(mesh.vertices, np.float64))
        f = np.asarray(mesh.faces, np.int64)
        keep = np.ones(len(f), bool)
        if region is not None:
            (x0, y0), (x1, y1) = region
            c = v[f].mean(axis=1)
            keep = ((c[:, 0] >= x0 - margin_m) & (c[:, 0] < x1 + margin_m) & (c[:, 1] >= y0 - margin_m)
                    & (c[:, 1] < y1 + margin_m))
        verts.append(v)
        faces.append(f[keep] + offset)
        labels.append(np.asarray(mesh.face_labels)[keep])
        offset += len(v)
    if not verts:
        return FusedMesh.empty()
    return FusedMesh(np.concatenate(verts).astype(np.float32), np.concatenate(faces).astype(np.int32),
                     np.zeros(offset, np.uint8), np.ones(offset, np.float32), np.concatenate(labels).astype(np.uint8))


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


def sensor_text(report: dict[str, Any]) -> str:
    """The report's sensor and its camera / world overrides, for a table's footer."""
    extra = [f"--{flag} {item}" for flag in ("camera", "world") for item in report.get(flag, [])]
    return report.get("sensor", "exact") + (f" ({' '.join(extra)})" if extra else "")
