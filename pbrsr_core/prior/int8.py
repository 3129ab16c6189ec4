"""SRMD networks in 8-bit integers on the CPU.

The body convolutions after the first (ten of SRMD's twelve, 95 % of its multiply-adds)
run as int8 convolutions with the ReLU fused: weights quantized per output channel
(symmetric), activations per tensor with a scale and zero point measured once on training
crops (:func:`calibrate`, ``pbrsr priors calibrate``) and stored in the weights file's
metadata (:data:`METADATA_KEY`). The first convolution (the image and the degradation code)
and the head (the output pixels) stay float32.

Activations use all 8 bits, which is exact only where the CPU accumulates int8 products in
32 bits (VNNI or AMX: :func:`pbrsr_core.prior.base.native_int8`); without it the x86 kernels
may saturate, so the ``int8`` precision takes effect only there.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..errors import PriorUnavailable
from .srmd import SRMD

METADATA_KEY = "int8"
ENGINES = ("x86", "fbgemm")
"""Quantized engines whose int8 convolutions this module runs, in order of preference."""


@dataclass(frozen=True)
class Calibration:
    """Activation quantization of an SRMD network of ``convs`` body convolutions: the
    (scale, zero point) of the first convolution's output and of each later body
    convolution's output (``convs`` pairs), and how they were measured."""

    scales: tuple[float, ...]
    zero_points: tuple[int, ...]
    source: str = ""

    def to_json(self) -> str:
        data = {"scales": list(self.scales), "zero_points": list(self.zero_points)}
        return json.dumps({**data, "source": self.source})

    @classmethod
    def from_json(cls, text: str, convs: int) -> Calibration:
        """Parse metadata written by :meth:`to_json` for a network of ``convs`` body
        convolutions; :class:`PriorUnavailable` when it does not fit."""
        try:
            data = json.loads(text)
            scales = tuple(float(s) for s in data["scales"])
            zero_points = tuple(int(z) for z in data["zero_points"])
            source = str(data.get("source", ""))
        except (ValueError, TypeError, KeyError) as exc:
            raise PriorUnavailable(f"the int8 calibration is not readable: {exc}") from exc
        if len(zero_points) != len(scales):
            raise PriorUnavailable(
                f"the int8 calibration has {len(scales)} scales but {len(zero_points)} zero points"
            )
        out = cls(scales, zero_points, source)
        out.check(convs)
        if not all(math.isfinite(s) and s > 0 for s in scales):
            raise PriorUnavailable("the int8 calibration has a scale that is not positive")
        if not all(0 <= z <= 255 for z in zero_points):
            raise PriorUnavailable("the int8 calibration has a zero point outside 0-255")
        return out

    def check(self, convs: int) -> None:
        """:class:`PriorUnavailable` unless this fits a network of ``convs`` convolutions."""
        if len(self.scales) != convs:
            raise PriorUnavailable(
                f"the int8 calibration has {len(self.scales)} scales for {convs} convolutions"
            )


@contextmanager
def _quantized_tensors() -> Iterator[None]:
    """Quantized tensors without torch's notice that they are deprecated (torch 2.13 still
    runs them; the project pins it): the notice would reach every user of the prior."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*quantized tensor creation functions")
        yield


def engine() -> str | None:
    """The quantized engine to use (:data:`ENGINES`), or None where torch has none of them."""
    have = torch.backends.quantized.supported_engines
    return next((e for e in ENGINES if e in have), None)


def weight_qparams(weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per output channel, the (scale, zero point) of symmetric int8 weights: the largest
    magnitude maps to 127.5 (rounded and clamped to 127), zero to 0."""
    amax = weight.detach().abs().amax(dim=tuple(range(1, weight.ndim)))
    scale = (amax / 127.5).clamp_min(torch.finfo(torch.float32).eps)
    return scale, torch.zeros(len(scale), dtype=torch.int64)


