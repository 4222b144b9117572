"""Parse time of a large submap PLY upload, ASCII vs binary: ``python -m fusion.eval.meshio_bench``.

Builds a grid mesh of ``--faces`` triangles (default 2,000,000, the default upload limit) with face
labels, writes it as ASCII and as binary little-endian PLY, and prints the best of ``--repeat``
``read_submap_ply`` times for each (``--plyfile`` also times plyfile's row-by-row ASCII reader,
which the ASCII path used before). Run it pinned to one core, e.g. ``taskset -c 0``.
"""

from __future__ import annotations

import argparse
import io
import time
from collections.abc import Callable

import numpy as np
import plyfile

from fusion.meshio import MeshLimits, read_submap_ply, write_submap_ply
from fusion.types import SemanticMesh


def grid_mesh(n_faces: int) -> SemanticMesh:
    """About ``n_faces`` triangles on a square grid, 0.25 m cells (exact in decimal and binary)."""
    side = max(1, int(np.sqrt(n_faces / 2)))
    ys, xs = np.mgrid[0 : side + 1, 0 : side + 1]
    vertices = np.stack([xs.ravel() * 0.25, ys.ravel() * 0.25, np.zeros(xs.size)], axis=1)
    a = (ys[:-1, :-1] * (side + 1) + xs[:-1, :-1]).ravel()
    b, c, d = a + 1, a + side + 1, a + side + 2
    faces = np.concatenate([np.stack([a, b, c], axis=1), np.stack([b, d, c], axis=1)])
    labels = 1 + np.arange(len(faces)) % 3
    return SemanticMesh(vertices=vertices, faces=faces, face_labels=labels)


def ascii_ply(mesh: SemanticMesh) -> bytes:
    """ASCII submap PLY (as ``write_submap_ply(mesh, "ascii")`` writes it, but fast to produce)."""
    out = io.BytesIO()
    out.write(
        (
            "ply\nformat ascii 1.0\n"
            f"element vertex {len(mesh.vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(mesh.faces)}\nproperty list uchar int vertex_indices\nproperty uchar label\n"
            "end_header\n"
        ).encode()
    )
    np.savetxt(out, mesh.vertices, fmt="%.2f")
    rows = np.concatenate([np.asarray(mesh.faces), np.asarray(mesh.face_labels)[:, None]], axis=1)
    np.savetxt(out, rows, fmt="3 %d %d %d %d")
    return out.getvalue()


def best_time(fn: Callable[[], object], repeat: int) -> str:
    """Best wall-clock and CPU (process) seconds of ``repeat`` calls; CPU time is the figure to
    trust on a busy machine."""
    wall, cpu = [], []
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return f"{min(cpu):.2f} s CPU ({min(wall):.2f} s wall)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--faces", type=int, default=2_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--plyfile", action="store_true", help="also time plyfile's ASCII reader (slow)")
    args = parser.parse_args()
    mesh = grid_mesh(args.faces)
    text, binary = ascii_ply(mesh), write_submap_ply(mesh)
    limits = MeshLimits(max_faces=max(len(mesh.faces), MeshLimits().max_faces))
    parsed = read_submap_ply(text, limits)
    assert np.array_equal(parsed.vertices, mesh.vertices) and np.array_equal(parsed.faces, mesh.faces)
    assert np.array_equal(parsed.face_labels, mesh.face_labels)
    print(f"{len(mesh.faces)} faces, {len(mesh.vertices)} vertices")
    t_ascii = best_time(lambda: read_submap_ply(text, limits), args.repeat)
    print(f"ascii  ({len(text) / 1e6:.1f} MB): read_submap_ply {t_ascii}")
    t_binary = best_time(lambda: read_submap_ply(binary, limits), args.repeat)
    print(f"binary ({len(binary) / 1e6:.1f} MB): read_submap_ply {t_binary}")
    if args.plyfile:
        t_old = best_time(lambda: plyfile.PlyData.read(io.BytesIO(text)), 1)
        print(f"ascii via plyfile.PlyData.read (the reader used before): {t_old}")


if __name__ == "__main__":
    main()
