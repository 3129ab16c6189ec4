"""Does the prior help on this map? A check on each of the asset's own colour maps, one scale down.

A photo-trained prior can make textures worse than bicubic interpolation: on the Avocado at
x4 rrdn-thick's albedo was 0.9 dB below bicubic's (``pbrsr bench upscale``). Before a PBR-SR
run spends prior calls on the init and the pseudo-GT, each LR colour map (a centre crop of at
most ``CROP`` texels a side) is degraded once more by the scale (``degrade.degrade_image``,
the declared LR model), upscaled back by the prior and by bicubic, and both are compared
with the LR map itself: the prior initialises a map only if it wins on that map
(self-similarity across scales, as in zero-shot SR). The cost is one prior call on at most
``(CROP / s)^2`` pixels per colour map.
"""

from __future__ import annotations

import math

import numpy as np

from ..degrade import degrade_image
from .base import Prior
from .direct import bicubic_map, upscale_map

CROP = 512


def _centre(a: np.ndarray, size: int) -> np.ndarray:
    h, w = a.shape[:2]
    y, x = max(0, (h - size) // 2), max(0, (w - size) // 2)
    return a[y : y + size, x : x + size]


def prior_self_check(prior: Prior, colour_map: np.ndarray, scale: int) -> dict | None:
    """``{"prior_db", "bicubic_db", "texels", "use_prior"}`` for one colour map (H, W, C) as
    stored (sRGB), or None when it is not at least ``4 * scale`` texels a side (nothing to
    check on: the prior is used, as the paper does)."""
    rgb = _centre(np.asarray(colour_map, dtype=np.float32)[..., :3], CROP)
    if min(rgb.shape[:2]) < 4 * scale:
        return None
    small = degrade_image(rgb, scale)
    up_p = upscale_map(prior, small, "colour", scale)
    up_b = bicubic_map(small, "colour", scale)
    h = min(rgb.shape[0], up_p.shape[0])
    w = min(rgb.shape[1], up_p.shape[1])
    ref = rgb[:h, :w]
    n = ref.size

    def db(up: np.ndarray) -> float:
        se = float(((up[:h, :w, :3] - ref) ** 2).sum())
        return 100.0 if se <= 0 else 10.0 * math.log10(n / se)

    p, b = db(up_p), db(up_b)
    return {"prior_db": round(p, 3), "bicubic_db": round(b, 3), "texels": h * w, "use_prior": p > b}
