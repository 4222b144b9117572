"""``fleetmap simulate | fuse | bench``: the fusion library's commands.

``register(subparsers)`` adds them to the ``fleetmap`` CLI (``service/cli.py``). Everything heavy
(torch, trimesh, the synthetic world) is imported inside the handlers, so importing this module stays
cheap and torch-free for the API process. ``python -m fusion.eval.cli ...`` runs them standalone.
Errors: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any

from fusion.config import PRESETS

EXIT_ERROR = 2
SENSORS = ("camera", "exact")  # fusion.eval.synth.camera.SENSORS, spelled out: that module imports scipy and trimesh


def _fail(message: str) -> int:
    print(f"fleetmap: error: {message}", file=sys.stderr)
    return EXIT_ERROR


def _guard(handler: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """Turn expected failures (bad input, typed library errors) into one stderr line and exit code 2."""

    def run(args: argparse.Namespace) -> int:
        from fusion.errors import FusionLibraryError

        try:
            return handler(args)
        except FusionLibraryError as exc:
            return _fail(exc.message)
        except (OSError, ValueError) as exc:
            return _fail(str(exc))

    run.__doc__ = handler.__doc__
    return run


@_guard
def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a synthetic fleet's uploads (NAME.ply + NAME.json) and ground_truth/ to OUT."""
    from fusion.eval.synth.fleet import FleetParams
    from fusion.eval.synth.simulate import simulate

    if (error := fleet_overrides_error(args.sensor, args.camera, args.world)) is not None:
        return _fail(error)
    records = simulate(args.out, seed=args.seed, sessions=args.sessions, gps_noise=(args.gps_noise_m, args.gps_noise_deg),
                       fleet_params=FleetParams(vertex_noise_m=args.vertex_noise_m), sensor=args.sensor,
                       camera=args.camera, world=args.world)
    print(f"wrote {len(records)} submaps of {args.sessions} sessions ({args.sensor} sensor) to {args.out} "
          "(ground truth in ground_truth/)")
    return 0


@_guard
def cmd_fuse(args: argparse.Namespace) -> int:
    """Fuse a directory of submaps tile by tile into OUT/tiles/*.ply and OUT/poses.json."""
    from tqdm import tqdm

    from fusion.config import FusionConfig
    from fusion.offline import fuse_directory
    from fusion.types import ProgressEvent

    bars: dict[str, Any] = {}

    def progress(ev: ProgressEvent) -> None:
        bar = bars.get(ev.stage)
        if bar is None:
            for old in bars.values():
                old.close()
            bars.clear()
            bar = bars[ev.stage] = tqdm(total=ev.total, desc=ev.stage, unit="it", leave=False)
        bar.total = ev.total
        bar.update(ev.iteration - bar.n)
        if ev.losses:
            bar.set_postfix(loss=f"{ev.losses.get('total', float('nan')):.4f}")

    try:
        config = FusionConfig.preset(args.preset).with_overrides(args.set)
    except ValueError as exc:
        return _fail(f"--set {exc}")
    try:
        summary = fuse_directory(args.dir, args.out, config, tile_size=args.tile_size,
                                 origin=args.origin, progress=progress)
    finally:
        for bar in bars.values():
            bar.close()
    print(f"fused {summary['submaps']} submaps into {len(summary['metrics'])} tiles in {args.out}/tiles"
          + (f" ({len(summary['skipped'])} tiles without data skipped)" if summary["skipped"] else ""))
    return 0


