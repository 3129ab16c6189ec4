"""Texture files: PNG 8/16-bit, JPEG, EXR (half/float), TIFF through OpenImageIO; KTX2
(Basis Universal), WebP and AVIF through :mod:`pbrsr_core.asset.texture_codecs`.

Pixels are numpy ``(H, W, C)`` float32 in [0, 1] as stored (no colour conversion here; see
``pbrsr_core.colour``). Decisions, documented once:

* The header is checked against :class:`~pbrsr_core.limits.Limits` *before* any pixel is
  decoded (PNG and JPEG headers are parsed here, EXR/TIFF through OpenImageIO's header read,
  KTX2/WebP/AVIF in ``texture_codecs``), so a decompression bomb costs a few bytes of reading.
* Bytes whose magic is none of these formats are :class:`InvalidAsset` ("not an image"),
  except known image formats pbrsr does not take (KTX 1, GIF, BMP, JPEG 2000):
  :class:`UnsupportedAsset`.
* Grey images are expanded to RGB (grey+alpha to RGBA), as glTF samplers see them.
* Alpha is read and written *unassociated* (straight), as PNG stores it.
* EXR: NaN or infinite texels are refused (``InvalidAsset``): a texture with NaN is broken
  and silently replacing values would hide it. Finite values are clipped to [0, 1].
* Bit depth: 8 and 16 for integer formats; 16 for half EXR, 32 for float EXR/TIFF; 8 for
  KTX2, WebP and AVIF.
"""

from __future__ import annotations

import os
import struct
import tempfile
from pathlib import Path
from typing import Literal, NamedTuple, cast

import numpy as np
import OpenImageIO as oiio

from ..errors import InvalidAsset, InvalidOptions, LimitExceeded, UnsupportedAsset
from ..limits import Limits, check_image_size
from .model import SRGB_ROLES, ImageData
from .texture_codecs import (
    TextureEncoding,
    TextureFormat,
    decode_texture,
    default_encoding,
    encode_texture,
    sniff_texture_format,
)

ImageFormat = Literal["png", "jpeg", "exr", "tiff", "ktx2", "webp", "avif"]
TEXTURE_FORMATS: frozenset[ImageFormat] = frozenset({"ktx2", "webp", "avif"})
"""The formats :mod:`pbrsr_core.asset.texture_codecs` reads and writes (8 bits per channel)."""

MIME: dict[ImageFormat, str] = {
    "png": "image/png",
    "jpeg": "image/jpeg",
    "exr": "image/x-exr",
    "tiff": "image/tiff",
    "ktx2": "image/ktx2",
    "webp": "image/webp",
    "avif": "image/avif",
}
EXT: dict[ImageFormat, str] = {
    "png": ".png",
    "jpeg": ".jpg",
    "exr": ".exr",
    "tiff": ".tif",
    "ktx2": ".ktx2",
    "webp": ".webp",
    "avif": ".avif",
}
FORMAT_OF_MIME: dict[str, ImageFormat] = {v: k for k, v in MIME.items()}
_LOSSLESS_MIMES = {"image/png", "image/x-exr", "image/tiff"}


JpegSubsampling = Literal["4:4:4", "4:2:0"]


class JpegEncoding(NamedTuple):
    """How :func:`write_image` stores a JPEG: its quality (libjpeg's 1-100 scale of the
    standard quantisation tables) and whether its chroma is kept at full resolution (4:4:4)
    or at half in each direction (4:2:0, as most image editors and web pipelines store it)."""

    quality: int = 95
    subsampling: JpegSubsampling = "4:4:4"


JPEG_SUBSAMPLING: dict[str, JpegSubsampling] = {"444": "4:4:4", "420": "4:2:0"}
"""The chroma suffixes of a ``jpeg:Q:...`` request and the sampling each names."""


def jpeg_request(requested: str) -> tuple[str, JpegEncoding | None]:
    """An image format request, and the JPEG encoding it names: ``jpeg:Q`` (quality Q at
    4:4:4) or ``jpeg:Q:420`` / ``jpeg:Q:444`` -> ("jpeg", that encoding); any other request
    -> (it, None). A malformed ``jpeg:`` request is refused (:class:`InvalidOptions`)."""
    if not requested.startswith("jpeg:"):
        return requested, None
    parts = requested.split(":")[1:]
    quality = parts[0] if parts else ""
    chroma = parts[1] if len(parts) > 1 else "444"
    if (
        len(parts) > 2
        or not quality.isdigit()
        or not 1 <= int(quality) <= 100
        or chroma not in JPEG_SUBSAMPLING
    ):
        raise InvalidOptions(
            f"bad JPEG format {requested!r}: use jpeg:QUALITY or jpeg:QUALITY:420 (chroma at "
            "half resolution) or jpeg:QUALITY:444, QUALITY 1-100"
        )
    return "jpeg", JpegEncoding(int(quality), JPEG_SUBSAMPLING[chroma])


