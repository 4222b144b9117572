"""Ablation studies and the classical baseline comparison of the paper, on the synthetic fleet.

Each study returns table rows (dicts of plain numbers/strings) and, given a directory, writes a PNG
plot (matplotlib, Agg). Simulation, fusion and scoring come from :mod:`fusion.eval.bench` through a
:class:`Harness`, so the studies use exactly the bench's scenario and metrics.

Row keys: ``geo_p/geo_r/geo_f`` (precision, recall, F at the bench's distance threshold, gauge-aligned
like the bench's fused row), ``sem_f`` (mean per-class F, aligned), ``abs_geo_f``/``abs_sem_f`` (the same
in the absolute map frame), ``trans_m``/``rot_deg`` (pose RMSE after rigid alignment), ``time_s``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fusion.eval.harness import Harness, Row, bench_harness
from fusion.types import FusedMesh, Pose


def _emit(row: Row) -> Row:
    """Prints a row as soon as it exists (a long study that fails late keeps what it measured)."""
    print(
        "  row: " + ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()),
        file=sys.stderr,
        flush=True,
    )
    return row


def _fused_row(h: Harness, scenario: Any, config: Any, **label: Any) -> Row:
    mesh, poses, seconds = h.fuse(scenario, config)
    return _emit({**label, **h.evaluate(scenario, mesh, poses), "time_s": seconds})


def _gps_poses(h: Harness, scenario: Any) -> dict[str, Pose]:
    return {s.id: s.pose_init for s in h.submaps(scenario)}


def baseline_vs_fusion(h: Harness, plots: Path | None = None, baseline_config: Any = None) -> list[Row]:
    """Classical (ICP / GICP / GPS poses + Poisson) against the neural fusion on one tile."""
    from fusion.eval.baseline.registration import BaselineConfig, run_baseline

    scenario = h.simulate()
    rows: list[Row] = [_fused_row(h, scenario, h.base_config, method="fusion (hash)")]
    gps = _gps_poses(h, scenario)
    for method in ("gps", "icp", "gicp"):
        cfg = baseline_config or BaselineConfig()
        t0 = time.perf_counter()
        mesh, poses, timing = run_baseline(h.submaps(scenario), h.tile(scenario), method=method, config=cfg)
        seconds = time.perf_counter() - t0
        scores = h.evaluate(scenario, mesh, {**gps, **poses})
        rows.append(_emit({"method": f"poisson+{method}", **scores, "time_s": seconds}))
    if plots is not None:
        _bars(rows, "method", ["geo_f", "sem_f", "trans_m"], plots / "baseline.png", "baseline vs fusion")
    return rows


def alignment(h: Harness, plots: Path | None = None) -> list[Row]:
    """Paper Table "Submap alignment": relative-pose (odometry) loss, positional encoding, progressive LOD."""
    scenario = h.simulate()
    c = h.base_config
    gps_scores = h.evaluate(scenario, FusedMesh.empty(), _gps_poses(h, scenario))
    rows: list[Row] = [{"rel": "-", "pe": "-", "lod": "-", "name": "none (GPS)", **gps_scores, "time_s": 0.0}]
    variants = [
        ("none", dict(lambda_odom=0.0, pe_frequencies=0, lod_start_levels=c.num_levels)),
        ("rel", dict(pe_frequencies=0, lod_start_levels=c.num_levels)),
        ("rel+pe", dict(lod_start_levels=c.num_levels)),
        ("rel+lod", dict(pe_frequencies=0)),
        ("rel+pe+lod", {}),
    ]
    for name, changes in variants:
        flags = {k: ("x" if k in name else "") for k in ("rel", "pe", "lod")}
        rows.append(_fused_row(h, scenario, c.with_(**changes), **flags, name=f"NeF {name}"))
    if plots is not None:
        _bars(rows, "name", ["trans_m", "rot_deg"], plots / "alignment.png", "alignment ablation")
    return rows


def sessions(
    h: Harness, plots: Path | None = None, counts: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7)
) -> list[Row]:
    """Reconstruction quality against the number of mapping sessions."""
    rows = [_fused_row(h, h.simulate(sessions=n), h.base_config, sessions=n) for n in counts]
    if plots is not None:
        _lines(rows, "sessions", ["geo_f", "geo_p", "geo_r", "sem_f"], plots / "sessions.png")
    return rows


def submap_size(
    h: Harness, plots: Path | None = None, lengths: tuple[float, ...] = (5, 10, 25, 50)
) -> list[Row]:
    """Submap length (m) against uploaded data (MB/km) and quality."""
    rows = []
    for length in lengths:
        scenario = h.simulate(submap_length=float(length))
        row = _fused_row(h, scenario, h.base_config, submap_m=length)
        rows.append({**row, "upload_mb_km": h.uploaded_mb_per_km(scenario)})
    if plots is not None:
        _lines(rows, "upload_mb_km", ["sem_f", "geo_f"], plots / "submap_size.png", logx=True)
    return rows


def codebook(
    h: Harness, plots: Path | None = None, log2_sizes: tuple[int, ...] = (8, 10, 12, 14, 16, 18)
) -> list[Row]:
    """Hash-grid codebook size 2^N_C against fused field size (MB/km) and quality."""
    scenario = h.simulate()
    rows = []
    for n in log2_sizes:
        cfg = h.base_config.with_(log2_table_size=n)
        row = _fused_row(h, scenario, cfg, log2_table_size=n)
        rows.append({**row, "field_mb_km": h.field_mb_per_km(scenario, cfg)})
    if plots is not None:
        _lines(rows, "field_mb_km", ["sem_f", "geo_f"], plots / "codebook.png", logx=True)
    return rows


def grid_type(h: Harness, plots: Path | None = None) -> list[Row]:
    """Hash grid against the dense grid and the paper's OcTree set-up (4 levels, 0.5 m leaves, N_F = 4)."""
    from fusion.grids.dense import octree_config

    scenario = h.simulate()
    c = h.base_config
    tile = h.tile(scenario)
    box_m = tile.size_m + 2 * c.tile_margin_m
    octree = octree_config(c, box_m)
    configs = [("hash", c), ("dense", octree.with_(grid_type="dense")), ("octree (sparse)", octree)]
    rows = []
    for name, cfg in configs:
        row = _fused_row(h, scenario, cfg, grid=name)
        rows.append({**row, "field_mb_km": h.field_mb_per_km(scenario, cfg)})
    if plots is not None:
        _bars(rows, "grid", ["geo_f", "sem_f", "field_mb_km"], plots / "grid_type.png", "grid type")
    return rows