@_guard
def cmd_bench(args: argparse.Namespace) -> int:
    """Simulate, fuse one tile, evaluate against the ground truth, print the table."""
    from fusion.eval.ablations import run_extras, wants_extras
    from fusion.eval.bench import ROWS, run_bench
    from fusion.eval.bench_region import ROWS as REGION_ROWS

    if args.throughput:  # field training points/s micro-benchmark (python -m fusion.eval.perf has more knobs)
        from fusion.eval.perf import run as run_throughput

        return run_throughput(args)
    if (error := fleet_overrides_error(args.sensor, args.camera, args.world)) is not None:
        return _fail(error)
    region = args.tiles > 1
    components = region and args.ablation == "components"  # the multi-tile ablation: variant rows below
    if components:
        from fusion.eval.bench_region import COMPONENTS

        args.variant = [*COMPONENTS, *args.variant]
        args.ablation = None
    if args.variant and not region:
        return _fail("--variant and --ablation components run on the multi-tile bench (--tiles 2 or more)")
    if args.seeds and not (region and not args.ablation):
        return _fail("--seeds runs the multi-tile bench (--tiles 2 or more, no --ablation but components)")
    if wants_extras(args) and not (region and args.baseline and not args.ablation):
        run_extras(args)  # --ablation, or --baseline --tiles 1: fusion.eval.ablations prints its own tables
        return 0
    rows = args.rows.split(",") if args.rows else None
    baseline_config = None
    if region and args.baseline:  # the baseline's rows beside the fusion's, on the same multi-tile data
        from fusion.eval.baseline.registration import BaselineConfig

        rows = [*(rows or ["gps", "fused"]), "icp", "gicp"]
        baseline_config = BaselineConfig(poisson_points=args.baseline_points, poisson_depth=args.baseline_depth)
    known = ROWS if not region else REGION_ROWS
    unknown = [r for r in rows or [] if r not in known]
    if unknown:
        return _fail(f"unknown bench rows {unknown} (known: {', '.join(known)})")
    config = None
    if args.iterations or args.align_iterations or args.set:  # knobs of the bench (its JSON records the config)
        from fusion.config import FusionConfig

        base = FusionConfig.preset(args.preset)
        try:
            base = base.with_overrides(args.set)
        except ValueError as exc:
            return _fail(f"--set {exc}")
        config = base.with_(iterations=args.iterations or base.iterations,
                            align_iterations_per_tile=args.align_iterations or base.align_iterations_per_tile)
    gps_noise = (args.gps_noise_m, args.gps_noise_deg)
    if region:  # the multi-tile bench: align the region, reconstruct every tile
        from fusion.eval.bench_region import run_region_bench
        from fusion.eval.bench_seeds import run_region_seeds

        bench = {"preset": args.preset, "sessions": args.sessions, "gps_noise": gps_noise, "rows": rows,
                 "config": config, "tile_size": args.tile_size, "vertex_noise_m": args.vertex_noise_m,
                 "tiles": args.tiles, "sensor": args.sensor, "baseline_config": baseline_config,
                 "variants": args.variant, "camera": args.camera, "world": args.world}
        if args.seeds:
            run_region_seeds(args.seeds, json_path=args.json, out=print, **bench)
        else:
            run_region_bench(seed=args.seed, json_path=args.json, out=print, **bench)
        return 0
    run_bench(preset=args.preset, sessions=args.sessions, gps_noise=gps_noise, seed=args.seed,
              json_path=args.json, rows=rows, tile_size=args.tile_size, vertex_noise_m=args.vertex_noise_m,
              config=config, sensor=args.sensor, camera=args.camera, world=args.world)
    return 0


def _seed_list(text: str) -> list[int]:
    try:
        seeds = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    return seeds  # distinct or not: run_region_seeds says (a one-line error through _guard)


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError("must be at least 1")
    return value


def add_fleet_arguments(p: argparse.ArgumentParser) -> None:
    """The synthetic fleet's options (``simulate``, ``bench``). ``--sensor`` defaults to the camera for both:
    ``simulate`` writes what the bench fuses (``simulate`` + ``fuse`` reproduce a bench run's input), and
    camera fleets are what the service is for; ``--sensor exact`` keeps the old exact crops."""
    p.add_argument("--seed", type=int, default=0, help="world and fleet seed (default 0)")
    p.add_argument("--sensor", choices=SENSORS, default="camera",
                   help="what the vehicles map with (default camera): camera, one front camera's pipeline "
                        "(field of view, smooth range-dependent depth error, scale drift and bend, segmenter "
                        "errors, holes; fusion.eval.synth.camera); exact, crops of the world with white noise")
    p.add_argument("--sessions", type=_positive_int, default=5, help="driving sessions (default 5)")
    p.add_argument("--gps-noise-m", type=float, default=1.5, help="GPS translation sigma, metres (default 1.5)")
    p.add_argument("--gps-noise-deg", type=float, default=1.5, help="GPS rotation sigma, degrees (default 1.5)")
    p.add_argument("--vertex-noise-m", type=float, default=0.025,
                   help="submap vertex noise sigma, metres (default 0.025) of the exact sensor (--sensor exact)")
    p.add_argument("--camera", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the camera model (repeatable; fusion.eval.synth.camera.CameraSensor), "
                        "e.g. --camera depth_sigma_10m=0.3 --camera thin_miss=pole:0.3,traffic_sign:0.3")
    p.add_argument("--world", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field of the simulated world (repeatable; fusion.eval.synth.world.WorldParams), "
                        "e.g. --world max_grade=0.1 --world junction=t --world class_mix=vehicle:2")


