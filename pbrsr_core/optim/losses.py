"""The PBR-SR losses (paper section 3.5, METHOD.md "Losses"), as plain differentiable functions.

Norm conventions (the paper writes ``||.||_1`` without saying sum or mean; a sum would tie
every lambda to the map resolution, so like ``torch.nn.L1Loss`` we use means):

* ``L_pix`` (robust): per view i, ``sum_uv W_i^2 ||I_i - P_i||_2^2 / sum_uv W_i^2`` over the
  *covered* pixels (``||.||_2^2`` sums the colour channels), then the mean over the views of
  the batch that cover at least one pixel.
* ``R(W) = sum_i mean_uv (1 - W_i^2)^2`` over every pixel of each view (sum over views, mean
  over pixels, exactly as METHOD.md writes it).
* ``L_pbr = sum_T w_T (mean|AvgPool_s(T) - T_lr| + lambda_ssim (1 - SSIM(AvgPool_s(T), T_lr)))``
  where a "map" T is a :class:`MapGroup`: some channels of one image (roughness = G of the
  metallicRoughness image, metallic = B, occlusion = R, albedo = RGB of baseColor, ...).
* ``L_tv = sum_T (mean|grad_x T| + mean|grad_y T|)``: ``whole_map.tv_loss`` (one fused pass).

All functions accept float32 or float64 and never produce NaN/Inf for inputs in range
(denominators are clamped, empty differences give 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .ssim import SsimTarget

_EPS = 1e-12


@dataclass(frozen=True)
class MapGroup:
    """One PBR "map" T of the paper inside an image: ``channels`` of that image, its
    consistency weight ``weight`` (w_T) and a readable ``name`` ("base_color",
    "roughness", "metallic", "occlusion", "normal", "emissive")."""

    name: str
    channels: tuple[int, ...]
    weight: float = 1.0


# ---------------------------------------------------------------------------------------------
# Robust pixel loss
# ---------------------------------------------------------------------------------------------


def upsample_weights(w: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinearly upsample per-view weight maps (B, h, w) to (B, H, W) (half-pixel centres,
    ``align_corners=False``)."""
    if w.ndim != 3:
        raise ValueError(f"weight maps must be (B, h, w), got {tuple(w.shape)}")
    return F.interpolate(w[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]


def sample_weights(w: torch.Tensor, view: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Weight-map values at arbitrary pixels: the same numbers as
    ``upsample_weights(w, (H, W))[view, y, x]``.

    ``w`` (V, h, w); ``view`` (P,) long; ``xy`` (P, 2) pixel centres in normalised [-1, 1]
    coordinates (x = (2 px + 1) / W - 1). Returns (P,).
    """
    if w.ndim != 3 or xy.ndim != 2 or xy.shape[1] != 2 or view.shape != xy.shape[:1]:
        raise ValueError("sample_weights expects w (V, h, w), view (P,), xy (P, 2)")
    vals = w.new_zeros(xy.shape[0])
    for v in torch.unique(view).tolist():  # grid_sample reads one image per batch entry
        sel = (view == v).nonzero(as_tuple=True)[0]
        grid = xy[sel].to(w.dtype).view(1, 1, -1, 2)
        s = F.grid_sample(
            w[v : v + 1, None], grid, mode="bilinear", padding_mode="border", align_corners=False
        )
        vals = vals.index_put((sel,), s.reshape(-1))
    return vals


def robust_pixel_terms(
    sq_err: torch.Tensor,
    weight: torch.Tensor,
    view: torch.Tensor,
    n_views: int,
    covered: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(L_pix, R(W))`` from per-pixel values of several views.

    ``sq_err`` (P,) squared colour error ``||I - P||_2^2`` of each pixel; ``weight`` (P,)
    W in [0, 1]; ``view`` (P,) long in [0, n_views); ``covered`` (P,) bool, pixels that take
    part in ``L_pix`` (default all). Every given pixel takes part in ``R``.
    """
    if not (sq_err.shape == weight.shape == view.shape) or sq_err.ndim != 1:
        raise ValueError("sq_err, weight and view must be 1-D tensors of the same length")
    w2 = weight * weight
    cov = torch.ones_like(w2) if covered is None else covered.to(w2.dtype)
    num = torch.zeros(n_views, dtype=w2.dtype, device=w2.device).index_add(
        0, view, cov * w2 * sq_err
    )
    den = torch.zeros_like(num).index_add(0, view, cov * w2)
    cnt_cov = torch.zeros_like(num).index_add(0, view, cov)
    has = cnt_cov > 0
    per_view = num / den.clamp_min(_EPS)
    l_pix = (
        per_view[has].mean() if bool(has.any()) else (sq_err * 0).sum()
    )  # keeps the graph when nothing is covered
    reg_sum = torch.zeros_like(num).index_add(0, view, (1.0 - w2) ** 2)
    cnt = torch.zeros_like(num).index_add(0, view, torch.ones_like(w2))
    reg = (reg_sum / cnt.clamp_min(1.0)).sum()
    return l_pix, reg


def robust_pixel_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense form of :func:`robust_pixel_terms`.

    ``pred``, ``target`` (B, H, W, C); ``weight`` (B, H, W) in [0, 1] (already upsampled);
    ``mask`` (B, H, W) bool, covered pixels (default all). Returns ``(L_pix, R(W))``.
    """
    if pred.shape != target.shape or pred.ndim != 4:
        raise ValueError(
            f"pred and target must be (B, H, W, C) of one shape, got {tuple(pred.shape)} and "
            f"{tuple(target.shape)}"
        )
    b, h, w, _ = pred.shape
    if weight.shape != (b, h, w):
        raise ValueError(f"weight must be {(b, h, w)}, got {tuple(weight.shape)}")
    sq = ((pred - target) ** 2).sum(-1).reshape(-1)
    view = torch.arange(b, device=pred.device).repeat_interleave(h * w)
    cov = None if mask is None else mask.reshape(-1)
    return robust_pixel_terms(sq, weight.reshape(-1), view, b, cov)


# ---------------------------------------------------------------------------------------------
# PBR consistency and TV
# ---------------------------------------------------------------------------------------------


def map_factor(hr: torch.Tensor | np.ndarray, lr: torch.Tensor | np.ndarray) -> int:
    """The factor an HR map (H, W, C) has over its LR map (its height over the LR's)."""
    return int(hr.shape[0]) // int(lr.shape[0])


def avg_pool_map(hr: torch.Tensor, scale: int) -> torch.Tensor:
    """AvgPool with kernel = stride = ``scale`` of an (H, W, C) map -> (H/s, W/s, C)."""
    if hr.ndim != 3:
        raise ValueError(f"map must be (H, W, C), got {tuple(hr.shape)}")
    if scale < 1 or hr.shape[0] % scale or hr.shape[1] % scale:
        raise ValueError(f"map of {hr.shape[1]}x{hr.shape[0]} is not divisible by scale {scale}")
    if scale == 1:
        return hr
    h, w, c = hr.shape
    # one pass over the texels (avg_pool2d on the (1, C, H, W) view would copy it first)
    return hr.reshape(h // scale, scale, w // scale, scale, c).mean(dim=(1, 3))


def pbr_consistency(
    hr: torch.Tensor,
    lr: torch.Tensor,
    scale: int,
    groups: list[MapGroup],
    lambda_ssim: float,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``sum_T w_T (L1 + lambda_ssim (1 - SSIM))`` of ``AvgPool_s(hr)`` against ``lr``.

    ``hr`` (sH, sW, C), ``lr`` (H, W, C). Returns the weighted sum and the unweighted term of
    each group (by name).
    """
    return pooled_consistency(avg_pool_map(hr, scale), lr, groups, lambda_ssim)


def ssim_target(lr: torch.Tensor) -> SsimTarget:
    """The LR map (H, W, C) as the fixed side of the consistency loss's SSIM (its local
    moments computed once, not at every step)."""
    return SsimTarget(lr.permute(2, 0, 1)[None])


def pooled_consistency(
    pooled: torch.Tensor,
    lr: torch.Tensor,
    groups: list[MapGroup],
    lambda_ssim: float,
    target: SsimTarget | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`pbr_consistency` from the already pooled HR map (H, W, C): the optimiser
    differentiates at this size and spreads the gradient over the texels itself.
    ``target``: ``ssim_target(lr)``, when the caller keeps it across steps."""
    if pooled.shape != lr.shape:
        raise ValueError(
            f"pooled HR map {tuple(pooled.shape)} does not match the LR map {tuple(lr.shape)}"
        )
    total = pooled.new_zeros(())
    terms: dict[str, torch.Tensor] = {}
    if not groups:
        return total, terms
    # per-channel L1 and SSIM once for every channel, then averaged over each group's channels
    l1 = (pooled - lr).abs().mean(dim=(0, 1))  # (C,)
    target = ssim_target(lr) if target is None else target
    s = target.per_channel(pooled.permute(2, 0, 1)[None])[0]  # (C,)
    for g in groups:
        idx = list(g.channels)
        term = l1[idx].mean() + lambda_ssim * (1.0 - s[idx].mean())
        terms[g.name] = term
        total = total + g.weight * term
    return total, terms


def psnr(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> float:
    """PSNR in dB of two same-shape tensors (capped at 100 dB when they are equal)."""
    mse = float(((a.double() - b.double()) ** 2).mean())
    if mse <= 1e-10 * data_range**2:
        return 100.0
    return float(10.0 * torch.log10(torch.tensor(data_range**2 / mse)))


def consistency_psnr(hr: torch.Tensor, lr: torch.Tensor, scale: int, group: MapGroup) -> float:
    """PSNR (dB) of ``AvgPool_s(hr)`` against ``lr`` on one group's channels."""
    with torch.no_grad():
        idx = list(group.channels)
        return psnr(avg_pool_map(hr, scale)[..., idx], lr[..., idx])
