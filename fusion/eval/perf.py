"""Field training throughput micro-benchmark: ``python -m fusion.eval.perf`` / ``fleetmap bench --throughput``.

Measures points per second of forward + backward on CPU (or the configured device) for three
workloads on a 64 m tile box with every grid level active:

- ``grid``: the feature grid alone, ``grid(x01)`` with gradients w.r.t. the table and ``x``;
- ``field``: the whole field (grid + encoding + both heads), gradients w.r.t. parameters and ``x``
  (``x`` stands for posed samples: pose gradients flow through it);
- ``step``: one training step's field terms (``fusion.losses.field_losses``: SDF, semantic,
  confidence, numerical normals + eikonal on ``normal_fraction`` of the samples) + backward, counted
  the way ``fusion.reconstruct`` counts ``points_per_s`` (samples + 6 probes per normal sample).

Each figure is the median of ``runs`` timed repetitions after ``warmup`` untimed ones. Timings on a
shared machine are noisy: compare medians measured back to back, and quote the load (printed).

Allocator tuning (``fusion.runtime.tune_allocator``) is on unless ``--no-malloc-tune``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

from fusion.config import PRESETS
from fusion.runtime import tune_allocator

WORKLOADS = ("grid", "field", "step")


def _load() -> str:
    try:
        return "load average " + " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:  # pragma: no cover - not on every platform
        return "load average n/a"


def _median_rate(fn: Callable[[], int], runs: int, warmup: int) -> dict[str, float]:
    """Median wall-clock points/s of ``fn`` (it returns the points it evaluated), min / max, median points
    per CPU-second of this process, and the first call's seconds (includes any compilation)."""
    t0 = time.perf_counter()
    fn()
    first_s = time.perf_counter() - t0
    for _ in range(max(0, warmup - 1)):
        fn()
    rates, cpu_rates = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        n = fn()
        rates.append(n / (time.perf_counter() - t0))
        cpu_rates.append(n / max(time.process_time() - c0, 1e-9))
    return {"points_per_s": statistics.median(rates), "min": min(rates), "max": max(rates),
            "points_per_cpu_s": statistics.median(cpu_rates), "first_call_s": first_s}


def measure_throughput(
    preset: str = "cpu",
    batch: int | None = None,
    runs: int = 7,
    warmup: int = 2,
    workloads: tuple[str, ...] = WORKLOADS,
    threads: int | None = None,
    seed: int = 0,
) -> dict[str, Any]:
    """Median forward+backward throughput (points/s) of each workload; ``batch`` defaults to the
    preset's samples per step (surface + space)."""
    import torch

    from fusion.config import FusionConfig

    if threads is not None:
        torch.set_num_threads(threads)
    tuned = tune_allocator()
    cfg = FusionConfig.preset(preset)
    n = batch or cfg.surface_samples + cfg.space_samples
    fns, params = _workloads(cfg, n, seed)
    out: dict[str, Any] = {"preset": preset, "batch": n, "runs": runs, "threads": torch.get_num_threads(),
                           "torch": torch.__version__, "allocator_tuned": tuned, "load": _load(), "results": {}}
    for name in workloads:
        for p in params:
            p.grad = None
        out["results"][name] = _median_rate(fns[name], runs, warmup)
    out["load_after"] = _load()
    return out


