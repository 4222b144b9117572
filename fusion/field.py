"""The neural semantic SDF of one tile: feature grid + positional encoding + geometry and semantic heads.

Frames: the field is queried with points in the *map* frame (metres); ``TileNormalizer`` maps the tile
box (tile + margin, height slab) to [0, 1]³ for the grid and the encoding. SDF outputs are metres,
positive in free space.
"""

from __future__ import annotations

import io
import math

import numpy as np
import torch
from torch import Tensor, nn

from fusion.config import FusionConfig
from fusion.grids import FeatureGrid, make_grid
from fusion.labels import NUM_CLASSES
from fusion.runtime import tune_allocator


class TileNormalizer(nn.Module):
    """Affine map of map-frame points in the box ``[lo, hi]`` (metres) to [0, 1]³ (per-axis scaling),
    after the rigid ``frame`` (4, 4): the frame the field was trained in, from the one it is queried in
    (identity, unless the field was carried along with its surface: :func:`moved_state`)."""

    lo: Tensor  # (3,) buffer
    extent: Tensor  # (3,) buffer
    frame: Tensor  # (4, 4) buffer

    def __init__(self, lo: Tensor, hi: Tensor) -> None:
        super().__init__()
        self.register_buffer("lo", lo.float().clone())  # (3,)
        self.register_buffer("extent", (hi - lo).float().clone())  # (3,)
        self.register_buffer("frame", torch.eye(4))
        self.moved = False  # ``frame`` is not the identity (kept in step by every state load): a fresh or
        # uncarried field skips the transform on its hot path
        self.register_load_state_dict_post_hook(TileNormalizer._frame_loaded)

    @staticmethod
    def _frame_loaded(module: nn.Module, incompatible: object) -> None:
        assert isinstance(module, TileNormalizer)
        module.moved = not torch.equal(module.frame, torch.eye(4, dtype=module.frame.dtype, device=module.frame.device))

    @property
    def aspect(self) -> tuple[float, float, float]:
        e = self.extent / self.extent.max()
        return (float(e[0]), float(e[1]), float(e[2]))

    @property
    def longest_m(self) -> float:
        return float(self.extent.max())

    def forward(self, x_map: Tensor) -> Tensor:
        """``(n, 3)`` map-frame metres → ``(n, 3)`` normalised."""
        if self.moved:
            f = self.frame
            x_map = x_map @ f[:3, :3].T + f[:3, 3]
        return (x_map - self.lo) / self.extent


class PositionalEncoding(nn.Module):
    """``[sin(2^k π x), cos(2^k π x)]`` for ``k < num_frequencies`` on normalised coordinates."""

    freqs: Tensor  # (F,) buffer

    def __init__(self, num_frequencies: int) -> None:
        super().__init__()
        self.register_buffer("freqs", (2.0 ** torch.arange(num_frequencies)) * math.pi)
        self.out_dim = 6 * num_frequencies

    def forward(self, x01: Tensor) -> Tensor:
        """``(n, 3)`` → ``(n, 6F)``."""
        if self.out_dim == 0:
            return x01.new_zeros(x01.shape[0], 0)
        xf = (x01[:, :, None] * self.freqs).reshape(x01.shape[0], -1)
        return torch.cat([torch.sin(xf), torch.cos(xf)], dim=-1)


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int) -> nn.Sequential:
    mods: list[nn.Module] = []
    d = in_dim
    for _ in range(layers):
        mods += [nn.Linear(d, hidden), nn.ReLU(inplace=True)]
        d = hidden
    mods.append(nn.Linear(d, out_dim))
    return nn.Sequential(*mods)


