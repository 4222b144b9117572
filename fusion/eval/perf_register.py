"""Scaling of the fine registration's solver: ``python -m fusion.eval.perf_register``.

Times Levenberg-Marquardt steps of ``fusion.register._gauss_newton`` on synthetic regions of growing
size: ``sessions`` parallel chains of submaps 10 m apart, each submap matched (``matches`` point-to-plane
pairs) with its chain neighbour and with the submap beside it in every other session, odometry along
each chain, GPS on every submap, poses started a few decimetres and tenths of a degree off. Prints,
per region size, the seconds per accepted step and the process's peak memory, so the cost is seen to
follow the region's overlaps (linear in the submaps) rather than the submaps squared.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np
import torch

from fusion.drift_fit import Matches
from fusion.register import _chain_colours, _gauss_newton
from fusion.training import PoseTerms
from fusion.types import Pose, SemanticMesh, Sigma, SubmapInput

_EMPTY = SemanticMesh(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), np.zeros(1, np.uint8))


def _yaw(deg: float) -> np.ndarray:
    """Unit quaternion (w-first) of a rotation about z."""
    a = np.radians(deg / 2)
    return np.array([np.cos(a), 0.0, 0.0, np.sin(a)])


def synthetic_region(submaps: int, sessions: int, matches: int, seed: int = 0
                     ) -> tuple[torch.Tensor, Matches, PoseTerms, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(start poses, matches, odometry/GPS terms, GPS anchors, local centroids, chain colours)."""
    rng = np.random.default_rng(seed)
    per = max(2, submaps // sessions)
    subs, truth = [], []
    for s in range(sessions):
        for k in range(per):
            true = Pose(np.array([10.0 * k, 6.0 * s, 0.0]), _yaw(0.0))
            start = Pose(true.t + rng.normal(size=3) * 0.3, _yaw(float(rng.normal() * 0.3)))
            subs.append(SubmapInput(f"s{s}-{k}", f"s{s}", k, _EMPTY, start, true, Sigma(1.5, 1.5),
                                    Sigma(0.05, 0.5), pose_gps=true))
            truth.append(true)
    m = len(subs)
    pairs = [(s * per + k, s * per + k + 1) for s in range(sessions) for k in range(per - 1)]
    pairs += [(s * per + k, t * per + k) for s in range(sessions) for t in range(s + 1, sessions) for k in range(per)]
    src: list[np.ndarray] = []
    dst: list[np.ndarray] = []
    p_src: list[np.ndarray] = []
    p_dst: list[np.ndarray] = []
    normal: list[np.ndarray] = []
    for a, b in pairs:
        world = np.column_stack([rng.uniform(0, 10, matches), rng.uniform(-3, 3, matches), rng.uniform(0, 3, matches)])
        n = rng.normal(size=(matches, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        for owner, into in ((a, p_src), (b, p_dst)):
            into.append(world - truth[owner].t)  # local: the truth's frame (no rotation)
        src.append(np.full(matches, a))
        dst.append(np.full(matches, b))
        normal.append(n)
    match = Matches(torch.tensor(np.concatenate(src)), torch.tensor(np.concatenate(dst)),
                     torch.tensor(np.concatenate(p_src)), torch.tensor(np.concatenate(p_dst)),
                     torch.tensor(np.concatenate(normal)), torch.ones(len(pairs) * matches, dtype=torch.float64), 0.1)
    poses = torch.tensor(np.stack([s.pose_init.matrix() for s in subs]))
    gps = torch.tensor(np.stack([t.matrix() for t in truth]))
    cents = torch.zeros(m, 3, dtype=torch.float64)
    return poses, match, PoseTerms.of(subs, torch.device("cpu")), gps, cents, torch.tensor(_chain_colours(subs))


def run(sizes: list[int], sessions: int, matches: int, steps: int, out=print) -> list[dict[str, float]]:  # noqa: ANN001
    rows = []
    for size in sizes:
        poses, match, terms, gps, cents, colour = synthetic_region(size, sessions, matches)
        free = torch.ones(len(poses), dtype=torch.bool)
        t0 = time.perf_counter()
        final, taken = _gauss_newton(poses, match, terms, gps, cents, free, colour, steps)
        wall = time.perf_counter() - t0
        err = float((final[:, :3, 3] - gps[:, :3, 3]).norm(dim=1).square().mean().sqrt())
        start = float((poses[:, :3, 3] - gps[:, :3, 3]).norm(dim=1).square().mean().sqrt())
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        row = {"submaps": len(poses), "matches": len(match.src), "steps": taken, "s_per_step": wall / max(taken, 1),
               "start_rms_m": start, "final_rms_m": err, "peak_rss_mib": peak}
        out(f"submaps {row['submaps']:5d}  matches {row['matches']:8d}  steps {taken}  "
            f"s/step {row['s_per_step']:8.3f}  translation RMS {start:.3f} -> {err:.4f} m  peak RSS {peak:7.0f} MiB")
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fusion.eval.perf_register", description=__doc__.split("\n\n")[0])
    p.add_argument("--submaps", default="50,200,800", help="comma-separated region sizes (default 50,200,800)")
    p.add_argument("--sessions", type=int, default=5, help="parallel session chains (default 5)")
    p.add_argument("--matches", type=int, default=100, help="matches per overlapping submap pair (default 100)")
    p.add_argument("--steps", type=int, default=3, help="Levenberg-Marquardt steps per size (default 3)")
    args = p.parse_args(argv)
    try:
        sizes = [int(v) for v in args.submaps.split(",") if v]
    except ValueError:
        print(f"error: --submaps wants comma-separated integers, got {args.submaps!r}", file=sys.stderr)
        return 2
    run(sizes, args.sessions, args.matches, args.steps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
