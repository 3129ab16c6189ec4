"""An efficient super-resolution network of the SPAN shape (Wan et al., "Swift Parameter-free
Attention Network for Efficient Super-Resolution", CVPR workshops 2024, first in the NTIRE 2024
efficient-SR challenge): a 3x3 convolution to ``feat`` features, ``blocks`` attention blocks,
a 1x1 convolution over the concatenated first features, first and last block outputs and the
last block's inner features, a 3x3 convolution, then a convolution to ``3 * stride**2``
channels and a pixel shuffle, all at the input's size.

Each block is three 3x3 convolutions (SiLU, then leaky ReLU between them) whose output ``y``
weighs itself and the block's input with no parameters of its own: ``(y + x) *
(sigmoid(y) - 1/2)``, the symmetric attention of the paper. The paper trains each convolution
as a wider 1x1-3x3-1x1 stack folded into one 3x3 for inference; here each is one 3x3
convolution in training too (the same inference network, a fifth of the training cost).

The network's output is added to a bicubic resize of its input and its head starts at zero,
so at its start weights it is bicubic exactly and training begins from there (no pretrained
weights of this shape can be installed offline). The input is padded by reflection (``PREPAD``
pixels, fewer on a smaller input) and the result cropped, so borders see texture.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .bicubic import bicubic_upscale


def _conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2)


class Block(nn.Module):
    """Three convolutions and the parameter-free attention (see the module docstring)."""

    def __init__(self, feat: int) -> None:
        super().__init__()
        self.c1, self.c2, self.c3 = _conv(feat, feat), _conv(feat, feat), _conv(feat, feat)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the block's output, its first convolution's output)."""
        inner = self.c1(x)
        y = self.c3(F.leaky_relu(self.c2(F.silu(inner)), 0.1))
        return (y + x) * (torch.sigmoid(y) - 0.5), inner


class Span(nn.Module):
    """``blocks`` attention blocks of ``feat`` features and an upscaling head of ``stride``
    (2 or 4), residual to bicubic (see the module docstring)."""

    PREPAD = 8

    def __init__(self, feat: int = 48, blocks: int = 6, stride: int = 4) -> None:
        super().__init__()
        if feat < 1 or blocks < 1:
            raise ValueError(f"feat and blocks must be positive: {feat}, {blocks}")
        if stride not in (2, 4):
            raise ValueError(f"stride must be 2 or 4, got {stride}")
        self.feat, self.blocks, self.stride = int(feat), int(blocks), stride
        self.first = _conv(3, feat)
        self.body = nn.ModuleList(Block(feat) for _ in range(blocks))
        self.fuse = _conv(4 * feat, feat, 1)
        self.last = _conv(feat, feat)
        self.head = _conv(feat, 3 * stride * stride)
        with torch.no_grad():
            self.head.weight.zero_()
            self.head.bias.zero_()  # type: ignore[union-attr]  # the conv has a bias

    @property
    def widths(self) -> tuple[int, ...]:
        """The width of each block (as UpConv7 lists its layers' widths)."""
        return (self.feat,) * self.blocks

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p, s = min(self.PREPAD, x.shape[-2] - 1, x.shape[-1] - 1), self.stride
        y = F.pad(x, (p,) * 4, mode="reflect") if p > 0 else x
        f0 = self.first(y - 0.5)
        b1, inner = self.body[0](f0)
        b = b1
        for block in self.body[1:]:
            b, inner = block(b)
        y = self.fuse(torch.cat([f0, self.last(b), b1, inner], 1))
        y = F.pixel_shuffle(self.head(y), s)
        if p > 0:
            y = y[..., p * s : -p * s, p * s : -p * s]
        return y.contiguous() + bicubic_upscale(x, s)
