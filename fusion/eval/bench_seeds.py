"""The multi-tile bench across seeds: each seed its own world and fleet, the method judged on all of them.

One seed's world can flatter or sink a method (camera seed 3 tied GICP where seeds 0-2 beat it); the figures
per seed beside their mean, and the verdict against the baseline counted per seed, say how general a result is.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fusion.eval.bench_context import fmt
from fusion.eval.bench_region import VERDICT_MARK, run_region_bench

SEED_FIGURES = ("geo_f", "sem_f", "pose_trans_m", "pose_rot_deg", "transient_survival")


def run_region_seeds(seeds: Sequence[int], json_path: str | Path | None = None, out: Callable[[str], None] = print,
                     **bench: Any) -> dict[str, Any]:
    """The multi-tile bench on each of ``seeds`` in turn, each its own world and fleet with the same rows,
    variants and config (``bench``: ``run_region_bench``'s other arguments), each seed's table as it finishes,
    then the figures across the seeds (``seed_summary``, ``format_seed_summary``): a method is judged on several
    worlds, not on one. ``json_path``: every seed's report and the summary."""
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must be distinct and at least one, got {list(seeds)}")
    reports = {seed: run_region_bench(seed=seed, out=out, **bench) for seed in seeds}
    summary = seed_summary(reports)
    out(format_seed_summary(summary))
    if json_path is not None:
        Path(json_path).write_text(json.dumps({"seeds": {str(k): r for k, r in reports.items()}, "summary": summary},
                                              indent=1, default=str))
    return {"seeds": reports, "summary": summary}


def seed_summary(reports: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """Figures across the seeds' reports (``run_region_bench``'s, by seed): per row that every seed ran, each of
    ``SEED_FIGURES`` per seed and their mean (over the seeds that have it); per condition of the verdict against
    the best baseline (``against_baseline``'s checks), per seed whether it held and on how many it did, beside
    the miss ratios (camera fleets) per seed."""
    seeds = list(reports)
    first = reports[seeds[0]]
    names = [n for n in first["rows"] if all(n in r["rows"] for r in reports.values())]
    rows: dict[str, dict[str, Any]] = {}
    for name in names:
        rows[name] = {}
        for key in SEED_FIGURES:
            values = [reports[s]["rows"][name].get(key) for s in seeds]
            known = [v for v in values if v is not None]
            if known:
                rows[name][key] = {"per_seed": values, "mean": float(np.mean(known))}
    checks: dict[str, dict[str, Any]] = {}
    verdicts = [reports[s].get("against_baseline") or {} for s in seeds]
    for i, versus in enumerate(verdicts):
        for key, ok in versus.get("checks", {}).items():
            checks.setdefault(key, {"per_seed": [None] * len(seeds)})["per_seed"][i] = ok
    for key, entry in checks.items():
        entry["held"] = sum(ok is True for ok in entry["per_seed"])
        entry["judged"] = sum(ok is not None for ok in entry["per_seed"])
        if key.endswith("_miss_ratio"):
            entry["values"] = [versus.get(key) for versus in verdicts]
    return {"seeds": seeds, "sensor": first.get("sensor"), "preset": first.get("preset"),
            "sessions": first.get("sessions"), "gps_noise": first.get("gps_noise"), "rows": rows, "checks": checks,
            "verdict_row": (first.get("against_baseline") or {}).get("row")}


def format_seed_summary(summary: dict[str, Any]) -> str:
    """The across-seeds table: one line per row and figure (a column per seed, then the mean) and one per
    condition of the verdict against the best baseline (per seed, then on how many seeds it held)."""
    seeds = summary["seeds"]
    spec = {"transient_survival": ".1%"}
    head = f"{'row':<34} {'figure':<19}" + "".join(f"{'seed ' + str(s):>14}" for s in seeds) + f"{'mean':>14}"
    gps = summary.get("gps_noise") or [None, None]
    lines = [f"across seeds {', '.join(str(s) for s in seeds)} (sensor {summary.get('sensor')}, preset "
             f"{summary.get('preset')}, {summary.get('sessions')} sessions, GPS {fmt(gps[0], 'g')} m / "
             f"{fmt(gps[1], 'g')} deg)", head]
    for name, figures in summary["rows"].items():
        for key, entry in figures.items():
            f = spec.get(key, ".3f")
            lines.append(f"{name:<34} {key:<19}" + "".join(f"{fmt(v, f):>14}" for v in entry["per_seed"])
                         + f"{fmt(entry['mean'], f):>14}")
    if summary["checks"]:
        lines.append(f"{summary.get('verdict_row')} against the best baseline of each seed's run:")
        for key, entry in summary["checks"].items():
            values = entry.get("values") or [None] * len(seeds)
            cells = [(f"{fmt(v, '.2f')}x " if v is not None else "") + VERDICT_MARK[ok]
                     for v, ok in zip(values, entry["per_seed"], strict=True)]
            lines.append(f"  {key:<52}" + "".join(f"{c:>14}" for c in cells)
                         + f"   held on {entry['held']} of {entry['judged']}")
    return "\n".join(lines)
