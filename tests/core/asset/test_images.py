"""Texture files through OpenImageIO: round trips per format, limits before decoding, output
format rules, tangents on hard UV layouts."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest

from pbrsr_core.asset.images import (
    encode_image,
    output_encoding,
    output_format,
    read_image,
    read_texture,
    write_image,
)
from pbrsr_core.asset.model import ImageData
from pbrsr_core.asset.tangents import generate_tangents
from pbrsr_core.asset.texture_codecs import Ktx2Encoding
from pbrsr_core.errors import InvalidAsset, LimitExceeded, UnsupportedAsset
from pbrsr_core.limits import Limits
from tests.hostile import png_header_bomb

RNG = np.random.default_rng(1)


@pytest.mark.parametrize(
    "fmt,bits,tol",
    [
        ("png", 8, 0.5 / 255),
        ("png", 16, 0.5 / 65535),
        ("exr", 16, 5e-4),
        ("exr", 32, 0.0),
        ("tiff", 8, 0.5 / 255),
        ("tiff", 16, 0.5 / 65535),
        ("tiff", 32, 0.0),
    ],
)
@pytest.mark.parametrize("channels", [3, 4])
def test_encode_read_round_trip(fmt, bits, tol, channels):
    px = RNG.random((7, 5, channels), dtype=np.float32)
    data = encode_image(px, bits, fmt)
    out, depth, mime = read_image(data, "x")
    assert out.shape == px.shape and out.dtype == np.float32 and depth == bits
    assert np.abs(out - px).max() <= tol + 1e-7  # alpha is kept straight (unassociated)


def test_jpeg_and_grey_and_file(tmp_path):
    y, x = np.mgrid[0:16, 0:16] / 16.0
    smooth = np.stack([x, y, 0.5 * (x + y)], -1).astype(np.float32)
    out, depth, mime = read_image(encode_image(smooth, 8, "jpeg"), "j")
    assert mime == "image/jpeg" and depth == 8 and np.abs(out - smooth).mean() < 0.02
    grey = RNG.random((4, 6, 1), dtype=np.float32)
    path = write_image(tmp_path / "g.png", grey, 8, "png")
    out, _, _ = read_image(path, "g.png")
    assert out.shape == (4, 6, 3) and np.allclose(out, grey, atol=0.5 / 255 + 1e-7)


def test_png_bomb_refused_fast_with_little_memory():
    tracemalloc.start()
    t = time.perf_counter()
    with pytest.raises(LimitExceeded, match="100000x100000"):
        read_image(png_header_bomb(), "bomb.png")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert time.perf_counter() - t < 1.0 and peak < 10 * 2**20


def test_limits_and_not_images():
    px = np.zeros((20, 10, 3), np.float32)
    with pytest.raises(LimitExceeded):
        read_image(encode_image(px, 8, "exr" if False else "png"), "a", Limits(max_texture_dim=16))
    with pytest.raises(LimitExceeded):
        read_image(encode_image(px, 8, "jpeg"), "a", Limits(max_texture_dim=16))
    with pytest.raises(LimitExceeded):
        read_image(encode_image(px, 16, "exr"), "a", Limits(max_texture_dim=16))
    with pytest.raises(InvalidAsset, match="not an image"):
        read_image(b"hello, I am text in a .png", "a.png")
    with pytest.raises(InvalidAsset):
        read_image(encode_image(px, 8, "png")[:60], "cut.png")
    with pytest.raises(UnsupportedAsset):
        read_image(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;", "a.gif")
    with pytest.raises(InvalidAsset):
        read_image(b"", "e.png")


def test_exr_nan_is_refused():
    px = np.full((4, 4, 3), 0.5, np.float32)
    data = bytearray(encode_image(px, 32, "exr"))
    import OpenImageIO as oiio  # write a NaN through OIIO directly (write_image refuses NaN)

    bad = px.copy()
    bad[1, 1, 0] = np.nan
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        p = str(Path(d) / "n.exr")
        out = oiio.ImageOutput.create(p)
        out.open(p, oiio.ImageSpec(4, 4, 3, "float"))
        out.write_image(bad)
        out.close()
        data = Path(p).read_bytes()
    with pytest.raises(InvalidAsset, match="NaN"):
        read_image(data, "n.exr")


def _img(mime, depth, c=3):
    return ImageData(
        index=0, name="x", pixels=np.zeros((2, 2, c), np.float32), bit_depth=depth, mime=mime
    )


@pytest.mark.parametrize(
    "mime,depth,c,req,expect",
    [
        ("image/png", 8, 3, "same", ("png", 8)),
        ("image/jpeg", 8, 3, "same", ("jpeg", 8)),
        ("image/jpeg", 8, 3, "png", ("png", 8)),
        ("image/png", 16, 3, "jpeg", ("png", 16)),  # upgraded, never lower precision
        ("image/png", 16, 3, "png", ("png", 16)),
        ("image/png", 8, 4, "jpeg", ("png", 8)),  # JPEG has no alpha
        ("image/x-exr", 32, 3, "png16", ("exr", 32)),
        ("image/x-exr", 16, 3, "same", ("exr", 16)),
        ("image/png", 8, 3, "exr", ("exr", 16)),
        ("image/tiff", 16, 3, "same", ("tiff", 16)),
        ("image/webp", 8, 4, "same", ("webp", 8)),
        ("image/png", 8, 4, "avif", ("avif", 8)),
        ("image/png", 16, 3, "webp", ("png", 16)),
        ("image/png", 8, 3, "ktx2", ("png", 8)),  # 2x2: KTX2 needs sides that are multiples of 4
    ],
)
def test_output_format(mime, depth, c, req, expect):
    fmt, bits, _, _ = output_format(_img(mime, depth, c), req)
    assert (fmt, bits) == expect


def test_4096_square_ktx2_map_is_written_as_ktx2_and_reads_back():
    # a 1024x1024 KTX2 map upscaled x4 stays KTX2: a flat occlusion/roughness/metalness map
    # (flat is cheap to encode) as UASTC + Zstandard with mips, as pbrsr writes data maps
    n = 4096
    pixels = np.broadcast_to(np.array([0.8, 0.45, 0.1], np.float32), (n, n, 3))
    encoding = Ktx2Encoding(codec="uastc", zstd=True, srgb=False, mipmaps=True)
    image = ImageData(0, "x", pixels, 8, "image/ktx2", {"metallic_roughness"}, encoding=encoding)
    fmt, bits, mime, _ = output_format(image)
    assert (fmt, bits, mime) == ("ktx2", 8, "image/ktx2")
    data = encode_image(pixels, bits, fmt, output_encoding(image, fmt))
    back, depth, back_mime, read_as = read_texture(data, "x")
    assert (back.shape, depth, back_mime, read_as) == ((n, n, 3), 8, "image/ktx2", encoding)
    assert np.abs(back - pixels).max() <= 1.5 / 255


def _check_frames(t, n):
    assert np.isfinite(t).all()
    assert np.allclose(np.linalg.norm(t[:, :3], axis=1), 1.0, atol=1e-5)
    assert np.abs(np.sum(t[:, :3] * n, axis=1)).max() < 1e-5
    assert set(np.unique(t[:, 3])) <= {-1.0, 1.0}


def test_tangents_plane_mirrored_and_degenerate():
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    nrm = np.tile([0.0, 0.0, 1.0], (4, 1))
    tri = np.array([[0, 1, 2], [1, 3, 2]])
    # glTF UVs: u right, v down; here v = 1 - y
    uv = np.stack([pos[:, 0], 1 - pos[:, 1]], 1)
    t = generate_tangents(pos, nrm, uv, tri)
    _check_frames(t, nrm)
    assert np.allclose(t[:, :3], [1, 0, 0], atol=1e-6) and (t[:, 3] == 1).all()
    mirrored = uv.copy()
    mirrored[:, 0] = 1 - mirrored[:, 0]
    t = generate_tangents(pos, nrm, mirrored, tri)
    _check_frames(t, nrm)
    assert np.allclose(t[:, :3], [-1, 0, 0], atol=1e-6) and (t[:, 3] == -1).all()
    for bad_uv in (np.zeros((4, 2)), np.tile([[0.3, 0.7]], (4, 1)), None):
        _check_frames(generate_tangents(pos, nrm, bad_uv, tri), nrm)
    # zero-area triangles and normals parallel to the only tangent direction
    pos2 = np.zeros((4, 3))
    _check_frames(generate_tangents(pos2, nrm, uv, tri), nrm)
    nx = np.tile([1.0, 0.0, 0.0], (4, 1))
    _check_frames(generate_tangents(pos, nx, uv, tri), nx)


def test_write_checks_and_clamps_strip_by_strip(tmp_path):
    """A 1200 x 600 map is written in several strips: a NaN in the last strip is refused
    before anything is written, and values outside [0, 1] in any strip are clamped."""
    rng = np.random.default_rng(7)
    px = rng.random((1200, 600, 3), dtype=np.float32)
    px[0, 0] = [2.0, -1.0, 0.5]
    px[-1, -1] = [1.5, 0.25, -0.5]
    out = write_image(tmp_path / "a.png", px, 16, "png")
    back = read_image(out, "a.png")[0]
    np.testing.assert_allclose(back, np.clip(px, 0, 1), atol=1 / 65535)
    bad = px.copy()
    bad[-1, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        write_image(tmp_path / "b.png", bad, 8, "png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]