class EncodedImage(NamedTuple):
    """An image's encoded file bytes, with what they were encoded as."""

    data: bytes
    mime: str
    ext: str
    fmt: ImageFormat
    bit_depth: int


_UNSUPPORTED_MAGIC = {
    b"\xabKTX 11": "KTX 1",
    b"GIF8": "GIF",
    b"BM": "BMP",
    b"\x00\x00\x00\x0cjP": "JPEG 2000",
}


def sniff_format(head: bytes) -> ImageFormat:
    """The image format from the first bytes; raises InvalidAsset/UnsupportedAsset."""
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if head.startswith(b"\x76\x2f\x31\x01"):
        return "exr"
    if head.startswith((b"II*\x00", b"MM\x00*")):
        return "tiff"
    texture = sniff_texture_format(head)
    if texture is not None:
        return texture
    for magic, what in _UNSUPPORTED_MAGIC.items():
        if head.startswith(magic):
            raise UnsupportedAsset(
                f"{what} images are not supported (use PNG, JPEG, EXR, TIFF, KTX2, WebP, AVIF)"
            )
    raise InvalidAsset("not an image (unknown file signature)")


def _png_size(data: bytes) -> tuple[int, int]:
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise InvalidAsset("truncated PNG header")
    w, h = struct.unpack(">II", data[16:24])
    return w, h


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """Width and height from the first SOFn marker (no decoding)."""
    i = 2
    n = len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            i += 1
            continue
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in (0x01, 0xD8) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        (seg_len,) = struct.unpack(">H", data[i + 2 : i + 4])
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                break
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return w, h
        i += 2 + seg_len
    raise InvalidAsset("truncated JPEG header (no frame marker)")


def _read_with_oiio(
    filename: str, fmt: ImageFormat, name: str, limits: Limits
) -> tuple[np.ndarray, int, str]:
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(filename, config)
    if inp is None:
        msg = oiio.geterror()
        if "exceeds" in msg and "limit" in msg:
            raise LimitExceeded(f"the image '{name}' declares a size over the limit")
        raise InvalidAsset(
            f"the image '{name}' cannot be read: {msg.splitlines()[0] if msg else fmt}"
        )
    try:
        spec = inp.spec()
        check_image_size(spec.width, spec.height, name, limits)
        if spec.depth > 1 or spec.nchannels < 1 or spec.nchannels > 4:
            raise UnsupportedAsset(
                f"the image '{name}' has {spec.nchannels} channels/depth {spec.depth}; "
                "pbrsr takes 1-4 channel 2D images"
            )
        basetype = spec.format.basetype
        if basetype in (oiio.UINT8, oiio.INT8):
            bit_depth = 8
        elif basetype in (oiio.UINT16, oiio.INT16) or basetype == oiio.HALF:
            bit_depth = 16
        else:
            bit_depth = 32
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise InvalidAsset(f"the image '{name}' is corrupt or truncated: {oiio.geterror()}")
    finally:
        inp.close()
        oiio.geterror()  # clear any pending message so OIIO does not print it at exit
    pixels = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, -1)
    if fmt in ("exr", "tiff") and not np.isfinite(pixels).all():
        raise InvalidAsset(f"the image '{name}' contains NaN or infinite values")
    pixels = np.clip(pixels, 0.0, 1.0)
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    elif pixels.shape[2] == 2:
        pixels = np.concatenate([np.repeat(pixels[..., :1], 3, axis=2), pixels[..., 1:]], axis=2)
    return np.ascontiguousarray(pixels), bit_depth, MIME[fmt]


def read_image(
    data: bytes | Path, name: str, limits: Limits = Limits()
) -> tuple[np.ndarray, int, str]:
    """Decode one image -> ``(pixels (H, W, C) float32 [0, 1], bit_depth, mime)``.

    ``data`` is the encoded bytes or a file path; ``name`` is the asset-relative label used in
    error messages. C is 3 or 4 (grey is expanded). Raises InvalidAsset (not an image,
    corrupt, NaN), UnsupportedAsset (a known format pbrsr does not take) and LimitExceeded
    (dimensions over ``limits.max_texture_dim``, checked from the header before decoding).
    """
    pixels, depth, mime, _ = read_texture(data, name, limits)
    return pixels, depth, mime


