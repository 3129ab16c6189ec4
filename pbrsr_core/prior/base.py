"""The image SR prior interface.

A :class:`Prior` maps a batch of sRGB-encoded LDR images in [0, 1], shape (N, 3, H, W), to
(N, 3, s*H, s*W) for each scale ``s`` in ``prior.scales``. Any H and W work: images are padded
inside to what the network needs, and large images run through overlapping tiles with blended
seams (:mod:`pbrsr_core.prior.tiling`). The output is clamped to [0, 1] and never NaN, lives on
the input's device, and is an ordinary tensor (computed under ``torch.inference_mode`` but
returned as a normal tensor, so it can serve as a loss target). A network prior's output is
back-projected onto its input (one step, :mod:`pbrsr_core.prior.backproject`): degraded by the
LR model it gives the input back, whatever offsets the network has.

Precision: a network prior whose bfloat16 output was measured against its float32 output
(``bf16_validated``) runs under bfloat16 autocast where the hardware computes bfloat16
natively (AVX512-BF16/AMX CPUs, CUDA GPUs with bf16): rrdn-thick at x4 ran 2.1x faster on an
AVX512-BF16 CPU and its output stayed 56 dB from float32's; where bfloat16 is only emulated it
runs in float32. The runtime's ``prior_precision`` (``$PBRSR_PRIOR_PRECISION``; or the
``precision`` attribute) = ``fp32`` turns that off, ``bf16`` forces it for any network prior.

``int8`` runs the networks that have an int8 calibration (``int8_ready``: pbr-srmd's SRMD
networks, :mod:`pbrsr_core.prior.int8`) in int8 on CPUs with VNNI or AMX (elsewhere, and on
GPUs, in float32): pbr-srmd's colour network about 3x faster than in float32 on a 2-core
AVX-512 EPYC with VNNI, 0.18 dB lower on the shared assets' albedo crops (docs/BENCHMARKS.md).
It is never automatic: the output would then depend on which CPU ran the job.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import torch
import torch.nn.functional as F

from .. import runtime
from ..errors import InvalidOptions, UnprocessableAsset
from ..runtime import PRECISIONS
from .backproject import back_project
from .int8 import engine as int8_engine
from .tiling import count_tiles, default_tile_size, run_tiled

TileProgress = Callable[[int, int], None]
"""``progress(done, total)`` in tiles; raise :class:`pbrsr_core.errors.Cancelled` to stop."""


class Prior(ABC):
    """Base class of every prior. Subclasses set ``name``, ``scales``, ``device`` and
    implement :meth:`_forward`; they may set ``pad_multiple``/``min_size`` (network input
    size requirements), ``bytes_per_pixel`` (estimated peak memory per LR input pixel, for the
    default tile size) and ``default_overlap`` (LR pixels shared by neighbouring tiles)."""

    name: str = ""
    scales: tuple[int, ...] = ()
    device: torch.device = torch.device("cpu")
    pad_multiple: int = 1
    min_size: int = 1
    bytes_per_pixel: float = 4096.0
    default_overlap: int = 16
    is_network: bool = True
    """False for classical interpolation (never run in reduced precision)."""
    one_pass_scales: tuple[int, ...] = ()
    """Scales its network makes in one pass at the input's size (waifu2x: x2; a stride-4
    texture network: x4); a pass costs about the same whatever its scale."""
    back_project: bool = True
    """Whether :meth:`upscale` back-projects the output onto the input (prior/backproject.py);
    False for interpolation, whose output already is what it is meant to be."""
    cpu_tile_max: int = 512
    """Largest tile side (LR pixels) on the CPU: UpConv7's tiles at x4 are no faster past it
    (its second pass, at twice the size, is bound by memory traffic)."""
    bf16_validated: bool = False
    """True when bfloat16 output was measured close to float32's (then ``auto`` uses it)."""

    def __init__(self) -> None:
        self.tile_size: int | None = None  # LR pixels; None: chosen from free memory
        self.tile_overlap: int | None = None  # LR pixels; None: default_overlap
        self.precision: str | None = None  # auto, fp32, bf16; None: the runtime's

    # -- to implement ------------------------------------------------------------------
    @abstractmethod
    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        """Run the network: x (B, 3, h, w) float32 on ``self.device``, h and w already
        multiples of ``pad_multiple`` and at least ``min_size``; returns (B, 3, s*h, s*w)."""

    def num_parameters(self) -> int:
        """Trainable parameter count (0 for classical interpolation)."""
        return 0

    def for_kind(self, kind: str) -> Prior:
        """The prior to run on maps of ``kind`` (colour, data, normal): itself, unless it
        holds a network per kind (:class:`~pbrsr_core.prior.texture.TexturePrior`)."""
        return self

    def candidates(self, kind: str, scale: int) -> list[Prior]:
        """The priors that may upscale a map of ``kind`` by ``scale`` (the factor the prior
        may run at, :func:`~.selfcheck.offered`), best guess first: the self-check
        (prior/selfcheck.py) keeps, per map, the one that reconstructs it best from one scale
        down. One, :meth:`for_kind`'s, unless a texture set also offers its fallback (and at
        x4 its x2 passes)."""
        return [self.for_kind(kind)]

    # -- the public call ---------------------------------------------------------------
    def check_scale(self, scale: int) -> None:
        """Raise :class:`UnprocessableAsset` if this prior cannot upscale by ``scale``."""
        if scale not in self.scales:
            have = ", ".join(f"x{s}" for s in self.scales)
            raise UnprocessableAsset(
                f"the prior '{self.name}' cannot upscale x{scale}; it supports {have}"
            )

    def int8_ready(self) -> bool:
        """Whether a network this prior runs has an int8 calibration."""
        return False

    def precision_in_use(self) -> str:
        """``fp32``, ``bf16`` (the network under bfloat16 autocast) or ``int8`` (its calibrated
        networks in int8), from the prior's or the runtime's choice and the hardware (see the
        module docstring)."""
        choice = self.precision or runtime.current().prior_precision
        if choice not in PRECISIONS:
            raise InvalidOptions(
                f"prior precision {choice!r} is not one of {', '.join(PRECISIONS)}"
            )
        if not self.is_network or choice == "fp32":
            return "fp32"
        if choice == "int8" and self.int8_ready() and native_int8(self.device):
            return "int8"
        validated = self.bf16_validated and native_bf16(self.device)
        if choice == "bf16" or (choice == "auto" and validated):
            return "bf16"
        return "fp32"

    def tile_limits(self, scale: int) -> tuple[float, int]:
        """(estimated peak memory per LR input pixel, largest tile side on the CPU) of a run
        at ``scale``: ``bytes_per_pixel`` and ``cpu_tile_max``."""
        return self.bytes_per_pixel, self.cpu_tile_max

    def effective_tile(self, scale: int, tile_size: int | None = None) -> int:
        """The tile side of a run at ``scale`` (argument, attribute, or from free memory and
        :meth:`tile_limits`)."""
        tile = tile_size or self.tile_size
        if tile is None:
            bytes_per_pixel, cpu_max = self.tile_limits(scale)
            tile = default_tile_size(self.device, bytes_per_pixel, cpu_max=cpu_max)
        return max(int(tile), self.min_size, 8)

    def upscale(
        self,
        images: torch.Tensor,
        scale: int,
        *,
        progress: TileProgress | None = None,
        tile_size: int | None = None,
        tile_overlap: int | None = None,
    ) -> torch.Tensor:
        """Upscale images (N, 3, H, W) sRGB in [0, 1] to (N, 3, s*H, s*W) in [0, 1].

        ``tile_size``/``tile_overlap`` (LR pixels) override the prior's settings for this call.
        ``progress(done, total)`` is called after every tile of every image.
        """
        if not isinstance(images, torch.Tensor):
            raise TypeError(f"images must be a torch.Tensor, got {type(images).__name__}")
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"images must have shape (N, 3, H, W), got {tuple(images.shape)}")
        if images.shape[0] == 0 or images.shape[2] == 0 or images.shape[3] == 0:
            raise ValueError(f"images must not be empty, got {tuple(images.shape)}")
        self.check_scale(scale)
        bf16 = self.precision_in_use() == "bf16"
        tile = self.effective_tile(scale, tile_size)
        overlap = self.default_overlap if tile_overlap is None else int(tile_overlap)
        if self.tile_overlap is not None and tile_overlap is None:
            overlap = self.tile_overlap
        overlap = min(overlap, tile // 2)
        n, _, h, w = images.shape
        total = n * count_tiles(h, w, tile, overlap)
        done = 0

        def tick() -> None:
            nonlocal done
            done += 1
            if progress is not None:
                progress(done, total)

        with torch.inference_mode():
            x = torch.nan_to_num(images.detach().float(), nan=0.0).clamp(0.0, 1.0)
            outs = [
                run_tiled(
                    lambda t: self._run_padded(t, scale, bf16),
                    x[i : i + 1],
                    scale,
                    tile,
                    overlap,
                    tick,
                )
                for i in range(n)
            ]
            out = torch.cat(outs, 0)
            out = torch.nan_to_num(out, nan=0.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)
            if self.back_project:
                out = back_project(out, x, scale)
        return out.clone()  # outside inference mode: an ordinary tensor

    def _run_padded(self, x: torch.Tensor, scale: int, bf16: bool = False) -> torch.Tensor:
        """Pad x (B, 3, h, w) to the network's size requirements, run, crop back."""
        _, _, h, w = x.shape
        ph = _padded_size(h, self.pad_multiple, self.min_size) - h
        pw = _padded_size(w, self.pad_multiple, self.min_size) - w
        x = x.to(self.device)
        if ph or pw:
            mode = "reflect" if ph < h and pw < w else "replicate"
            x = F.pad(x, (0, pw, 0, ph), mode=mode)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16):
            y = self._forward(x, scale).float()
        expected = (x.shape[0], 3, x.shape[2] * scale, x.shape[3] * scale)
        if tuple(y.shape) != expected:
            raise RuntimeError(
                f"prior '{self.name}' returned {tuple(y.shape)} for x{scale}, expected {expected}"
            )
        return y[:, :, : h * scale, : w * scale]

    def describe(self) -> dict:
        """Name, scales, parameters and device for listings and reports."""
        return {
            "name": self.name,
            "scales": list(self.scales),
            "parameters": self.num_parameters(),
            "device": str(self.device),
            "precision": self.precision_in_use(),
        }


