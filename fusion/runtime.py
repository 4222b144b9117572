"""Where and how the fusion runs in this process: the torch device and the allocator tuning.

Allocator: glibc returns large freed blocks to the kernel (trim / per-allocation mmap) and
page-faults them back in on the next step (~8.5k minor faults per 8192-point step measured here,
~2.7k with the settings below; ~15-25 % more points per CPU-second). ``tune_allocator`` raises
``M_MMAP_THRESHOLD`` / ``M_TRIM_THRESHOLD`` with ``mallopt`` at run time, which works after the
process has started (glibc 2.36 here), so no ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
environment is needed in the CLI or the worker; ``SemanticSDFField`` calls it once per process. Opt
out with ``FLEETMAP_MALLOC_TUNE=0``; an explicit ``MALLOC_*_THRESHOLD_`` environment wins. Cost: freed
heap memory stays mapped up to the trim threshold (peak RSS is unchanged: it was needed anyway).
Note that setting only the trim threshold is much worse than neither (it turns off glibc's dynamic
mmap threshold: ~60k faults per step).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

MMAP_THRESHOLD = 2**30  # bytes: allocations below this come from the heap (paper batches: ~256 MiB)
TRIM_THRESHOLD = 2**31  # bytes of free heap top kept mapped
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters
_tuned: bool | None = None


def tune_allocator() -> bool:
    """Keep large temporaries on the heap between steps (glibc ``mallopt``); once per process, no-op
    elsewhere, when ``FLEETMAP_MALLOC_TUNE=0`` or when ``MALLOC_*_THRESHOLD_`` is in the environment.
    Returns whether the settings are in effect."""
    global _tuned
    if _tuned is not None:
        return _tuned
    _tuned = False
    if os.environ.get("FLEETMAP_MALLOC_TUNE", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        _tuned = bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    except (OSError, AttributeError):  # not glibc (musl, macOS)
        _tuned = False
    return _tuned


def cpu_threads() -> int:
    """Threads for the fusion's CPU-side work beside torch (scipy k-d tree queries of 10^5+ points: a
    registration's 2000-sample queries ran slower on two threads): torch's intra-op count, so a worker's
    ``FLEETMAP_TORCH_THREADS`` bounds both."""
    return max(1, torch.get_num_threads())


def resolve_device(name: str | None) -> torch.device:
    """``"auto"``/None → CUDA when available, else CPU."""
    if name in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@contextmanager
def reproducible(dev: torch.device) -> Iterator[None]:
    """On a CPU device, torch's deterministic kernels for the duration (the previous setting restored
    after): the same inputs and seed give the same field, poses and mesh, bit for bit, on one machine and
    thread count (another CPU or thread count reduces in another order: exact seed 1's sem F 0.774 on one
    machine, 0.784 on another; one and two threads differ in the third decimal). Without them two
    runs of one tile differed after 20 steps (a CPU kernel that accumulates in thread order) and the
    bench's figures moved between runs of the same code (sem F ±0.02, single-session share 5-19 % on exact
    seed 1). Cost: none measured (one 64 m tile, 200 steps, 2 threads: 7.9-9.7 s against 7.7-12.0 s).
    CUDA is left as it is: several of its kernels have no deterministic form and would raise."""
    if dev.type != "cpu" or torch.are_deterministic_algorithms_enabled():
        yield
        return
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(False)
