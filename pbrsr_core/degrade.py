"""The paper's low-resolution protocol: Gaussian blur, then bicubic downsampling by s.

The paper does not give the blur's width. We use ``sigma = s * sqrt(2 ln 2) / pi`` (about
``0.375 * s`` texels of the HR image): the Gaussian whose frequency response is exactly 1/2 at
the Nyquist frequency of the LR grid (``1 / (2 s)`` cycles per HR texel). Narrower blurs let
bicubic decimation alias high-frequency texture detail into moire; wider ones remove detail
the LR grid could still hold. Borders are reflected. Images are degraded as stored (sRGB maps
stay sRGB-encoded, as an artist's LR export would be); normal maps are degraded encoded and
then decoded, renormalised (z >= 0) and re-encoded.

Real LR maps are not always made so: a mip chain averages blocks, an image editor resizes
with an antialiased bicubic or Lanczos filter. :func:`degrade_image` takes those as
``kernel`` (``KERNELS``) to measure how the method holds on inputs its priors were not
trained for; ``gaussian`` is the protocol, the one the shipped priors were trained on.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .errors import InvalidOptions
from .limits import Limits

KERNELS = ("gaussian", "area", "bicubic", "lanczos")
"""gaussian: the protocol (blur, then bicubic interpolation at the LR texel centres); area:
the mean of each LR texel's HR texels (a box filter, as mipmaps are made); bicubic and
lanczos: antialiased resizing with the Keys cubic (a = -0.5) or Lanczos-3 kernel stretched
by the scale (Pillow's BICUBIC and LANCZOS, ImageMagick's default Lanczos for shrinking)."""


_RUN_KERNEL: ContextVar[str] = ContextVar("lr_kernel", default="gaussian")


@contextmanager
def lr_model(kernel: str) -> Iterator[None]:
    """Within it, the kernel that made the run's LR maps: the LR model the prior's
    back-projection (:func:`lr_downsample`) and the self-check and guided upscale one scale
    down (:func:`run_kernel`) invert. The pipeline sets it from ``UpscaleOptions.lr_kernel``."""
    check_kernels((kernel,))
    token = _RUN_KERNEL.set(kernel)
    try:
        yield
    finally:
        _RUN_KERNEL.reset(token)


def run_kernel() -> str:
    """The kernel of the run's LR model (:func:`lr_model`; the protocol's outside one)."""
    return _RUN_KERNEL.get()


def lr_downsample(x: torch.Tensor, scale: int) -> torch.Tensor:
    """The run's LR model (:func:`lr_model`) on (N, C, H, W): :func:`downsample` by its
    kernel."""
    return downsample(x, scale, run_kernel())


def check_kernels(kernels: tuple[str, ...]) -> None:
    """Refuse an empty or unknown list of LR kernels."""
    bad = [k for k in kernels if k not in KERNELS]
    if not kernels or bad:
        raise InvalidOptions(
            f"unknown LR kernel(s) {', '.join(bad) or '(none given)'}: use {', '.join(KERNELS)}"
        )


def degrade_sigma(scale: int) -> float:
    """Gaussian sigma (in HR texels) used before downsampling by ``scale``."""
    return scale * math.sqrt(2.0 * math.log(2.0)) / math.pi


def _gaussian_kernel(sigma: float) -> torch.Tensor:
    radius = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).to(torch.float32)


def degrade_tensor(x: torch.Tensor, scale: int) -> torch.Tensor:
    """The blur and bicubic downsampling on (N, C, H, W) -> (N, C, max(1, round(H/s)),
    max(1, round(W/s))), unclamped, on ``x``'s device and dtype."""
    h, w = x.shape[2:]
    k = _gaussian_kernel(degrade_sigma(scale)).tolist()
    r = len(k) // 2
    for dim in (2, 3):
        size = x.shape[dim]
        if size > 1:
            pad = (r, r, 0, 0) if dim == 3 else (0, 0, r, r)
            mode = "reflect" if size > r else "replicate"
            xp = F.pad(x, pad, mode=mode)
            # the separable blur as a weighted sum of shifted views: a 2048² RGB image in
            # 0.18 s where torch's depthwise convolution took 0.44 s (2-core AMD CPU)
            x = xp.narrow(dim, 0, size) * k[0]
            for t in range(1, len(k)):
                x.add_(xp.narrow(dim, t, size), alpha=k[t])
    out_h, out_w = max(1, round(h / scale)), max(1, round(w / scale))
    return F.interpolate(x, size=(out_h, out_w), mode="bicubic", align_corners=False)


def _filter(kernel: str, x: np.ndarray) -> np.ndarray:
    """The bicubic or lanczos resizing filter at ``x`` (in LR texels)."""
    a = np.abs(x)
    if kernel == "bicubic":  # Keys, a = -0.5
        return np.where(
            a <= 1, (1.5 * a - 2.5) * a * a + 1,
            np.where(a < 2, ((-0.5 * a + 2.5) * a - 4) * a + 2, 0.0),
        )  # fmt: skip
    return np.where(a < 3, np.sinc(x) * np.sinc(x / 3), 0.0)  # lanczos


