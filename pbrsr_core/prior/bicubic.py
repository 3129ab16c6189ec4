"""The classical reference prior: bicubic interpolation (torch, a = -0.75, clamped)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .base import Prior


class BicubicPrior(Prior):
    """Bicubic upscaling by any integer factor 2..8. Each output pixel depends on a 4x4
    input neighbourhood, so tiles only need a small overlap."""

    name = "bicubic"
    is_network = False
    back_project = False
    scales = (2, 3, 4, 8)
    bytes_per_pixel = 4.0 * 3 * 2 * 64  # input + output at x8, float32
    default_overlap = 8  # dead zone 2 px >= the 2-px bicubic footprint: seams are exact

    def __init__(self, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.device = torch.device(device)
        # Tiling only bounds temporaries here (memory is dominated by the output itself), and
        # each tile costs a weighted accumulation: use few, large tiles.
        self.tile_size = 2048

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        """x (B, 3, h, w) -> (B, 3, s*h, s*w); edges replicated (align_corners=False)."""
        return F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False)


def bicubic_upscale(x: torch.Tensor, scale: int) -> torch.Tensor:
    """Plain bicubic of any-channel images x (N, C, H, W) -> (N, C, s*H, s*W), unclamped."""
    return F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False)