def _workloads(cfg: Any, n: int, seed: int) -> tuple[dict[str, Callable[[], int]], list[Any]]:
    """The timed workloads on a fresh field of a 64 m tile (+ margin, 20 m slab) and ``n`` random points
    (half of them surface samples), seeded by ``seed``: ``grid`` (feature grid only), ``field`` (grid +
    heads), ``step`` (the training objective); each returns the points it evaluated. Also the field's
    parameters (their gradients are reset between workloads)."""
    import torch

    from fusion.field import SemanticSDFField
    from fusion.labels import NUM_CLASSES
    from fusion.losses import field_losses
    from fusion.sampling import Batch

    n_surf = n // 2
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor([-8.0, -8.0, -3.0]), torch.tensor([72.0, 72.0, 17.0])  # 64 m tile + margin, 20 m slab
    field = SemanticSDFField(cfg, lo, hi)
    field.set_active_levels(cfg.num_levels)
    x = torch.rand(n, 3, generator=gen) * (hi - lo) + lo  # (n, 3) tile frame
    normals = torch.nn.functional.normalize(torch.randn(n_surf, 3, generator=gen), dim=-1)
    labels = torch.randint(0, NUM_CLASSES, (n_surf,), generator=gen)

    def grid() -> int:
        xg = field.norm(x).requires_grad_(True)
        field.grid(xg).square().sum().backward()
        return n

    def whole() -> int:
        xg = x.clone().requires_grad_(True)
        s, c, logits = field(xg)
        assert logits is not None
        (s.square().sum() + c.sum() + logits.square().sum()).backward()
        return n

    def step() -> int:
        xg = x.clone().requires_grad_(True)
        b = Batch(xg[:n_surf], torch.zeros(n_surf), normals, labels, torch.ones(n_surf), xg[n_surf:])
        terms, evaluated = field_losses(field, b, cfg, gen)
        sum(terms.values(), start=torch.zeros(())).backward()
        return evaluated

    return {"grid": grid, "field": whole, "step": step}, list(field.parameters())


def format_throughput(report: dict[str, Any]) -> str:
    lines = [f"field training throughput (forward+backward), preset {report['preset']}, batch {report['batch']}, "
             f"median of {report['runs']} runs, {report['threads']} threads, torch {report['torch']}, "
             f"allocator {'tuned' if report['allocator_tuned'] else 'default'}",
             f"{'workload':<8}{'points/s':>12}{'min':>12}{'max':>12}{'pts/cpu-s':>12}{'first s':>10}"]
    for name, r in report["results"].items():
        lines.append(f"{name:<8}{r['points_per_s']:>12,.0f}{r['min']:>12,.0f}{r['max']:>12,.0f}"
                     f"{r['points_per_cpu_s']:>12,.0f}{r['first_call_s']:>10.2f}")
    lines.append(f"{report['load']} before, {report['load_after']} after (2 cores shared: compare medians; "
                 "pts/cpu-s = points per CPU-second, the load-independent figure with --threads 1)")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", choices=PRESETS, default="cpu", help="fusion configuration (default cpu)")
    p.add_argument("--batch", type=int, default=None, help="points per step (default: the preset's samples)")
    p.add_argument("--runs", type=int, default=7, help="timed repetitions; the median is reported (default 7)")
    p.add_argument("--warmup", type=int, default=2, help="untimed repetitions first (default 2)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    p.add_argument("--workloads", default=",".join(WORKLOADS), help=f"comma-separated of {', '.join(WORKLOADS)}")
    p.add_argument("--default-allocator", action="store_true",
                   help="measure without tune_allocator (as FLEETMAP_MALLOC_TUNE=0)")


def run(args: argparse.Namespace) -> int:
    """Measure and print; ``args`` from ``add_arguments`` or from ``fleetmap bench --throughput`` (which
    has only ``--preset``: the other settings take their defaults)."""
    if getattr(args, "default_allocator", False):
        os.environ["FLEETMAP_MALLOC_TUNE"] = "0"
    workloads = tuple(w for w in getattr(args, "workloads", ",".join(WORKLOADS)).split(",") if w)
    unknown = [w for w in workloads if w not in WORKLOADS]
    if unknown:
        print(f"fleetmap: error: unknown workloads {unknown} (known: {', '.join(WORKLOADS)})", file=sys.stderr)
        return 2
    report = measure_throughput(getattr(args, "preset", "cpu"), getattr(args, "batch", None),
                                getattr(args, "runs", 7), getattr(args, "warmup", 2), workloads,
                                getattr(args, "threads", None))
    print(format_throughput(report))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fusion.eval.perf", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
