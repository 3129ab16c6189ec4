"""Which texels a mesh's UVs cover: the region metrics are computed over and the optimiser may
change. Triangles are rasterised in texel space (texel centres inside the triangle, plus the
texels under each vertex so that sub-texel triangles still count)."""

from __future__ import annotations

import numba
import numpy as np
import torch

from .asset.model import Asset, TextureRef


@numba.njit(cache=True)
def raster_uv_mask(uv: np.ndarray, tris: np.ndarray, h: int, w: int, wrap: bool) -> np.ndarray:
    mask = np.zeros((h, w), dtype=np.bool_)
    for t in range(tris.shape[0]):
        x0 = uv[tris[t, 0], 0] * w - 0.5
        y0 = uv[tris[t, 0], 1] * h - 0.5
        x1 = uv[tris[t, 1], 0] * w - 0.5
        y1 = uv[tris[t, 1], 1] * h - 0.5
        x2 = uv[tris[t, 2], 0] * w - 0.5
        y2 = uv[tris[t, 2], 1] * h - 0.5
        if not (np.isfinite(x0) and np.isfinite(x1) and np.isfinite(x2)):
            continue
        if not (np.isfinite(y0) and np.isfinite(y1) and np.isfinite(y2)):
            continue
        ox = 0.0
        oy = 0.0
        if wrap:  # move the triangle so its first vertex lies in the first tile
            ox = np.floor((x0 + 0.5) / w) * w
            oy = np.floor((y0 + 0.5) / h) * h
        x0 -= ox
        x1 -= ox
        x2 -= ox
        y0 -= oy
        y1 -= oy
        y2 -= oy
        xmin = int(np.floor(min(x0, x1, x2)))
        xmax = int(np.ceil(max(x0, x1, x2)))
        ymin = int(np.floor(min(y0, y1, y2)))
        ymax = int(np.ceil(max(y0, y1, y2)))
        if xmax - xmin > 4 * w or ymax - ymin > 4 * h:
            continue  # absurd UVs: ignore rather than spin
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        for vx, vy in ((x0, y0), (x1, y1), (x2, y2)):
            ix = int(np.floor(vx + 0.5))
            iy = int(np.floor(vy + 0.5))
            if wrap:
                ix %= w
                iy %= h
            if 0 <= ix < w and 0 <= iy < h:
                mask[iy, ix] = True
        if area == 0.0:
            continue
        for y in range(ymin, ymax + 1):
            for x in range(xmin, xmax + 1):
                e0 = ((x1 - x) * (y2 - y) - (x2 - x) * (y1 - y)) / area
                e1 = ((x2 - x) * (y0 - y) - (x0 - x) * (y2 - y)) / area
                e2 = 1.0 - e0 - e1
                if e0 >= -1e-6 and e1 >= -1e-6 and e2 >= -1e-6:
                    ix = x
                    iy = y
                    if wrap:
                        ix %= w
                        iy %= h
                    if 0 <= ix < w and 0 <= iy < h:
                        mask[iy, ix] = True
    return mask


def transform_uv(uv: torch.Tensor, ref: TextureRef) -> torch.Tensor:
    """Apply a TextureRef's KHR_texture_transform matrix to (N, 2) UVs."""
    if ref.uv_transform is None:
        return uv
    m = torch.tensor(ref.uv_transform, dtype=uv.dtype, device=uv.device).reshape(3, 3)
    return uv @ m[:2, :2].T + m[:2, 2]


def coverage_masks(
    asset: Asset, sizes: dict[int, tuple[int, int]] | None = None
) -> dict[int, np.ndarray]:
    """Per image index, a (H, W) bool mask of the texels the mesh's UVs cover, through every
    material slot that samples the image. ``sizes`` overrides (H, W) per image (e.g. HR)."""
    mesh = asset.mesh
    tris_all = mesh.t_pos_idx.numpy()
    mats = mesh.t_mat.numpy()
    out: dict[int, np.ndarray] = {}
    for img in asset.images:
        if not img.roles:
            continue
        h, w = sizes[img.index] if sizes and img.index in sizes else (img.height, img.width)
        out[img.index] = np.zeros((h, w), dtype=bool)
    for mi in np.unique(mats):
        material = asset.material(int(mi))
        tris = tris_all[mats == mi]
        seen: set[tuple] = set()
        for ref in material.textures().values():
            if ref.image not in out or ref.texcoord not in mesh.v_uv:
                continue
            key = (ref.image, ref.texcoord, ref.uv_transform)
            if key in seen:
                continue
            seen.add(key)
            uv = transform_uv(mesh.v_uv[ref.texcoord].double(), ref).numpy()
            h, w = out[ref.image].shape
            out[ref.image] |= raster_uv_mask(uv, tris, h, w, True)
    return out
