"""Roughness and metallic upscaled with the material's colour map as guide.

In an authored asset the roughness and metallic maps change where the paint, the label or the
metal part changes, and so does the colour map, which the prior upscales best. A local linear
model ``p = a . I + b`` of the data channel ``p`` in the colour ``I`` is fitted in every
(2r+1)² window of the LR maps (the guided filter, He, Sun and Tang 2010; fitted at the LR
size and applied at the HR size as in He and Sun's fast guided filter, 2015); its averaged
coefficients, interpolated to the HR size, are applied to the upscaled colour map, and the
result is back-projected onto the LR channel (prior/backproject.py). Where the channel does not
follow the colour (``a`` near 0), it comes out as a smooth interpolation.

It is one of the upscales a channel's blend weighs (prior/blend.py), scored one scale down
with the colour map upscaled by the source the colour map's own check chose. ``RADIUS`` and
``EPS`` were chosen on the roughness and metallic maps of the CC0 texture set (x4, 512²
crops), with no benchmark asset taking part (docs/METHOD.md, "Roughness and metallic guided
by the colour map").
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

from ..asset.model import Asset
from ..degrade import degrade_image, run_kernel
from ..filters import box_mean
from .backproject import back_project
from .selfcheck import CROP, _centre

RADIUS = 1
"""Window radius in LR texels."""
EPS = 1e-4
"""Regularisation of the fit (values in [0, 1]): larger keeps the channel smoother."""
CHANNELS = (1, 2)
"""The channels of a metallic-roughness image that may follow its colour map: roughness (G)
and metallic (B). Occlusion (R) follows the geometry, not the paint."""


def guide_pairs(asset: Asset, indices: set[int]) -> dict[int, int]:
    """{metallic-roughness image: the colour image that guides it}, for every image of
    ``indices`` that each material using it as ``metallic_roughness`` pairs with the same
    ``base_color`` image of ``indices`` through the same UVs (texcoord and transform); an
    image without such a single partner is left out."""
    pairs: dict[int, int | None] = {}
    for m in asset.materials:
        mr, bc = m.metallic_roughness, m.base_color
        if mr is None or mr.image not in indices:
            continue
        ok = (
            bc is not None
            and bc.image in indices
            and bc.image != mr.image
            and bc.texcoord == mr.texcoord
            and bc.uv_transform == mr.uv_transform
        )
        partner = bc.image if ok and bc is not None else None
        if pairs.get(mr.image, partner) != partner:
            partner = None
        pairs[mr.image] = partner
    return {i: g for i, g in pairs.items() if g is not None}


def _t(a: np.ndarray, dtype: type = np.float64) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=dtype)).permute(2, 0, 1)[None]


def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(x.shape[-2:]) == size:
        return x
    return F.interpolate(x, size=size, mode="bicubic", align_corners=False, antialias=True)


def guided_upscale(
    lr: np.ndarray,
    guide_lr: np.ndarray,
    guide_hr: np.ndarray,
    scale: int,
    *,
    radius: int = RADIUS,
    eps: float = EPS,
) -> np.ndarray:
    """``lr`` (h, w, C) data channels upscaled to (s*h, s*w, C) with ``guide_lr`` (any size,
    3 colour channels first) as the guide's LR and ``guide_hr`` (any size) as its upscaled
    version; each guide is resampled to the channel's grid. Values in [0, 1]."""
    if lr.ndim != 3 or guide_lr.ndim != 3 or guide_hr.ndim != 3:
        raise ValueError("lr, guide_lr and guide_hr must be (H, W, C) arrays")
    h, w = lr.shape[:2]
    size_hr = (h * scale, w * scale)
    with torch.inference_mode():
        i_lr = _resize(_t(guide_lr[..., :3]), (h, w))
        i_hr = _resize(_t(guide_hr[..., :3], np.float32), size_hr)  # the HR side in float32
        m_i = box_mean(i_lr, radius)
        var = torch.stack(
            [
                box_mean(i_lr[:, j : j + 1] * i_lr[:, k : k + 1], radius)[:, 0]
                - m_i[:, j] * m_i[:, k]
                for j in range(3)
                for k in range(3)
            ],
            -1,
        ).reshape(h * w, 3, 3) + eps * torch.eye(3, dtype=torch.float64)
        out = []
        for c in range(lr.shape[2]):
            p = _t(lr[..., c : c + 1])
            m_p = box_mean(p, radius)
            cov = (box_mean(i_lr * p, radius) - m_i * m_p)[0].permute(1, 2, 0).reshape(h * w, 3, 1)
            a = torch.linalg.solve(var, cov)[..., 0].reshape(h, w, 3).permute(2, 0, 1)[None]
            b = m_p - (a * m_i).sum(1, keepdim=True)
            a, b = box_mean(a, radius).float(), box_mean(b, radius).float()
            q = F.interpolate(b, size=size_hr, mode="bilinear")
            for k in range(3):  # one HR coefficient plane at a time
                q += (
                    F.interpolate(a[:, k : k + 1], size=size_hr, mode="bilinear")
                    * i_hr[:, k : k + 1]
                )
            q.clamp_(0.0, 1.0)
            out.append(back_project(q, p.float(), scale)[0, 0])
        hr = torch.stack(out, -1).nan_to_num_(0.0).clamp_(0.0, 1.0)
    return hr.numpy().astype(np.float32)


def guided_check_upscale(
    kept: dict,
    size: tuple[int, int],
    guide_lr: np.ndarray,
    upscale_guide: Callable[[np.ndarray, int], np.ndarray],
    channels: list[int],
) -> np.ndarray:
    """The guided upscale of ``channels`` of a map of ``size`` (H, W) from one scale down, as
    its self-check upscaled the candidates (``kept``, what
    :func:`~.selfcheck.prior_self_check` keeps): the guide resampled to the map's grid, its
    centre crop degraded by the same factor and upscaled back by
    ``upscale_guide(pixels, factor)`` (what the run will guide with). (h, w, len(channels)),
    cut to the check's mask."""
    with torch.inference_mode():
        g = _resize(_t(guide_lr[..., :3]), size)[0].permute(1, 2, 0).numpy().astype(np.float32)
    f = kept["factor"]
    g_small = degrade_image(_centre(g, CROP), f, kernel=run_kernel())
    up = guided_upscale(kept["small"][..., channels], g_small, upscale_guide(g_small, f), f)
    h, w = kept["mask"].shape
    return up[:h, :w]
