"""Window means over image tensors: the box filter of the guided filter's local linear fits
(prior/guided.py fits data channels to the colour map, asset/jpeg.py fits subsampled chroma
to the luma)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def box_mean(x: torch.Tensor, r: int) -> torch.Tensor:
    """The mean over the (2r + 1)² window around each texel of ``x`` (N, C, H, W), edges
    replicated; the same shape back."""
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)