class GeometryHead(nn.Module):
    """Features → signed distance (metres) and confidence logit."""

    def __init__(self, in_dim: int, hidden: int, layers: int) -> None:
        super().__init__()
        self.net = mlp(in_dim, hidden, layers, 2)

    def forward(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """``(n, d)`` → sdf ``(n,)``, confidence logit ``(n,)``."""
        out = self.net(h)
        return out[:, 0], out[:, 1]


class SemanticHead(nn.Module):
    """Features → class logits ``(n, K)``."""

    def __init__(self, in_dim: int, hidden: int, layers: int, num_classes: int = NUM_CLASSES) -> None:
        super().__init__()
        self.net = mlp(in_dim, hidden, layers, num_classes)

    def forward(self, h: Tensor) -> Tensor:
        return self.net(h)


class SemanticSDFField(nn.Module):
    """``Ω(x) = {s(x), c(x), l(x)}`` over one tile box (map frame, metres)."""

    def __init__(self, config: FusionConfig, lo: Tensor, hi: Tensor) -> None:
        super().__init__()
        tune_allocator()  # glibc: keep large training temporaries on the heap (once per process, see fusion.runtime)
        self.norm = TileNormalizer(lo, hi)
        self.grid: FeatureGrid = make_grid(
            config.grid_type,
            self.norm.aspect,
            num_levels=config.num_levels,
            features_per_level=config.features_per_level,
            log2_table_size=config.log2_table_size,
            base_resolution=config.base_resolution,
            max_resolution=config.max_resolution,
        )
        self.pe = PositionalEncoding(config.pe_frequencies)
        in_dim = self.grid.out_dim + self.pe.out_dim
        self.geo = GeometryHead(in_dim, config.geo_hidden, config.geo_layers)
        self.sem = SemanticHead(in_dim, config.sem_hidden, config.sem_layers)

    def set_active_levels(self, k: int) -> None:
        self.grid.set_active_levels(k)

    def finest_active_cell_m(self) -> float:
        """Cell size (metres) of the finest active grid level: the numerical-gradient step scale."""
        return self.grid.finest_active_cell() * self.norm.longest_m

    def features(self, x_map: Tensor) -> Tensor:
        """``(n, 3)`` map frame → ``(n, d)`` grid features ‖ positional encoding."""
        x01 = self.norm(x_map)
        return torch.cat([self.grid(x01), self.pe(x01)], dim=-1)

    def sdf(self, x_map: Tensor) -> Tensor:
        """Signed distance ``(n,)`` in metres (positive in free space)."""
        return self.geo(self.features(x_map))[0]

    def forward(self, x_map: Tensor, semantics: bool = True) -> tuple[Tensor, Tensor, Tensor | None]:
        """sdf ``(n,)`` metres, confidence logit ``(n,)``, class logits ``(n, K)`` (None if not asked)."""
        h = self.features(x_map)
        s, c_logit = self.geo(h)
        return s, c_logit, (self.sem(h) if semantics else None)

    def numerical_gradient(self, x_map: Tensor, eps_m: float) -> Tensor:
        """Central-difference gradient of ``s`` ``(n, 3)`` with step ``eps_m`` metres (differentiable)."""
        n = x_map.shape[0]
        offs = torch.eye(3, dtype=x_map.dtype, device=x_map.device) * eps_m  # (3, 3)
        probes = torch.cat([x_map[:, None, :] + offs, x_map[:, None, :] - offs], dim=1)  # (n, 6, 3)
        s = self.sdf(probes.reshape(-1, 3)).view(n, 6)
        return (s[:, :3] - s[:, 3:]) / (2 * eps_m)


def field_from_state(state: dict[str, Tensor], config: FusionConfig) -> SemanticSDFField:
    """A tile field (tile frame) rebuilt from a saved ``state_dict`` (its box travels in ``norm.*``; a state
    saved before fields had a ``norm.frame`` was trained where it is queried)."""
    lo = state["norm.lo"].float()
    f = SemanticSDFField(config, lo, lo + state["norm.extent"].float())
    f.load_state_dict({"norm.frame": torch.eye(4)} | state)
    return f


def moved_state(state: dict[str, Tensor], motion: np.ndarray) -> dict[str, Tensor]:
    """``state``'s field carried by the rigid ``motion`` (4, 4, tile frame): the new field at ``motion · x``
    is the old one at ``x``, as for a surface that moved by ``motion`` (a re-alignment's poses: the tile's
    next reconstruction then starts from its last field where its surface now is). The grid and the
    heads are shared with ``state``, not copied."""
    frame = state.get("norm.frame", torch.eye(4)).double().numpy()
    return state | {"norm.frame": torch.from_numpy(frame @ np.linalg.inv(np.asarray(motion, np.float64))).float()}


def field_state(field: SemanticSDFField) -> dict[str, Tensor]:
    """A detached CPU copy of ``field``'s ``state_dict``: what a job keeps (``field_from_state``)."""
    return {k: v.detach().cpu().clone() for k, v in field.state_dict().items()}


def pack_state(state: dict[str, Tensor]) -> bytes:
    """A field state as bytes (a job's blob)."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def unpack_state(data: bytes) -> dict[str, Tensor]:
    """Inverse of :func:`pack_state` (tensors only: no code is unpickled)."""
    return torch.load(io.BytesIO(data), weights_only=True)