def read_texture(
    data: bytes | Path, name: str, limits: Limits = Limits()
) -> tuple[np.ndarray, int, str, TextureEncoding | None]:
    """:func:`read_image`, with the encoding a KTX2 or WebP file needs to be written back as
    it was (:mod:`~pbrsr_core.asset.texture_codecs`; None for the other formats)."""
    if isinstance(data, (str, Path)):
        path = Path(data)
        with open(path, "rb") as f:
            head = f.read(1 << 16)
        if not head:
            raise InvalidAsset(f"the image '{name}' is empty")
        fmt = _sniff(head, name)
        if fmt in TEXTURE_FORMATS:
            return _read_texture_format(path.read_bytes(), fmt, name, limits)
        _precheck(fmt, head, name, limits)
        return (*_read_with_oiio(str(path), fmt, name, limits), None)
    data = bytes(data)
    if not data:
        raise InvalidAsset(f"the image '{name}' is empty")
    fmt = _sniff(data[:16], name)
    if fmt in TEXTURE_FORMATS:
        return _read_texture_format(data, fmt, name, limits)
    _precheck(fmt, data, name, limits)
    fd, tmp = tempfile.mkstemp(prefix="pbrsr-img-", suffix=EXT[fmt])
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return (*_read_with_oiio(tmp, fmt, name, limits), None)
    finally:
        os.unlink(tmp)


def _sniff(head: bytes, name: str) -> ImageFormat:
    try:
        return sniff_format(head)
    except InvalidAsset as exc:
        raise InvalidAsset(f"the image '{name}' is {exc.message}") from None


def _read_texture_format(
    data: bytes, fmt: ImageFormat, name: str, limits: Limits
) -> tuple[np.ndarray, int, str, TextureEncoding | None]:
    pixels, encoding = decode_texture(data, cast(TextureFormat, fmt), name, limits)
    return np.ascontiguousarray(pixels), 8, MIME[fmt], encoding


def _precheck(fmt: ImageFormat, head: bytes, name: str, limits: Limits) -> None:
    if fmt == "png":
        check_image_size(*_png_size(head), name, limits)
    elif fmt == "jpeg":
        try:
            w, h = _jpeg_size(head)
        except InvalidAsset:
            return  # frame marker beyond the first bytes read: OIIO's header read checks it
        check_image_size(w, h, name, limits)


def _oiio_type(fmt: ImageFormat, bit_depth: int) -> str:
    if fmt == "jpeg":
        if bit_depth != 8:
            raise InvalidOptions("JPEG holds 8 bits per channel only")
        return "uint8"
    if fmt == "png":
        if bit_depth not in (8, 16):
            raise InvalidOptions("PNG holds 8 or 16 bits per channel")
        return "uint8" if bit_depth == 8 else "uint16"
    if fmt == "exr":
        if bit_depth not in (16, 32):
            raise InvalidOptions("EXR holds half (16) or float (32) channels")
        return "half" if bit_depth == 16 else "float"
    if fmt == "tiff":
        return {8: "uint8", 16: "uint16", 32: "float"}[bit_depth]
    raise InvalidOptions(f"unknown image format {fmt!r}")