def gps_noise(
    h: Harness, plots: Path | None = None, sigmas: tuple[float, ...] = (1, 2, 3, 4, 5.5)
) -> list[Row]:
    """Alignment convergence against initial GPS noise (σ metres and degrees alike)."""
    rows = []
    for s in sigmas:
        scenario = h.simulate(gps_sigma_m=float(s), gps_sigma_deg=float(s))
        before = h.evaluate(scenario, FusedMesh.empty(), _gps_poses(h, scenario))
        row = _fused_row(h, scenario, h.base_config, sigma=s)
        rows.append({**row, "trans_init_m": before["trans_m"], "rot_init_deg": before["rot_deg"]})
    if plots is not None:
        _lines(rows, "sigma", ["trans_init_m", "trans_m", "rot_init_deg", "rot_deg"], plots / "gps_noise.png")
    return rows


def confidence(
    h: Harness, plots: Path | None = None, thresholds: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
) -> list[Row]:
    """Precision / recall trade-off of the confidence threshold ``c_th`` (one fusion, filtered after)."""
    from fusion.meshio import filter_confidence

    scenario = h.simulate()
    mesh, poses, seconds = h.fuse(scenario, h.base_config.with_(c_th=0.0))
    rows = [
        {"c_th": t, **h.evaluate(scenario, filter_confidence(mesh, t), poses), "time_s": seconds}
        for t in thresholds
    ]
    if plots is not None:
        _lines(rows, "c_th", ["geo_f", "geo_p", "geo_r", "sem_f"], plots / "confidence.png")
    return rows