def fleet_overrides_error(sensor: str, camera: Sequence[str], world: Sequence[str] = ()) -> str | None:
    """The one-line error of a bad ``--camera`` / ``--world`` override (None: they apply), checked before
    anything is simulated (``simulate``, ``bench``, ``fleetmap demo``)."""
    from fusion.eval.synth.camera import sensor_model
    from fusion.eval.synth.world import WorldParams, world_overrides

    try:
        sensor_model(sensor, camera)
    except ValueError as exc:
        return f"--camera {exc}"
    try:
        world_overrides(WorldParams(), world)
    except ValueError as exc:
        return f"--world {exc}"
    return None


def register(subparsers: Any) -> None:
    """Add ``simulate``, ``fuse`` and ``bench`` to an argparse sub-parser collection; each sets ``func``."""
    p = subparsers.add_parser("simulate", help="write a synthetic fleet's submap uploads and ground truth")
    p.add_argument("out", help="output directory")
    add_fleet_arguments(p)
    p.set_defaults(func=cmd_simulate)

    p = subparsers.add_parser("fuse", help="fuse a directory of submaps (NAME.ply + NAME.json) tile by tile")
    p.add_argument("dir", help="directory with NAME.ply + NAME.json submaps")
    p.add_argument("--out", required=True, help="output directory (tiles/*.ply, poses.json)")
    p.add_argument("--preset", choices=PRESETS, default="cpu", help="fusion configuration (default cpu)")
    p.add_argument("--tile-size", type=float, default=64.0, help="tile size, metres (default 64)")
    p.add_argument("--origin", default=None, help="geodetic map origin 'lat,lon,alt' for geodetic GPS fixes")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a fusion configuration field (repeatable; fusion.config.FusionConfig), "
                        "e.g. --set fine_drift=true for a monocular camera fleet")
    p.set_defaults(func=cmd_fuse)

    p = subparsers.add_parser("bench", help="simulate, fuse (3×3 tiles by default) and evaluate against the ground truth")
    p.add_argument("--preset", choices=PRESETS, default="cpu", help="fusion configuration (default cpu)")
    p.add_argument("--json", default=None, metavar="FILE", help="write every figure to FILE")
    add_fleet_arguments(p)
    p.add_argument("--rows", default=None, help="comma-separated bench rows (default: all)")
    p.add_argument("--seeds", type=_seed_list, default=None, metavar="N,N,...",
                   help="(multi-tile) the bench on each of these seeds in turn, each its own world and fleet, then "
                        "every figure and the verdict against the baseline across them (instead of --seed)")
    p.add_argument("--tile-size", type=float, default=None,
                   help="benchmark tile edge, metres (default: 64 for cpu, 128 for paper)")
    p.add_argument("--tiles", type=_positive_int, default=3,
                   help="core of N×N tiles (default 3: align the region, reconstruct 9 tiles); 1: the one-tile bench")
    p.add_argument("--iterations", type=_positive_int, default=None,
                   help="reconstruction iterations per tile (default: the preset's)")
    p.add_argument("--align-iterations", type=_positive_int, default=None,
                   help="alignment iterations per tile of the region (default: the preset's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a fusion configuration field (repeatable; fusion.config.FusionConfig), "
                        "e.g. --set extract_support_m=0 for an ablation")
    p.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]",
                   help="(multi-tile) one more fused row with these config overrides, on the same data "
                        "(repeatable; --ablation components: one per method component)")
    p.add_argument("--throughput", action="store_true",
                   help="only measure field training throughput (points/s forward+backward, fusion.eval.perf)")
    from fusion.eval.ablations import add_bench_arguments

    add_bench_arguments(p)  # --baseline, --ablation NAME|all, --plots DIR, Poisson sizes
    p.set_defaults(func=cmd_bench)


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point: ``python -m fusion.eval.cli {simulate,fuse,bench} ...``."""
    parser = argparse.ArgumentParser(prog="fleetmap", description="fleetmap fusion commands")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