@torch.no_grad()
def calibrate(net: SRMD, lr_crops: torch.Tensor, source: str = "", chunk: int = 8) -> Calibration:
    """The activation quantization of ``net`` from LR crops (N, 3, h, w) in [0, 1]: per
    quantized activation, the range of least squared quantization error over the crops'
    histogram (torch's HistogramObserver)."""
    from torch.ao.quantization import HistogramObserver

    observers = [HistogramObserver(dtype=torch.quint8) for _ in range(net.convs)]
    net = net.eval()
    for i in range(0, len(lr_crops), chunk):
        y = net._input(lr_crops[i : i + chunk].float())[0]
        for conv, observer in zip(net.body, observers, strict=True):
            y = F.relu(conv(y))
            observer(y)
    scales, zero_points = [], []
    for observer in observers:
        scale, zero_point = observer.calculate_qparams()
        scales.append(float(scale))
        zero_points.append(int(zero_point))
    return Calibration(tuple(scales), tuple(zero_points), source)


class Int8SRMD(nn.Module):
    """``net`` with its body convolutions after the first in int8 (see the module
    docstring); the same call as :class:`SRMD`. CPU only."""

    def __init__(self, net: SRMD, calibration: Calibration) -> None:
        super().__init__()
        name = engine()
        if name is None:
            raise PriorUnavailable("this torch build has no x86 quantized engine for int8")
        calibration.check(net.convs)
        self.engine, self.stride = name, net.stride
        torch.backends.quantized.engine = name  # weights are packed for the engine in use
        self.net = net.eval()
        self.scale, self.zero_point = calibration.scales[0], calibration.zero_points[0]
        self.body = nn.ModuleList()
        with _quantized_tensors():
            self._pack(net, calibration)

    def _pack(self, net: SRMD, calibration: Calibration) -> None:
        from torch.ao.nn.intrinsic.quantized import ConvReLU2d

        convs: list[nn.Conv2d] = [m for m in net.body[1:] if isinstance(m, nn.Conv2d)]
        for conv, scale, zero_point in zip(
            convs, calibration.scales[1:], calibration.zero_points[1:], strict=True
        ):
            weight = conv.weight.detach().float()
            w_scale, w_zero = weight_qparams(weight)
            q = ConvReLU2d(conv.in_channels, conv.out_channels, 3, padding=1)
            q.set_weight_bias(
                torch.quantize_per_channel(weight, w_scale, w_zero, 0, torch.qint8),
                conv.bias.detach().float() if conv.bias is not None else None,
            )
            q.scale, q.zero_point = float(scale), int(zero_point)
            self.body.append(q)

    @torch.no_grad()
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        torch.backends.quantized.engine = self.engine
        net = self.net
        y, p = net._input(x.float())
        y = F.relu_(net.body[0](y))
        with _quantized_tensors():
            y = torch.quantize_per_tensor(y, self.scale, self.zero_point, torch.quint8)
            for conv in self.body:
                y = conv(y)
            y = y.dequantize()
        return net._output(y, p)


class FakeInt8(nn.Module):
    """``net`` as :class:`Int8SRMD` computes it, in floating point: weights and activations
    rounded to the same int8 grids, the rounding passed straight through by the gradient
    (quantization-aware training, ``pbrsr priors finetune --int8``). Its parameters are
    ``net``'s."""

    def __init__(self, net: SRMD, calibration: Calibration) -> None:
        super().__init__()
        calibration.check(net.convs)
        self.net, self.calibration, self.stride = net, calibration, net.stride

    def _activation(self, y: torch.Tensor, i: int) -> torch.Tensor:
        c = self.calibration
        return torch.fake_quantize_per_tensor_affine(y, c.scales[i], c.zero_points[i], 0, 255)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        net = self.net
        y, p = net._input(x)
        y = self._activation(F.relu(net.body[0](y)), 0)
        for i, conv in enumerate(net.body[1:], 1):
            assert isinstance(conv, nn.Conv2d)
            scale, zero = weight_qparams(conv.weight)
            w = torch.fake_quantize_per_channel_affine(
                conv.weight, scale.float(), zero.int(), 0, -128, 127
            )
            y = self._activation(F.relu(F.conv2d(y, w, conv.bias, padding=1)), i)
        return net._output(y, p)
