"""Detail crops of the upscaled maps: for every map, one region at texel scale as the input
has it (LR) and as the result has it (HR), chosen where the LR map has the most detail, so a
viewer can compare the two texel for texel (the dashboard's wipe sliders).

A crops folder holds ``<stem>_lr.png`` and ``<stem>_hr.png`` per map (``stem`` as the map's
file in the bundle's ``maps/``; 8-bit, alpha dropped) and ``crops.json``: a list of
:func:`write_map_crops`'s entries.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .asset.images import write_image
from .asset.model import Asset
from .maps import map_file_stem, role_label

CROPS_INDEX = "crops.json"
CROP_HR_TEXELS = 128  # side of an HR crop when the map is that large
MIN_LR_TEXELS = 16  # side of an LR crop at least (x8: a 128 HR crop shows 16 LR texels)
SEARCH_STEPS = 4  # candidate windows start every side/SEARCH_STEPS texels
SAMPLE_TEXELS = 1 << 20  # texels a region search looks at, at most about


def crop_side(lr_shape: tuple[int, ...], scale: int) -> int:
    """LR texels per side of a crop: CROP_HR_TEXELS / scale (at least MIN_LR_TEXELS), no more
    than the map's smaller side."""
    side = max(CROP_HR_TEXELS // max(scale, 1), MIN_LR_TEXELS)
    return max(1, min(side, int(lr_shape[0]), int(lr_shape[1])))


def detail_origin(pixels: np.ndarray, side: int) -> tuple[int, int]:
    """Top-left ``(x, y)`` of the ``side`` x ``side`` window of ``pixels`` (H, W, C) with the
    highest local variance (summed over the colour channels; alpha left out).

    Windows start on a grid of ``side // SEARCH_STEPS`` texels; among windows of equal
    variance (a flat map) the one nearest the centre wins. A map of more than
    ``SAMPLE_TEXELS`` texels is sampled on a regular sub-grid."""
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    colour = arr[:, :, : _colour_channels(arr.shape[2])]
    h, w = colour.shape[:2]
    side = max(1, min(side, h, w))
    step = max(1, side // SEARCH_STEPS)
    k = max(1, side // step)  # blocks per window side
    # a large map is sampled every `stride` texels (a power of two dividing the block size):
    # about SAMPLE_TEXELS texels in all
    stride = 1
    while step % (2 * stride) == 0 and (h // stride) * (w // stride) > SAMPLE_TEXELS:
        stride *= 2
    hb, wb, b = h // step, w // step, step // stride
    sampled = colour[::stride, ::stride][: hb * b, : wb * b]
    blocks = sampled.reshape(hb, b, wb, b, colour.shape[2])
    m1 = blocks.mean(axis=(1, 3), dtype=np.float64)
    m2 = np.square(blocks, dtype=np.float64).mean(axis=(1, 3))
    s1, s2 = _window_sums(m1, k), _window_sums(m2, k)
    n = float(k * k)
    variance = (s2 / n - (s1 / n) ** 2).sum(axis=-1)  # (hb - k + 1, wb - k + 1)
    ys, xs = np.nonzero(variance >= variance.max() - 1e-9)
    # origins in texels; the window must fit (the grid may cover less than the map)
    oy = np.minimum(ys * step, h - side)
    ox = np.minimum(xs * step, w - side)
    centre = (oy + side / 2 - h / 2) ** 2 + (ox + side / 2 - w / 2) ** 2
    best = int(np.argmin(centre))
    return int(ox[best]), int(oy[best])


def _colour_channels(channels: int) -> int:
    """Channels that carry colour or data: all but an alpha (the 2nd of 2, the 4th of 4)."""
    return channels - 1 if channels in (2, 4) else channels


def _window_sums(grid: np.ndarray, k: int) -> np.ndarray:
    """Sums of every k x k window of ``grid`` (h, w, C) -> (h - k + 1, w - k + 1, C)."""
    c = np.zeros((grid.shape[0] + 1, grid.shape[1] + 1, grid.shape[2]), dtype=np.float64)
    c[1:, 1:] = grid.cumsum(axis=0).cumsum(axis=1)
    return c[k:, k:] - c[:-k, k:] - c[k:, :-k] + c[:-k, :-k]


def _display(pixels: np.ndarray) -> np.ndarray:
    """The colour channels of a crop, clipped to [0, 1] (a grey map stays one channel)."""
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    arr = arr[:, :, : _colour_channels(arr.shape[2])]
    if arr.shape[2] == 2:  # two data channels: shown as R and G
        arr = np.concatenate([arr, np.zeros_like(arr[:, :, :1])], axis=2)
    return np.clip(np.nan_to_num(arr), 0.0, 1.0)


def write_map_crops(asset: Asset, hr: dict[int, np.ndarray], dest: Path) -> list[dict]:
    """Write an LR and an HR crop of every map in ``hr`` (image index -> HR pixels as stored)
    and ``crops.json`` into ``dest`` (created); return the index's entries.

    An entry: ``map`` (the stem), ``label``, ``lr``/``hr`` (file names), ``scale``,
    ``lr_region``/``hr_region`` ([x, y, width, height] in texels of each map) and
    ``lr_size``/``hr_size`` ([width, height])."""
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    entries = []
    for img in asset.images:
        if img.index not in hr:
            continue
        lr_px, hr_px = img.pixels, hr[img.index]
        sy, sx = hr_px.shape[0] // lr_px.shape[0], hr_px.shape[1] // lr_px.shape[1]
        side = crop_side(lr_px.shape, min(sx, sy))
        x, y = detail_origin(lr_px, side)
        stem = map_file_stem(img)
        names = {"lr": f"{stem}_lr.png", "hr": f"{stem}_hr.png"}
        write_image(dest / names["lr"], _display(lr_px[y : y + side, x : x + side]), 8, "png")
        hr_crop = hr_px[y * sy : (y + side) * sy, x * sx : (x + side) * sx]
        write_image(dest / names["hr"], _display(hr_crop), 8, "png")
        entries.append(
            {
                "map": stem,
                "label": role_label(img.roles),
                **names,
                "scale": min(sx, sy),
                "lr_region": [x, y, side, side],
                "hr_region": [x * sx, y * sy, side * sx, side * sy],
                "lr_size": [int(lr_px.shape[1]), int(lr_px.shape[0])],
                "hr_size": [int(hr_px.shape[1]), int(hr_px.shape[0])],
            }
        )
    (dest / CROPS_INDEX).write_text(json.dumps(entries, indent=1))
    return entries


def read_crop_index(folder: Path) -> list[dict]:
    """The entries of ``folder``'s ``crops.json`` (none when it has none)."""
    path = Path(folder) / CROPS_INDEX
    if not path.is_file():
        return []
    entries = json.loads(path.read_text())
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []
