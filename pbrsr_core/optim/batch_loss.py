"""The pixel loss of one optimisation step (paper eq. 4, ``L_robust``): the batch's renders
against their targets, weighted by the per-view weight maps, over ``batch_views`` whole views
(``sampling="views"``) or ``pixels_per_step`` random covered pixels across every view
(``sampling="pixels"``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .gbuffers import concat_gbuffers, subset_gbuffer
from .losses import robust_pixel_terms, sample_weights, upsample_weights
from .targets import target_pixels

Render = Callable[[object], torch.Tensor]
"""G-buffer -> (P, 3) sRGB of its covered pixels, from the current maps."""


def view_batch_loss(
    batch: list[int], gbs, targets: list[np.ndarray], wmaps: torch.Tensor, render: Render, device
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(L_pix, L_reg)`` over the whole views ``batch`` (each at its full resolution: the
    weight maps are upsampled to it; uncovered pixels carry no loss)."""
    sq_all, w_all, v_all, cov_all = [], [], [], []
    for b, v in enumerate(batch):
        gb = gbs.get(v)
        h, w = gb.resolution
        sq = ((render(gb) - target_pixels(targets, v, gb.pix, device)) ** 2).sum(-1)
        full = torch.zeros(h * w, dtype=sq.dtype, device=device).index_put((gb.pix,), sq)
        cov = torch.zeros(h * w, dtype=torch.bool, device=device)
        cov[gb.pix] = True
        wup = upsample_weights(wmaps[v : v + 1], (h, w)).reshape(-1)
        sq_all.append(full)
        w_all.append(wup)
        cov_all.append(cov)
        v_all.append(torch.full((h * w,), b, dtype=torch.long, device=device))
    return robust_pixel_terms(
        torch.cat(sq_all), torch.cat(w_all), torch.cat(v_all), len(batch), torch.cat(cov_all)
    )


def pixel_batch_loss(
    n_pixels: int,
    npix: list[int],
    gbs,
    targets: list[np.ndarray],
    wmaps: torch.Tensor,
    render: Render,
    gen: torch.Generator,
    device,
) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """``(L_pix, L_reg, views)`` over ``n_pixels`` covered pixels drawn (from ``gen``) across
    every view (``npix`` covered pixels each), shaded in one pass; ``views``: those drawn
    from."""
    offsets = torch.tensor([0, *np.cumsum(npix).tolist()], dtype=torch.long)
    total = int(offsets[-1])
    n = min(n_pixels, total)
    flat = torch.randint(total, (n,), generator=gen).sort().values
    vid = torch.searchsorted(offsets[1:], flat, right=True)
    local = flat - offsets[vid]
    present = torch.unique(vid).tolist()
    subs, tg, vv, xy = [], [], [], []
    for j, v in enumerate(present):
        sel = local[vid == v].to(device)
        sub = subset_gbuffer(gbs.get(v), sel)
        subs.append(sub)
        tg.append(target_pixels(targets, v, sub.pix, device))
        h, w = sub.resolution
        px = (sub.pix % w).to(torch.float32)
        py = torch.div(sub.pix, w, rounding_mode="floor").to(torch.float32)
        xy.append(torch.stack([(2 * px + 1) / w - 1, (2 * py + 1) / h - 1], -1))
        vv.append(torch.full((sel.shape[0],), j, dtype=torch.long, device=device))
    sq = ((render(concat_gbuffers(subs)) - torch.cat(tg)) ** 2).sum(-1)
    vcat = torch.cat(vv)
    wv = sample_weights(wmaps[torch.tensor(present, device=device)], vcat, torch.cat(xy))
    l_pix, l_reg = robust_pixel_terms(sq, wv, vcat, len(present))
    return l_pix, l_reg, present
