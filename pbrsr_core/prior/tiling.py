"""Overlapping-tile inference with blended seams, and the default tile size.

An image is cut into tiles of ``tile`` x ``tile`` LR pixels whose starts step by
``tile - overlap``; the last tile on each axis is aligned with the image edge, so every tile
has the same size (good for batching and for caching kernels). Each tile's upscaled output is
weighted by a separable window that is 1 inside and, on a side shared with a neighbour, 0 for
the first quarter of the overlap (where the tile's zero padding makes the network's output
wrong), then a linear ramp across the middle half. The per-axis windows are normalised by
their sums, so the blend is a partition of unity and the result needs no final division.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from .. import runtime

TileFn = Callable[[torch.Tensor], torch.Tensor]


def tile_layout(length: int, tile: int, overlap: int) -> tuple[int, list[int]]:
    """Tile length and start offsets covering ``[0, length)`` with tiles of at most ``tile``
    pixels sharing at least ``overlap`` pixels with each neighbour. The fewest tiles that fit
    are used, shrunk to the smallest equal size that still covers the axis (so 1024 px with
    512-px tiles and 32 px overlap gives 3 tiles of 363, not 3 of 512); starts are spread
    evenly, the first at 0 and the last ending at ``length``."""
    if tile <= 0 or overlap < 0 or overlap >= tile:
        raise ValueError(f"need tile > overlap >= 0, got tile={tile}, overlap={overlap}")
    if length <= tile:
        return length, [0]
    n = -(-(length - overlap) // (tile - overlap))
    size = -(-(length - overlap) // n) + overlap
    step = (length - size) / (n - 1)
    return size, [round(k * step) for k in range(n)]


def tile_starts(length: int, tile: int, overlap: int) -> list[int]:
    """Start offsets of :func:`tile_layout`."""
    return tile_layout(length, tile, overlap)[1]


def _ramp(n: int, device: torch.device) -> torch.Tensor:
    """Rising weights over ``n`` output pixels: 0 in the first quarter, linear in the middle
    half, 1 in the last quarter. Shape (n,)."""
    t = (torch.arange(n, device=device, dtype=torch.float32) + 0.5) / max(n, 1)
    return ((t - 0.25) / 0.5).clamp(0.0, 1.0)


def axis_windows(
    length: int, starts: list[int], tile: int, overlap: int, scale: int, device: torch.device
) -> list[torch.Tensor]:
    """Per-tile 1-D blending weights along one axis, in output pixels, normalised so that
    their sum over tiles is 1 at every output position; ``tile`` is the tile length of
    :func:`tile_layout`. Each entry has shape (min(tile, length) * scale,)."""
    size = min(tile, length) * scale
    ramp_len = overlap * scale
    raw = []
    for k, _start in enumerate(starts):
        w = torch.ones(size, device=device)
        if ramp_len > 0:
            if k > 0:
                w[:ramp_len] = _ramp(ramp_len, device)
            if k < len(starts) - 1:
                w[size - ramp_len :] = torch.minimum(
                    w[size - ramp_len :], _ramp(ramp_len, device).flip(0)
                )
        raw.append(w)
    total = torch.zeros(length * scale, device=device)
    for w, start in zip(raw, starts, strict=True):
        total[start * scale : start * scale + size] += w
    if bool((total <= 0).any()):  # cannot happen for overlap < tile; guard against misuse
        raise ValueError("tile windows leave pixels uncovered")
    return [w / total[s * scale : s * scale + size] for w, s in zip(raw, starts, strict=True)]


def count_tiles(height: int, width: int, tile: int, overlap: int) -> int:
    """Number of tiles :func:`run_tiled` will run for one (height, width) image."""
    return len(tile_starts(height, tile, overlap)) * len(tile_starts(width, tile, overlap))


def run_tiled(
    fn: TileFn,
    image: torch.Tensor,
    scale: int,
    tile: int,
    overlap: int,
    on_tile: Callable[[], None] | None = None,
) -> torch.Tensor:
    """Upscale one image (1, C, H, W) with ``fn`` (maps (1, C, h, w) -> (1, C', s*h, s*w))
    tile by tile. Returns (1, C', s*H, s*W) on ``image.device``; ``on_tile`` is called after
    each tile (for progress and cancellation)."""
    if image.ndim != 4 or image.shape[0] != 1:
        raise ValueError(f"run_tiled takes one image (1, C, H, W), got {tuple(image.shape)}")
    _, _, h, w = image.shape
    th, ys = tile_layout(h, tile, overlap)
    tw, xs = tile_layout(w, tile, overlap)
    if len(ys) == 1 and len(xs) == 1:
        whole = fn(image)
        if on_tile is not None:
            on_tile()
        return whole.to(image.device)
    dev = image.device
    wy = axis_windows(h, ys, th, overlap, scale, dev)
    wx = axis_windows(w, xs, tw, overlap, scale, dev)
    out: torch.Tensor | None = None
    for iy, y0 in enumerate(ys):
        for ix, x0 in enumerate(xs):
            res = fn(image[:, :, y0 : y0 + th, x0 : x0 + tw]).to(dev)
            if out is None:
                out = torch.zeros(1, res.shape[1], h * scale, w * scale, device=dev)
            weight = wy[iy][:, None] * wx[ix][None, :]
            oy, ox = y0 * scale, x0 * scale
            out[:, :, oy : oy + th * scale, ox : ox + tw * scale] += res * weight
            if on_tile is not None:
                on_tile()
    assert out is not None
    return out


def free_memory_bytes(device: torch.device) -> int:
    """Free memory on ``device``: CUDA's free bytes, or the host's MemAvailable (Linux);
    4 GiB when it cannot be read."""
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 4 << 30


def default_tile_size(
    device: torch.device, bytes_per_pixel: float, *, fraction: float = 0.25, cpu_max: int = 512
) -> int:
    """Largest tile side (LR pixels, a multiple of 32 in [64, 1024]; at most ``cpu_max`` on
    the CPU, past which the prior's tiles are not faster) whose estimated peak memory
    ``tile**2 * bytes_per_pixel`` fits in ``fraction`` of the free memory. The runtime's
    ``prior_tile`` overrides it."""
    tile = runtime.current().prior_tile
    if tile:
        return max(16, tile)
    budget = free_memory_bytes(device) * fraction
    side = int(math.sqrt(max(budget, 1.0) / max(bytes_per_pixel, 1.0)))
    side = side // 32 * 32
    upper = 1024 if device.type == "cuda" else min(cpu_max, 1024)
    return int(min(max(side, 64), upper))
