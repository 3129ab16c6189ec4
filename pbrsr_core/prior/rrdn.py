"""``rrdn-thick``: UpscalerJS's pretrained RRDN (ESRGAN-style residual in
residual dense blocks; C=4, D=3, G=32, G0=64, T=10; trained on DIV2K; MIT licence) from the
npm package ``@upscalerjs/esrgan-thick@1.0.0`` (x2, x3, x4, x8).

``install()`` converts the package's TF.js layers-models once, into
``<cache>/priors/rrdn-thick-x{s}.safetensors`` (see :mod:`pbrsr_core.prior.tfjs`); loading
reads only those files. The networks take and return RGB in [0, 1] (UpscalerJS declares
``inputRange``/``outputRange`` [0, 1]; checked against the package's own sample outputs in the
tests).
"""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path

import torch

from ..errors import PriorUnavailable
from .base import Prior
from .paths import cache_dir, npm_dir
from .tfjs import FORMAT, TfjsGraphNet, convert, load_converted, read_metadata

PACKAGE = "@upscalerjs/esrgan-thick"
VERSION = "1.0.0"
NAME = "rrdn-thick"
SCALES = (2, 3, 4, 8)
INSTALL_HINT = "run `pbrsr priors install rrdn-thick` (or ./scripts/setup)"


def package_dir() -> Path:
    return npm_dir() / "@upscalerjs" / "esrgan-thick"


def weights_file(scale: int) -> Path:
    return cache_dir() / "priors" / f"{NAME}-x{scale}.safetensors"


def _source(scale: int) -> str:
    return f"{PACKAGE}@{VERSION}/models/x{scale}"


def _is_current(scale: int) -> bool:
    path = weights_file(scale)
    if not path.is_file():
        return False
    try:
        meta = read_metadata(path)
    except Exception:  # a truncated or foreign file: reconvert
        return False
    return meta.get("format") == FORMAT and meta.get("source") == _source(scale)


def is_installed() -> bool:
    """True when every scale has been converted by this version of the converter."""
    return all(_is_current(s) for s in SCALES)


def install(*, force: bool = False) -> list[Path]:
    """Convert the npm package's models (all scales) into the cache. Idempotent: scales
    already converted are skipped unless ``force``. Returns the files written."""
    pkg = package_dir()
    manifest = pkg / "package.json"
    if not manifest.is_file():
        raise PriorUnavailable(
            f"the npm package {PACKAGE}@{VERSION} is not installed: run ./scripts/setup, or "
            f"`npm install {PACKAGE}@{VERSION}` and point PBRSR_NPM_DIR at its node_modules"
        )
    version = json.loads(manifest.read_text(encoding="utf-8")).get("version")
    if version != VERSION:
        raise PriorUnavailable(
            f"found {PACKAGE}@{version}, but pbrsr needs version {VERSION}: run ./scripts/setup"
        )
    written = []
    for s in SCALES:
        if force or not _is_current(s):
            convert(pkg / "models" / f"x{s}", weights_file(s), source=_source(s))
            written.append(weights_file(s))
    return written


def installed_stats() -> tuple[int | None, int | None]:
    """(parameters of the x4 network, bytes of all converted files), read from the
    safetensors headers only; (None, None) when not installed."""
    from safetensors import safe_open

    if not is_installed():
        return None, None
    with safe_open(str(weights_file(4)), framework="pt") as fh:
        params = sum(math.prod(fh.get_slice(k).get_shape()) for k in fh.keys())  # noqa: SIM118
    return params, sum(weights_file(s).stat().st_size for s in SCALES)


class RRDNPrior(Prior):
    """The converted RRDN networks; each scale's network is loaded on first use and kept."""

    name = NAME
    scales = SCALES
    # Peak memory per LR input pixel, measured (CPU resident set, bench.prior.PeakMemory):
    # ~4.2 kB at x4, 2.6-3.7 kB at x2; x8 adds a larger output. Doubled for a margin.
    bytes_per_pixel = 8192.0
    # The network is 154 3x3 convs deep, but zero padding at a tile's cut edge only changes
    # outputs near it (measured at x2: 7e-2 at the edge, < 1e-3 beyond 6 LR px, < 1e-6 beyond
    # 14), so tiles share 32 px and the blend ignores the outer 8.
    default_overlap = 32
    bf16_validated = True  # 56 dB from float32 at x4 (tests/core/prior/test_rrdn.py checks >= 45)

    def __init__(self, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.device = torch.device(device)
        self._nets: dict[int, TfjsGraphNet] = {}
        self._lock = threading.Lock()
        missing = [s for s in SCALES if not weights_file(s).is_file()]
        if missing:
            raise PriorUnavailable(f"the prior '{NAME}' is not installed: {INSTALL_HINT}")

    def net(self, scale: int) -> TfjsGraphNet:
        """The network for ``scale`` (loaded once, from the safetensors file)."""
        self.check_scale(scale)
        with self._lock:
            if scale not in self._nets:
                try:
                    self._nets[scale] = load_converted(weights_file(scale), self.device)
                except FileNotFoundError as exc:
                    raise PriorUnavailable(
                        f"the prior '{NAME}' is not installed: {INSTALL_HINT}"
                    ) from exc
            return self._nets[scale]

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.net(4).parameters())

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        return self.net(scale)(x)
