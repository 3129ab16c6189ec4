"""Training views: the paper's fixed sphere, or views chosen for texel coverage, plus the render
resolution from texel density and which texels the chosen views see.

All positions are in the mesh's own frame, which the caller has normalised to unit size
(largest bounding-box extent 1, centred; see ``render.camera.normalize_transform``).

* :func:`fibonacci_directions` (n, 3) evenly spread unit vectors (deterministic).
* :func:`seen_texels` (H, W) bool per image: texels inside the UV footprint of triangles some
  view rasterised (``uvmask`` texel-space rasteriser), i.e. texels the loss can reach.
* :func:`select_coverage_views`: greedy set cover over candidate views (each candidate
  rasterised once at a small probe resolution): repeatedly take the view that adds the most
  not-yet-seen texels (coverage fraction averaged over images), until ``max_views`` or the
  gain drops under ``min_new_texels``.
* :func:`texel_density_resolution`: the render side at which the median covered pixel spans
  ``texel_footprint`` HR texels (from the rasteriser's UV derivatives), rounded to a multiple
  of the scale and clamped.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import torch

from ..asset.model import Material, Mesh, TextureRef
from ..render import camera as cam
from ..uvmask import raster_uv_mask, transform_uv


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors on a Fibonacci sphere (y up), deterministic."""
    if n < 1:
        raise ValueError("need at least one direction")
    i = np.arange(n, dtype=np.float64) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - y * y, 0.0, 1.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.sin(phi), y, r * np.cos(phi)], axis=1)


def sphere_cameras(
    n: int, distance: float, fov_deg: float, resolution: int | tuple[int, int]
) -> list[cam.Camera]:
    """``n`` cameras on a Fibonacci sphere of radius ``distance`` looking at the origin."""
    res = (
        (resolution, resolution) if isinstance(resolution, int) else (resolution[0], resolution[1])
    )
    return [
        cam.look_at(distance * d, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov_deg, res)
        for d in fibonacci_directions(n)
    ]


def with_resolution(c: cam.Camera, resolution: int | tuple[int, int]) -> cam.Camera:
    """The same view at another (H, W); the projection is rebuilt for the new aspect."""
    h, w = (resolution, resolution) if isinstance(resolution, int) else resolution
    return cam.Camera(
        eye=c.eye.copy(),
        world_to_cam=c.world_to_cam.copy(),
        proj=cam.perspective(c.fov_deg, w / h),
        resolution=(int(h), int(w)),
        fov_deg=c.fov_deg,
    )


def image_refs(materials: list[Material], image: int) -> list[tuple[int, TextureRef]]:
    """(material index, TextureRef) of every slot that samples ``image`` (deduplicated by
    material, texcoord and transform)."""
    out: list[tuple[int, TextureRef]] = []
    seen: set[tuple] = set()
    for m in materials:
        for ref in m.textures().values():
            if ref.image != image:
                continue
            key = (m.index, ref.texcoord, ref.uv_transform)
            if key not in seen:
                seen.add(key)
                out.append((m.index, ref))
    return out


def uv_texel_mask(
    mesh: Mesh,
    materials: list[Material],
    image: int,
    size: tuple[int, int],
    triangles: torch.Tensor | None = None,
) -> np.ndarray:
    """(H, W) bool: texels of ``image`` (at ``size``) under the UVs of ``triangles`` (default
    every triangle), through every material slot that samples it."""
    h, w = size
    mask = np.zeros((h, w), dtype=bool)
    t_mat = mesh.t_mat.detach().cpu()
    tri_idx = mesh.t_pos_idx.detach().cpu()
    keep = torch.ones(t_mat.shape[0], dtype=torch.bool)
    if triangles is not None:
        keep = torch.zeros_like(keep)
        keep[triangles.detach().cpu().long()] = True
    for mi, ref in image_refs(materials, image):
        if ref.texcoord not in mesh.v_uv:
            continue
        sel = keep & (t_mat == mi)
        if not bool(sel.any()):
            continue
        uv = transform_uv(mesh.v_uv[ref.texcoord].detach().cpu().double(), ref).numpy()
        mask |= raster_uv_mask(uv, tri_idx[sel].numpy(), h, w, True)
    return mask


def visible_triangles(gbuffers: Iterable) -> torch.Tensor:
    """Sorted unique triangle ids of covered pixels over G-buffers (cpu, int64)."""
    tris = [gb.tri.detach().cpu().long() for gb in gbuffers]
    if not tris:
        return torch.zeros(0, dtype=torch.long)
    return torch.unique(torch.cat(tris))


def seen_texels(
    mesh: Mesh,
    materials: list[Material],
    gbuffers: Iterable,
    sizes: dict[int, tuple[int, int]],
) -> dict[int, np.ndarray]:
    """Per image, (H, W) bool: texels inside triangles some G-buffer covers."""
    vis = visible_triangles(list(gbuffers))
    return {i: uv_texel_mask(mesh, materials, i, hw, vis) for i, hw in sizes.items()}


