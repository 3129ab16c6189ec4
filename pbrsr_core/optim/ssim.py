"""Differentiable SSIM with a Gaussian window (Wang et al. 2004).

Settings match ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1)``: an 11x11 Gaussian window
(sigma 1.5, truncated at 3.5 sigma), K1 = 0.01, K2 = 0.03, and the mean of the SSIM map over
the "valid" region (the window never leaves the image), per channel. On images smaller than
the window the window shrinks to the largest odd size that fits (a 1x1 image uses a 1x1
window, where SSIM reduces to the luminance term), so SSIM is defined for every map size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

DEFAULT_SIGMA = 1.5
DEFAULT_TRUNCATE = 3.5
K1, K2 = 0.01, 0.03


def gaussian_window(size: int, sigma: float, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Normalised 1-D Gaussian of odd length ``size`` -> (size,)."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and >= 1, got {size}")
    r = (size - 1) // 2
    x = torch.arange(-r, r + 1, dtype=dtype, device=device)
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


def _window_size(h: int, w: int, sigma: float, truncate: float) -> int:
    full = 2 * int(truncate * sigma + 0.5) + 1
    fit = min(full, h, w)
    return fit if fit % 2 == 1 else fit - 1


def ssim_per_channel(
    x: torch.Tensor,
    y: torch.Tensor,
    *,
    data_range: float = 1.0,
    sigma: float = DEFAULT_SIGMA,
    truncate: float = DEFAULT_TRUNCATE,
) -> torch.Tensor:
    """Mean SSIM of each channel.

    ``x``, ``y``: (N, C, H, W), same shape, any float dtype. Returns (N, C). Differentiable;
    finite for constant images (the stabilising constants keep denominators > 0).
    """
    if x.shape != y.shape:
        raise ValueError(f"ssim: shapes differ: {tuple(x.shape)} vs {tuple(y.shape)}")
    if x.ndim != 4:
        raise ValueError(f"ssim: expected (N, C, H, W), got shape {tuple(x.shape)}")
    n, c, h, w = x.shape
    if h == 0 or w == 0:
        raise ValueError("ssim: empty image")
    size = _window_size(h, w, sigma, truncate)
    g = gaussian_window(size, sigma, dtype=x.dtype, device=x.device)
    # the five local moments in one separable, grouped convolution (2 conv calls in all)
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # (N, 5C, H, W)
    kx = g.view(1, 1, 1, size).expand(5 * c, 1, 1, size)
    ky = g.view(1, 1, size, 1).expand(5 * c, 1, size, 1)
    blurred = F.conv2d(F.conv2d(stack, kx, groups=5 * c), ky, groups=5 * c)
    mx, my, exx, eyy, exy = blurred.split(c, dim=1)
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    sxx = exx - mx * mx
    syy = eyy - my * my
    sxy = exy - mx * my
    num = (2 * mx * my + c1) * (2 * sxy + c2)
    den = (mx * mx + my * my + c1) * (sxx + syy + c2)
    return (num / den).mean(dim=(2, 3))


def ssim(x: torch.Tensor, y: torch.Tensor, **kwargs) -> torch.Tensor:
    """Mean SSIM over batch and channels of (N, C, H, W) images -> scalar."""
    return ssim_per_channel(x, y, **kwargs).mean()


def window_size_for(h: int, w: int) -> int:
    """The window side :func:`ssim_per_channel` uses on an h x w image (11 when it fits)."""
    return _window_size(h, w, DEFAULT_SIGMA, DEFAULT_TRUNCATE)


__all__ = ["gaussian_window", "ssim", "ssim_per_channel", "window_size_for"]
