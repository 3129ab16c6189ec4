"""Basis Universal's KTX2 encoder: the WebAssembly build the npm package ``ktx2-encoder``
(MIT; Basis Universal itself Apache-2.0) ships, run through ``node``.

``ktx2_encode.mjs`` sits beside the npm ``node_modules`` directory (the repository's
``tools/npm``; :func:`pbrsr_core.prior.paths.npm_dir` follows ``PBRSR_NPM_DIR``), reads the
RGBA8 pixels on stdin and writes the KTX2 file on stdout. Each call is one ``node`` process:
about 1 s of it compiles the 3.3 MB module, the rest encodes on one thread. The 32-bit
WebAssembly build refuses images over :data:`MAX_PIXELS`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import PbrsrError
from ..prior.paths import npm_dir

MAX_PIXELS = 4096 * 3072
"""The most texels the encoder takes in one image (Basis Universal's limit for its 32-bit
WebAssembly build: 12 Mi)."""
SCRIPT_NAME = "ktx2_encode.mjs"
PACKAGE = "ktx2-encoder"


class Ktx2EncoderUnavailable(PbrsrError):
    """node or the npm package ktx2-encoder is not installed here, or the encoder failed."""

    code = "ktx2-encoder-unavailable"
    http_status = 503
    exit_code = 9


def _paths() -> tuple[Path, Path]:
    modules = npm_dir()
    return modules.parent / SCRIPT_NAME, modules / PACKAGE


def encoder_available() -> bool:
    """True when node, the npm package and the script are all present."""
    script, package = _paths()
    return shutil.which("node") is not None and package.is_dir() and script.is_file()


def encode_ktx2_rgba(
    rgba: np.ndarray,
    *,
    codec: Literal["etc1s", "uastc"],
    quality: int,
    effort: int,
    srgb: bool,
    mipmaps: bool,
    zstd: bool,
    alpha: bool,
    timeout_s: float = 1800.0,
) -> bytes:
    """The KTX2 file of ``rgba`` (H, W, 4) uint8: ``codec`` at ``quality`` (1-100) and
    ``effort`` (0-10), the sRGB or linear transfer function (``srgb`` also picks perceptual
    error metrics and sRGB mip filtering), a generated mip chain, UASTC Zstandard
    supercompression (at the encoder's fixed level) and the alpha channel stored or dropped.

    Raises :class:`Ktx2EncoderUnavailable` when node or the package is missing (run
    ``./scripts/setup``) or the encoder fails, ValueError for more than :data:`MAX_PIXELS`.
    """
    h, w, c = rgba.shape
    if c != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"rgba must be (H, W, 4) uint8, got {rgba.shape} {rgba.dtype}")
    if w * h > MAX_PIXELS:
        raise ValueError(f"a {w}x{h} image is over the KTX2 encoder's {MAX_PIXELS} texels")
    node = shutil.which("node")
    if node is None:
        raise Ktx2EncoderUnavailable(
            "Writing KTX2 needs Node.js: install node (>= 18) and run ./scripts/setup."
        )
    script, package = _paths()
    if not package.is_dir() or not script.is_file():
        raise Ktx2EncoderUnavailable(
            f"The npm package {PACKAGE} (Basis Universal's KTX2 encoder) is not installed: run "
            "'npm ci --prefix tools/npm' (./scripts/setup does it)."
        )
    options = {
        "width": w,
        "height": h,
        "codec": codec,
        "quality": quality,
        "effort": effort,
        "srgb": srgb,
        "mipmaps": mipmaps,
        "zstd": zstd,
        "alpha": alpha,
    }
    env = {k: v for k, v in os.environ.items() if k in ("PATH", "HOME", "LANG", "TMPDIR")}
    try:
        proc = subprocess.run(
            [node, str(script), json.dumps(options)],
            input=np.ascontiguousarray(rgba).tobytes(),
            capture_output=True,
            timeout=timeout_s,
            env=env,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise Ktx2EncoderUnavailable(
            f"the KTX2 encoder took longer than {timeout_s:.0f} s on a {w}x{h} image"
        ) from None
    if proc.returncode != 0 or not proc.stdout:
        lines = proc.stderr.decode("utf-8", "replace").strip().splitlines() or ["no reason given"]
        raise Ktx2EncoderUnavailable(f"the KTX2 encoder failed on a {w}x{h} image: {lines[-1]}")
    return proc.stdout
