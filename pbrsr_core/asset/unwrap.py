"""UV unwrapping of primitives that lack a TEXCOORD their material needs (xatlas).

The paper allows generating a UV atlas when an asset has none. xatlas cuts the surface into
charts and packs them into [0, 1]^2; cutting splits vertices along seams, so the result is a
*re-indexed* primitive: ``vmapping`` (V',) says which original vertex each new vertex copies,
``indices`` (T, 3) are triangles over the new vertices (one per input triangle, same order)
and ``uv`` (V', 2) the new coordinates. The loader gathers every attribute through
``vmapping``; the writer stores the re-indexed primitive with its new TEXCOORD accessors.
"""

from __future__ import annotations

import numpy as np

from ..errors import UnprocessableAsset
from .model import UnwrappedPrimitive

# Packing: a 1024-texel atlas with 4 texels between charts keeps charts apart down to
# 256-texel textures (1 texel), so bilinear sampling and mip-levels do not bleed across.
DEFAULT_RESOLUTION = 1024
DEFAULT_PADDING = 4


def unwrap_triangles(
    pos: np.ndarray,
    tri: np.ndarray,
    *,
    resolution: int = DEFAULT_RESOLUTION,
    padding: int = DEFAULT_PADDING,
    what: str = "a mesh",
) -> UnwrappedPrimitive:
    """Generate a UV atlas for the triangles ``tri`` (T, 3) int over ``pos`` (V, 3).

    Returns an :class:`UnwrappedPrimitive` with ``uvs`` holding the atlas under key 0 (callers
    rename it to the TEXCOORD sets they need). Degenerate (zero-area) triangles are kept, with
    UVs on a point. Positions are centred and scaled to unit size first so that meshes at any
    scale (1e-4 .. 1e4) unwrap alike. Raises UnprocessableAsset when xatlas fails.
    """
    import xatlas

    pos = np.asarray(pos, dtype=np.float64)
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    if tri.shape[0] == 0:
        return UnwrappedPrimitive(
            vmapping=np.arange(pos.shape[0], dtype=np.int64),
            indices=np.zeros((0, 3), dtype=np.int64),
            uvs={0: np.zeros((pos.shape[0], 2), dtype=np.float32)},
        )
    if tri.min() < 0 or tri.max() >= pos.shape[0]:
        raise ValueError("triangle indices out of range")
    used = pos[np.unique(tri)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    extent = float(np.max(hi - lo))
    scale = 1.0 / extent if extent > 0 and np.isfinite(extent) else 1.0
    unit = ((pos - (lo + hi) / 2) * scale).astype(np.float32)
    atlas = xatlas.Atlas()
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    try:
        atlas.add_mesh(unit, tri.astype(np.uint32))
        atlas.generate(pack_options=pack)
        vmapping, indices, uv = atlas[0]
    except (RuntimeError, ValueError, IndexError) as exc:
        raise UnprocessableAsset(f"{what} could not be unwrapped ({exc})") from None
    vmapping = np.asarray(vmapping, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    uv = np.asarray(uv, dtype=np.float32).reshape(-1, 2)
    if (
        indices.shape != tri.shape
        or uv.shape[0] != vmapping.shape[0]
        or (indices.size and indices.max() >= vmapping.shape[0])
        or not np.isfinite(uv).all()
    ):
        raise UnprocessableAsset(f"{what} could not be unwrapped (inconsistent atlas)")
    uv = np.clip(uv, 0.0, 1.0)
    return UnwrappedPrimitive(vmapping=vmapping, indices=indices, uvs={0: uv})