def _coarse_size(hw: tuple[int, int], limit: int = 128) -> tuple[int, int]:
    h, w = hw
    f = max(1.0, max(h, w) / limit)
    return max(1, int(round(h / f))), max(1, int(round(w / f)))


def select_coverage_views(
    mesh: Mesh,
    materials: list[Material],
    images: list[int],
    candidates: list[cam.Camera],
    rasterize,
    *,
    max_views: int,
    min_new_texels: float,
    image_sizes: dict[int, tuple[int, int]],
    views_per_texel: int = 1,
) -> tuple[list[int], dict]:
    """Greedy texel-coverage view selection: each step adds the candidate that sees the most
    texels still seen by fewer than ``views_per_texel`` chosen views (several views per texel
    let the multi-view loss average out the prior's per-view hallucinations).

    ``rasterize(camera) -> GBuffer``; ``image_sizes`` (H, W) per image (coverage is counted on
    a grid of at most 128 per side). Returns the chosen candidate indices in order and a
    summary (``coverage`` per image of the chosen set, ``gains``).
    """
    sizes = {i: _coarse_size(image_sizes[i]) for i in images}
    total = {i: uv_texel_mask(mesh, materials, i, sizes[i]) for i in images}
    denom = {i: max(int(total[i].sum()), 1) for i in images}
    per_view: list[dict[int, np.ndarray]] = []
    for c in candidates:
        gb = rasterize(c)
        vis = visible_triangles([gb])
        per_view.append(
            {i: uv_texel_mask(mesh, materials, i, sizes[i], vis) & total[i] for i in images}
        )
    covered = {i: np.zeros(sizes[i], dtype=np.int32) for i in images}
    chosen: list[int] = []
    gains: list[float] = []
    remaining = set(range(len(candidates)))
    while remaining and len(chosen) < max_views:
        best, best_gain = -1, -1.0
        for v in sorted(remaining):
            g = sum(
                float((per_view[v][i] & (covered[i] < views_per_texel)).sum()) / denom[i]
                for i in images
            ) / max(len(images), 1)
            if g > best_gain:
                best, best_gain = v, g
        if chosen and best_gain < min_new_texels:
            break
        chosen.append(best)
        gains.append(best_gain)
        remaining.discard(best)
        for i in images:
            covered[i] += per_view[best][i]
    coverage = {i: float((covered[i] > 0).sum()) / denom[i] for i in images}
    return chosen, {"coverage": coverage, "gains": gains}


def median_footprint(gb, materials: list[Material], image_sizes: dict[int, tuple[int, int]]):
    """Median HR texels spanned by one pixel over the covered pixels of ``gb`` for the images in
    ``image_sizes`` (largest of the two screen axes), or None when nothing is textured."""
    vals = []
    if gb.num_pixels == 0:
        return None
    mats = (gb.mat if gb.mat is not None else torch.zeros_like(gb.tri)).detach().cpu().long()
    for i, (h, w) in image_sizes.items():
        for mi, ref in image_refs(materials, i):
            if ref.texcoord not in gb.uv_grad:
                continue
            sel = mats == mi
            if not bool(sel.any()):
                continue
            d = gb.uv_grad[ref.texcoord].detach().cpu().double()[sel]
            if ref.uv_transform is not None:
                m = torch.tensor(ref.uv_transform, dtype=torch.float64).reshape(3, 3)[:2, :2]
                dx = d[:, 0:2] @ m.T
                dy = d[:, 2:4] @ m.T
            else:
                dx, dy = d[:, 0:2], d[:, 2:4]
            sx = torch.sqrt((dx[:, 0] * w) ** 2 + (dx[:, 1] * h) ** 2)
            sy = torch.sqrt((dy[:, 0] * w) ** 2 + (dy[:, 1] * h) ** 2)
            f = torch.maximum(sx, sy)
            vals.append(f[torch.isfinite(f)])
    if not vals:
        return None
    allv = torch.cat(vals)
    return float(allv.median()) if allv.numel() else None


def texel_density_resolution(
    footprints: list[float],
    probe_res: int,
    *,
    texel_footprint: float,
    scale: int,
    min_res: int,
    max_res: int,
) -> int:
    """Render side such that the median pixel spans ``texel_footprint`` HR texels.

    ``footprints``: median HR texels per pixel of probe views rendered at ``probe_res``; the
    footprint scales as 1 / resolution. The result is a multiple of ``scale`` in
    [min_res, max_res] (rounded to the scale grid), so the LR render is ``res / scale``.
    """
    good = [f for f in footprints if f is not None and math.isfinite(f) and f > 0]
    res = probe_res * float(np.median(good)) / texel_footprint if good else float(max_res)
    res = min(max(res, float(min_res)), float(max_res))
    res = max(scale, int(round(res / scale)) * scale)
    while res > max_res and res - scale >= scale:
        res -= scale
    return res