def native_bf16(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 convolutions natively."""
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type == "cpu":
        return cpu_has_bf16_units(cpu_capabilities())
    return False


def native_int8(device: torch.device) -> bool:
    """Whether ``device`` runs int8 networks (:mod:`pbrsr_core.prior.int8`) exactly: a CPU
    with int8 dot-product units and a quantized engine."""
    return (
        device.type == "cpu"
        and int8_engine() is not None
        and cpu_has_int8_units(cpu_capabilities())
    )


def cpu_has_int8_units(caps: dict) -> bool:
    """Whether a CPU with these flags sums int8 products in 32 bits (AVX512-VNNI, AVX-VNNI or
    AMX-INT8). Without them the x86 int8 kernels sum pairs in 16 bits, which full-range 8-bit
    activations can saturate."""
    return bool(caps.get("avx512_vnni") or caps.get("avx_vnni") or caps.get("amx_int8"))


def cpu_capabilities() -> dict:
    """The CPU's instruction-set flags as torch reports them ({} when it cannot)."""
    try:
        return dict(torch.cpu.get_capabilities())
    except (AttributeError, RuntimeError):
        return {}


def cpu_has_bf16_units(caps: dict) -> bool:
    """Whether a CPU with these flags has bfloat16 arithmetic units (AVX512-BF16 or AMX-BF16).

    oneDNN also reports bfloat16 as supported on AVX512 CPUs without them (Ice Lake, say),
    where it emulates it: rrdn-thick at x4 then ran 3.7x slower than in float32 (a 128² input,
    4.04 s against 1.09 s on this project's second machine), so only the flags count."""
    return bool(caps.get("avx512_bf16") or caps.get("amx_bf16"))


def _padded_size(n: int, multiple: int, minimum: int) -> int:
    n = max(n, minimum)
    return -(-n // multiple) * multiple