def write_image(
    path: Path,
    pixels: np.ndarray,
    bit_depth: int,
    fmt: ImageFormat,
    encoding: TextureEncoding | JpegEncoding | None = None,
) -> Path:
    """Write ``pixels`` (H, W, C) float32 [0, 1], C in 1..4, to ``path`` atomically.

    ``fmt``: "png" (8/16), "jpeg" (8, as ``encoding`` says, by default quality 95 and 4:4:4;
    no alpha: C must be 1 or 3), "exr"
    (16 half / 32 float, zip compression), "tiff" (8/16/32); "ktx2", "webp", "avif" (8) as
    ``encoding`` says (:func:`pbrsr_core.asset.texture_codecs.encode_texture`).
    """
    path = Path(path)
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or not 1 <= arr.shape[2] <= 4 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ValueError(f"pixels must be (H, W, C) with C in 1..4, got {arr.shape}")
    if fmt == "jpeg" and arr.shape[2] in (2, 4):
        raise InvalidOptions("JPEG has no alpha channel; write PNG for images with alpha")
    h, w, c = arr.shape
    # in strips of ~0.5 Mpixel: a 2048^2 PNG takes ~1 s to encode, and between strips the
    # interpreter runs (a job's cancel watchdog can interrupt; other threads get the GIL);
    # the checks and the clamped copy are per strip too (a whole 4096^2 RGB float copy is
    # 200 MB, per image being encoded)
    rows = max(1, (1 << 19) // w)
    strips = range(0, h, rows)
    if not all(np.isfinite(arr[y : y + rows]).all() for y in strips):
        raise ValueError("pixels contain NaN or infinite values")
    fd, tmp = tempfile.mkstemp(prefix=".pbrsr-", suffix=EXT[fmt], dir=path.parent)
    os.close(fd)
    try:
        if fmt in TEXTURE_FORMATS:
            texture_encoding = cast(TextureEncoding | None, encoding)
            Path(tmp).write_bytes(encode_texture(arr, cast(TextureFormat, fmt), texture_encoding))
            os.replace(tmp, path)
            return path
        spec = oiio.ImageSpec(w, h, c, _oiio_type(fmt, bit_depth))
        spec.attribute("oiio:UnassociatedAlpha", 1)
        if fmt == "jpeg":
            jpeg = encoding if isinstance(encoding, JpegEncoding) else JpegEncoding()
            spec.attribute("Compression", f"jpeg:{jpeg.quality}")
            spec.attribute("jpeg:subsampling", jpeg.subsampling)
        elif fmt == "exr" or fmt == "tiff":
            spec.attribute("compression", "zip")
        out = oiio.ImageOutput.create(tmp)
        if out is None or not out.open(tmp, spec):
            raise OSError(f"cannot write image: {oiio.geterror()}")
        ok = True
        for y in strips:
            strip = np.ascontiguousarray(np.clip(arr[y : y + rows], 0.0, 1.0))
            ok = ok and out.write_scanlines(y, min(h, y + rows), 0, strip)
        out.close()
        if not ok:
            raise OSError(f"cannot write image: {oiio.geterror()}")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def encode_image(
    pixels: np.ndarray,
    bit_depth: int,
    fmt: ImageFormat,
    encoding: TextureEncoding | JpegEncoding | None = None,
) -> bytes:
    """The encoded bytes of :func:`write_image`'s file (for embedding in a GLB/data URI)."""
    with tempfile.TemporaryDirectory(prefix="pbrsr-enc-") as d:
        p = write_image(Path(d) / f"image{EXT[fmt]}", pixels, bit_depth, fmt, encoding)
        return p.read_bytes()


def output_format(image: ImageData, requested: str = "same") -> tuple[ImageFormat, int, str, str]:
    """The output ``(fmt, bit_depth, mime, ext)`` for ``image`` under ``requested``.

    ``requested`` is "same", "png", "png16", "exr", "jpeg", "ktx2", "webp" or "avif".
    Precision never drops below the input's: a request that would lose precision is
    *upgraded* (not refused): 16-bit input asked as "png"/"jpeg"/"ktx2"/"webp"/"avif" gives
    16-bit PNG; 32-bit float input asked as anything but "exr" gives a float EXR. An image
    with alpha asked as "jpeg" gives PNG (JPEG has no alpha), and so does one asked as (or
    kept as) "ktx2" whose sides are not multiples of 4 (``KHR_texture_basisu`` requires them).
    """
    src = FORMAT_OF_MIME.get(image.mime, "png")
    depth = image.bit_depth
    fmt: ImageFormat
    if requested == "same":
        fmt, bits = src, depth
    elif requested == "png":
        fmt, bits = "png", 8
    elif requested == "png16":
        fmt, bits = "png", 16
    elif requested == "exr":
        fmt, bits = "exr", max(16, depth)
    elif requested in ("jpeg", "ktx2", "webp", "avif"):
        fmt, bits = cast(ImageFormat, requested), 8
    else:
        raise InvalidOptions(
            f"unknown image format {requested!r}: use same, png, png16, exr, jpeg, ktx2, "
            "webp or avif"
        )
    if fmt == "jpeg" and image.channels == 4:
        fmt = "png"
    if fmt == "ktx2" and (image.width % 4 or image.height % 4):
        fmt = "png"
    if depth > bits:
        if depth >= 32:
            fmt, bits = "exr", 32
        else:
            fmt, bits = "png", 16
    if fmt == "exr" and bits < 16:
        bits = 16
    if fmt == "tiff" and bits not in (8, 16, 32):
        bits = 32
    return fmt, bits, MIME[fmt], EXT[fmt]


def output_encoding(image: ImageData, fmt: ImageFormat) -> TextureEncoding | None:
    """The encoding ``image`` is written with as ``fmt``: its own when it keeps its KTX2/WebP
    format, else :func:`~pbrsr_core.asset.texture_codecs.default_encoding` for its role (a
    colour map or data) and source (WebP lossless from a lossless source)."""
    if fmt not in TEXTURE_FORMATS:
        return None
    if FORMAT_OF_MIME.get(image.mime) == fmt and image.encoding is not None:
        return image.encoding
    lossless = image.mime in _LOSSLESS_MIMES or getattr(image.encoding, "lossless", False)
    return default_encoding(cast(TextureFormat, fmt), bool(image.roles & SRGB_ROLES), lossless)