STUDIES: dict[str, Callable[..., list[Row]]] = {
    "alignment": alignment,
    "sessions": sessions,
    "submap_size": submap_size,
    "codebook": codebook,
    "gps_noise": gps_noise,
    "confidence": confidence,
    "grid": grid_type,
    "baseline": baseline_vs_fusion,
}


def format_table(rows: list[Row]) -> str:
    """Rows as a fixed-width text table (floats with 3 decimals)."""
    if not rows:
        return "(no rows)"
    keys = list(dict.fromkeys(k for r in rows for k in r))
    cells = [
        [f"{r.get(k, ''):.3f}" if isinstance(r.get(k), float) else str(r.get(k, "")) for k in keys]
        for r in rows
    ]
    widths = [max(len(k), *(len(c[i]) for c in cells)) for i, k in enumerate(keys)]
    lines = ["  ".join(k.rjust(w) for k, w in zip(keys, widths, strict=True))]
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)


def _pyplot():  # noqa: ANN202
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _lines(rows: list[Row], x: str, ys: list[str], path: Path, logx: bool = False) -> None:
    plt = _pyplot()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for y in ys:
        ax.plot([r[x] for r in rows], [r[y] for r in rows], marker="o", label=y)
    ax.set_xlabel(x)
    if logx:
        ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _bars(rows: list[Row], x: str, ys: list[str], path: Path, title: str) -> None:
    plt = _pyplot()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, len(ys), figsize=(3.2 * len(ys), 3.2))
    for ax, y in zip(list(getattr(axes, "flat", [axes])), ys, strict=True):
        ax.bar(range(len(rows)), [r[y] for r in rows])
        ax.set_xticks(range(len(rows)), [str(r[x]) for r in rows], rotation=30, ha="right", fontsize=7)
        ax.set_title(y, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_bench_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``fleetmap bench`` for the baseline and the ablations."""
    parser.add_argument(
        "--baseline", action="store_true", help="compare ICP/GICP/GPS + Poisson with the fusion"
    )
    parser.add_argument("--ablation", metavar="NAME",
                        help=f"ablation study: {', '.join(STUDIES)} or all (one tile); components (multi-tile: "
                             "one fused row per method component switched, fusion.eval.bench_region.COMPONENTS)")
    parser.add_argument("--plots", metavar="DIR", type=Path, help="write one PNG per study here")
    parser.add_argument("--baseline-points", type=int, default=1_000_000, help="Poisson samples (paper: 1e6)")
    parser.add_argument(
        "--baseline-depth", type=int, default=11, help="Poisson octree depth (paper set-up: 11)"
    )


def wants_extras(args: argparse.Namespace) -> bool:
    """Whether ``fleetmap bench`` was asked for the baseline or an ablation."""
    return bool(getattr(args, "baseline", False) or getattr(args, "ablation", None))


def run_extras(args: argparse.Namespace, harness: Harness | None = None) -> dict[str, list[Row]]:
    """Runs what ``--baseline`` / ``--ablation`` ask for, prints each table; returns rows by study."""
    from fusion.eval.baseline.registration import BaselineConfig

    h = harness or default_harness(args)
    names: list[str] = []
    if getattr(args, "baseline", False):
        names.append("baseline")
    ablation = getattr(args, "ablation", None)
    if ablation:
        names += [n for n in STUDIES if n != "baseline"] if ablation == "all" else [ablation]
    unknown = [n for n in names if n not in STUDIES]
    if unknown:
        raise SystemExit(f"unknown ablation {unknown[0]!r}; choose from {', '.join(STUDIES)} or all")
    out: dict[str, list[Row]] = {}
    for name in names:
        kwargs: dict[str, Any] = {"plots": getattr(args, "plots", None)}
        if name == "baseline":
            kwargs["baseline_config"] = BaselineConfig(
                poisson_points=args.baseline_points, poisson_depth=args.baseline_depth
            )
        out[name] = STUDIES[name](h, **kwargs)
        print(f"\n== {name} ==\n{format_table(out[name])}", flush=True)
    return out


def default_harness(args: argparse.Namespace) -> Harness:
    """The :class:`Harness` backed by :mod:`fusion.eval.bench` (see :mod:`fusion.eval.harness`)."""
    return bench_harness(args)