def resize_matrix(n_in: int, n_out: int, kernel: str) -> torch.Tensor:
    """(n_out, n_in) float64 weights of a resize along one axis: for area, the overlap of
    each input texel with output texel i's footprint; otherwise the filter, stretched by
    ``n_in / n_out`` when shrinking (antialiased), centred on output texel i's centre. Each
    row's weights, over the input texels inside the axis, sum to 1 (Pillow's border rule)."""
    s = n_in / n_out
    i, j = np.arange(n_out)[:, None], np.arange(n_in)[None, :]
    if kernel == "area":  # each input texel's overlap with the output texel's footprint
        w = np.clip(np.minimum(j + 1, (i + 1) * s) - np.maximum(j, i * s), 0.0, None)
    else:
        w = _filter(kernel, (j + 0.5 - (i + 0.5) * s) / max(s, 1.0))
    return torch.from_numpy(w / w.sum(axis=1, keepdims=True))


def downsample(x: torch.Tensor, scale: int, kernel: str) -> torch.Tensor:
    """(N, C, H, W) -> (N, C, max(1, round(H/s)), max(1, round(W/s))), unclamped, on ``x``'s
    device and dtype, by ``kernel``: the protocol's :func:`degrade_tensor` for gaussian."""
    check_kernels((kernel,))
    if kernel == "gaussian":
        return degrade_tensor(x, scale)
    h, w = x.shape[2:]
    return _resize_tensor(x, (max(1, round(h / scale)), max(1, round(w / scale))), kernel)


def _resize_tensor(x: torch.Tensor, size: tuple[int, int], kernel: str) -> torch.Tensor:
    """(N, C, H, W) -> (N, C, *size) by ``kernel`` (one of ``KERNELS`` but gaussian): each
    axis through its resize matrix stored sparse (a few taps a row: the cost grows with the
    texels, not with their square)."""
    for dim, n_out in ((2, size[0]), (3, size[1])):
        m = resize_matrix(x.shape[dim], n_out, kernel).to_sparse().to(x.device, x.dtype)
        moved = x.movedim(dim, 0)
        flat = torch.sparse.mm(m, moved.reshape(moved.shape[0], -1))
        x = flat.reshape(n_out, *moved.shape[1:]).movedim(0, dim)
    return x


def degrade_image(
    image: np.ndarray, scale: int, *, normal_map: bool = False, kernel: str = "gaussian"
) -> np.ndarray:
    """(H, W, C) float32 [0, 1] -> (max(1, round(H/s)), max(1, round(W/s)), C) float32, by the
    protocol or another ``kernel`` (``KERNELS``)."""
    if not isinstance(scale, int) or scale < 1:
        raise InvalidOptions(f"the degradation scale must be a positive integer, not {scale!r}")
    check_kernels((kernel,))
    arr = np.asarray(image, dtype=np.float32)
    if arr.ndim != 3:
        raise ValueError(f"image must be (H, W, C), got shape {arr.shape}")
    if scale == 1:
        return arr.copy()
    x = torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)[None]  # (1, C, H, W)
    y = downsample(x, scale, kernel)[0].permute(1, 2, 0).clamp(0.0, 1.0).numpy()
    if normal_map and arr.shape[2] >= 3:
        n = y[..., :3] * 2.0 - 1.0
        n[..., 2] = np.maximum(n[..., 2], 0.0)
        ln = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.where(ln > 1e-8, n / np.maximum(ln, 1e-8), np.array([0.0, 0.0, 1.0]))
        y = y.copy()
        y[..., :3] = n * 0.5 + 0.5
    return np.ascontiguousarray(y, dtype=np.float32)


def degrade_asset(
    in_path: Path,
    out_path: Path,
    scale: int,
    limits: Limits = Limits(),
    image_format: str = "same",
    kernel: str = "gaussian",
) -> list[Path]:
    """Write ``out_path`` (.glb/.gltf): the asset at ``in_path`` with every material image
    degraded by ``scale``, stored as ``image_format`` ("same" keeps each image's format, so
    JPEG textures are JPEG-compressed again; "png", "png16", "exr": lossless, the protocol's
    LR values as they are; "jpeg:Q", "jpeg:Q:420": every image without alpha a JPEG of
    quality Q, 4:4:4 or its chroma at half resolution; see ``asset.images.output_format``),
    each made by ``kernel`` (``KERNELS``; gaussian: the protocol). Returns the written paths,
    main file first."""
    from .asset.gltf import load_asset, save_asset
    from .asset.images import jpeg_request

    jpeg_request(image_format)  # a malformed JPEG request is refused before any work

    if scale not in (2, 3, 4, 8, 16):
        raise InvalidOptions(f"scale must be 2, 3, 4, 8 or 16, not {scale}")
    check_kernels((kernel,))
    asset = load_asset(Path(in_path), limits)
    new = {}
    for im in asset.images:
        if not im.roles or im.pixels.size == 0:
            continue
        new[im.index] = degrade_image(
            im.pixels, scale, normal_map="normal" in im.roles, kernel=kernel
        )
    return save_asset(asset, Path(out_path), new, image_format)
