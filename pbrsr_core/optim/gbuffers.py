"""The training views' G-buffers: rasterised once per view and kept in a bounded cache
(:class:`GBufferStore`), restricted to sampled pixels or joined across views for one shading
pass, and shaded into tonemapped sRGB (:func:`render_srgb`). Generic over the renderer's
GBuffer dataclass fields."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from types import ModuleType
from typing import Any

import torch

from . import views as vsel

BACKGROUND = 0.0
"""Linear value of the pixels no surface covers, in every render the optimiser makes."""


def _num_pixels(gb) -> int:
    return int(gb.pix.shape[0])


def subset_gbuffer(gb, idx: torch.Tensor):
    """The G-buffer restricted to covered pixels ``idx`` (indices into its P entries)."""
    p = _num_pixels(gb)
    changes: dict[str, Any] = {}
    for f in fields(gb):
        v = getattr(gb, f.name)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == p:
            changes[f.name] = v[idx]
        elif isinstance(v, dict) and all(
            isinstance(x, torch.Tensor) and x.shape[0] == p for x in v.values()
        ):
            changes[f.name] = {k: x[idx] for k, x in v.items()}
    return replace(gb, **changes)


def concat_gbuffers(gbs: list):
    """One G-buffer holding the covered pixels of several (same-resolution) G-buffers."""
    first = gbs[0]
    p = _num_pixels(first)
    changes: dict[str, Any] = {}
    for f in fields(first):
        v = getattr(first, f.name)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == p:
            changes[f.name] = torch.cat([getattr(g, f.name) for g in gbs])
        elif isinstance(v, dict) and all(
            isinstance(x, torch.Tensor) and x.shape[0] == p for x in v.values()
        ):
            changes[f.name] = {k: torch.cat([getattr(g, f.name)[k] for g in gbs]) for k in v}
    return replace(first, **changes)


def render_srgb(gb, materials, textures, light, shade_mod) -> torch.Tensor:
    """Shade the covered pixels of ``gb`` and tonemap: (P, 3) sRGB."""
    rgba = shade_mod.shade(gb, materials, textures, light)
    return shade_mod.tonemap(rgba[:, :3])


def gbuffer_bytes(gb) -> int:
    """Bytes held by a G-buffer's tensors."""
    n = 0
    for f in fields(gb):
        v = getattr(gb, f.name)
        vals = v.values() if isinstance(v, dict) else [v]
        n += sum(t.numel() * t.element_size() for t in vals if isinstance(t, torch.Tensor))
    return n


class GBufferStore:
    """The G-buffers of a fixed list of cameras, rasterised once each and kept while they fit
    in ``max_bytes`` (least recently used ones are dropped and rasterised again on demand: the
    paper's 750 views at 1024^2 would need ~80 GB). Records covered pixel counts and the
    triangles each view sees on the first pass."""

    def __init__(self, cameras: list, rasterize, max_bytes: int):
        self.cameras = cameras
        self.rasterize = rasterize
        self.max_bytes = max_bytes
        self.items: OrderedDict[int, object] = OrderedDict()
        self.bytes = 0
        self.npix: dict[int, int] = {}
        self.visible: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def get(self, k: int):
        gb = self.items.get(k)
        if gb is not None:
            self.items.move_to_end(k)
            return gb
        gb = self.rasterize(self.cameras[k])
        if k not in self.npix:
            self.npix[k] = _num_pixels(gb)
            self.visible[k] = vsel.visible_triangles([gb])
        size = gbuffer_bytes(gb)
        if size <= self.max_bytes:
            self.items[k] = gb
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, old = self.items.popitem(last=False)
                self.bytes -= gbuffer_bytes(old)
        return gb


@dataclass(frozen=True)
class RenderScene:
    """What every render of a run shares: the mesh (on the run's device), its materials, the
    light, the shading module and ``rasterize(camera) -> GBuffer``."""

    mesh: object
    materials: list
    light: object
    shade: ModuleType  # pbrsr_core.render.shade
    rasterize: Callable

    def render(self, gb, textures) -> torch.Tensor:
        """:func:`render_srgb` of ``gb`` with ``textures``."""
        return render_srgb(gb, self.materials, textures, self.light, self.shade)
