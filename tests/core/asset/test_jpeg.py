"""JPEG quantisation tables read from the file, and deblocking with them."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from pbrsr_core.asset import encode_image, load_asset, make_test_asset, read_image
from pbrsr_core.asset.jpeg import compress, deblock, quant_tables, standard_quant, stored_as
from pbrsr_core.optim.presets import get_preset
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset

# libjpeg's luminance table (Annex K), first row; at quality q the tables are scaled by
# s = 200 - 2q percent: entry = max(1, (base * s + 50) // 100)
ANNEX_K_LUMA_ROW0 = [16, 11, 10, 16, 24, 40, 51, 61]
ANNEX_K_CHROMA_ROW0 = [17, 18, 24, 47, 99, 99, 99, 99]


def _scaled(row: list[int], quality: int) -> list[int]:
    s = 200 - 2 * quality if quality >= 50 else 5000 // quality
    return [max(1, (b * s + 50) // 100) for b in row]


def _texture(size: int = 96) -> np.ndarray:
    """Smooth colour gradients, sinusoids and a hard-edged square (the LR map of a texture)."""
    y, x = np.mgrid[0:size, 0:size] / size
    img = np.stack(
        [
            0.5 + 0.3 * np.sin(2 * np.pi * 3 * x) * np.cos(2 * np.pi * 2 * y),
            0.3 + 0.5 * x,
            0.6 - 0.3 * y + 0.1 * np.sin(2 * np.pi * 7 * (x + y)),
        ],
        -1,
    )
    img[size // 3 : size // 2, size // 4 : size // 2] = [0.9, 0.1, 0.2]
    return np.ascontiguousarray(img.astype(np.float32).clip(0, 1))


def _pil_jpeg(img: np.ndarray, quality: int, subsampling: int, mode: str = "RGB") -> bytes:
    arr = (img * 255 + 0.5).astype(np.uint8)
    pil = Image.fromarray(arr[..., 0] if mode == "L" else arr, mode)
    buf = io.BytesIO()
    pil.save(buf, "JPEG", quality=quality, subsampling=subsampling)
    return buf.getvalue()


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(1 / float(((a.astype(np.float64) - b) ** 2).mean()))


def test_tables_of_our_own_writer_and_of_pillow():
    q = quant_tables(encode_image(_texture(), 8, "jpeg"))  # quality 95, 4:4:4
    assert q is not None and len(q.tables) == 3
    assert q.tables[0][0].tolist() == _scaled(ANNEX_K_LUMA_ROW0, 95)
    assert q.tables[1][0].tolist() == _scaled(ANNEX_K_CHROMA_ROW0, 95)
    p = quant_tables(_pil_jpeg(_texture(), 50, subsampling=0))
    assert p is not None and p.tables[0][0].tolist() == ANNEX_K_LUMA_ROW0  # quality 50: base
    grey = quant_tables(_pil_jpeg(_texture(), 80, subsampling=0, mode="L"))
    assert grey is not None and len(grey.tables) == 1


@pytest.mark.parametrize("quality", [10, 30, 75, 95, 100])
@pytest.mark.parametrize("subsampling", [0, 2])  # 4:4:4, 4:2:0
def test_standard_tables_are_the_ones_libjpeg_writes(quality, subsampling):
    read = quant_tables(_pil_jpeg(_texture(), quality, subsampling))
    ours = standard_quant(quality, subsampled=subsampling == 2)
    assert read is not None and read.full == ours.full
    for a, b in zip(read.tables, ours.tables, strict=True):
        np.testing.assert_array_equal(a, b)


def _noisy_texture(size: int = 96) -> np.ndarray:
    rng = np.random.default_rng(3)
    return (_texture(size) + rng.normal(0, 0.04, (size, size, 3))).clip(0, 1).astype(np.float32)


@pytest.mark.parametrize(("quality", "subsampling"), [(40, 0), (90, 0), (40, 2), (90, 2)])
def test_compress_decodes_as_a_real_jpeg_file(quality, subsampling):
    img = _noisy_texture(70)[:, :61]  # sides not multiples of 8 (nor of 16), one odd
    real = read_image(_pil_jpeg(img, quality, subsampling), "r.jpg")[0]
    x = torch.from_numpy(img).permute(2, 0, 1)[None]
    ours = compress(x, standard_quant(quality, subsampling == 2))[0].permute(1, 2, 0).numpy()
    assert ours.shape == img.shape and np.isfinite(ours).all()
    np.testing.assert_array_equal(ours, np.round(ours * 255) / 255)  # 8-bit steps
    # the file differs from its input by the compression, the simulation from the file by
    # libjpeg's integer arithmetic (measured here: 44-56 dB, the input 24-30 dB from the file)
    ref = (np.round(img * 255) / 255).astype(np.float32)
    assert _psnr(ours, real) > max(43.0, _psnr(ref, real) + 10.0), _psnr(ours, real)


@pytest.mark.parametrize("quality", [40, 90])
def test_compress_decodes_a_grey_image_as_a_real_grey_jpeg_file(quality):
    img = _noisy_texture(70)[:, :61, :1]
    data = _pil_jpeg(img, quality, subsampling=0, mode="L")
    real = read_image(data, "g.jpg")[0][..., :1]  # grey is read as RGB
    quant = quant_tables(data)
    assert quant is not None and len(quant.tables) == 1
    ours = compress(torch.from_numpy(img).permute(2, 0, 1)[None], quant)[0].permute(1, 2, 0)
    ref = (np.round(img * 255) / 255).astype(np.float32)
    assert _psnr(ours.numpy(), real) > max(43.0, _psnr(ref, real) + 10.0)
    with pytest.raises(ValueError, match="three tables, or grey ones and one"):
        compress(torch.from_numpy(img).permute(2, 0, 1)[None], standard_quant(quality))


def test_an_image_stored_as_a_file_would_store_it():
    """``stored_as``: the image through the file's compression (its chroma sampling kept),
    and with ``deblocked`` the deblocking the pipeline applies to such a file; a grey file
    stores the first channel and is read back as grey in every colour channel."""
    img = _noisy_texture(64)
    rgba = np.concatenate([img, np.full_like(img[..., :1], 0.5)], -1)
    for quant in (standard_quant(85, subsampled=True), standard_quant(60)):
        want = compress(torch.from_numpy(img).permute(2, 0, 1)[None], quant)[0].permute(1, 2, 0)
        got = stored_as(rgba, quant, deblocked=False)
        np.testing.assert_array_equal(got[..., :3], want.numpy())
        np.testing.assert_array_equal(got[..., 3], rgba[..., 3])  # beyond the file: kept
        np.testing.assert_array_equal(stored_as(img, quant, True), deblock(got[..., :3], quant))
    grey_quant = quant_tables(_pil_jpeg(img, 70, subsampling=0, mode="L"))
    assert grey_quant is not None
    grey = stored_as(img, grey_quant, deblocked=False)
    assert np.array_equal(grey[..., 0], grey[..., 1]) and np.array_equal(grey[..., 0], grey[..., 2])
    assert 25.0 < _psnr(grey[..., 0], img[..., 0]) < 60.0  # compressed, and the first channel's


def test_files_it_cannot_model_give_none():
    img = _texture()
    assert quant_tables(encode_image(img, 8, "png")) is None
    data = encode_image(img, 8, "jpeg")
    for cut in (2, 20, 100):  # truncated before the frame: no crash, no tables
        assert quant_tables(data[:cut]) is None
    assert quant_tables(b"\xff\xd8\x00garbage") is None
    # a frame header announcing three components but holding none
    assert quant_tables(b"\xff\xd8\xff\xc0\x00\x08\x08\x00\x10\x00\x10\x03") is None


@pytest.mark.parametrize("quality", [50, 95])
def test_deblocking_brings_the_pixels_closer_to_what_was_compressed(quality):
    img = _texture()
    data = _pil_jpeg(img, quality, subsampling=0)
    decoded = read_image(data, "t.jpg")[0]
    out = deblock(decoded, quant_tables(data))
    assert out.shape == decoded.shape and out.dtype == np.float32
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    # measured on this texture: +2.2 dB at quality 50, +3.4 dB at 95
    assert _psnr(out, img) > _psnr(decoded, img) + 1.0


def _ycc(a: np.ndarray) -> np.ndarray:
    rows = [[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]]
    return a.astype(np.float64) @ np.array(rows).T


@pytest.mark.parametrize(("subsampling", "steps"), [(1, (1, 2)), (2, (2, 2))])  # 4:2:2, 4:2:0
def test_subsampled_chroma_is_rebuilt_from_the_deblocked_luma(subsampling, steps):
    """The file's sampling steps are read; the luma is deblocked, the chroma rebuilt at full
    resolution comes closer to the image's, and its mean over each sample's texels stays near
    the decoded chroma's."""
    img = _texture()
    data = _pil_jpeg(img, 50, subsampling=subsampling)
    q = quant_tables(data)
    assert q is not None and q.full == (True, False, False)
    assert q.steps == ((1, 1), steps, steps)
    decoded = read_image(data, "s.jpg")[0]
    out = deblock(decoded, q)
    assert np.isfinite(out).all() and out.min() >= 0.0 and out.max() <= 1.0
    for c in range(3):  # luma deblocked, each chroma component closer
        assert _psnr(_ycc(out)[..., c], _ycc(img)[..., c]) > _psnr(
            _ycc(decoded)[..., c], _ycc(img)[..., c]
        )
    assert _psnr(out, img) > _psnr(decoded, img) + 0.05  # measured: +0.40 (4:2:2), +0.12 dB

    def sample_means(a):
        h, w = a.shape[0] // steps[0], a.shape[1] // steps[1]
        return a.reshape(h, steps[0], w, steps[1], -1).mean((1, 3))

    inside = (out > 0.002).all(-1) & (out < 0.998).all(-1)  # no clamping at 0 or 1
    assert sample_means(inside[..., None].astype(float)).min() == 1.0  # nowhere on this one
    moved = sample_means(_ycc(out)[..., 1:]) - sample_means(_ycc(decoded)[..., 1:])
    assert np.abs(moved).mean() < 1.0 / 255  # a back-projection step: within a level


def test_a_colour_edge_keeps_its_chroma_at_4_2_0():
    """Two flat colours meeting on an edge between chroma samples: the decoder spreads their
    chroma over four texels, the luma-guided rebuild puts the edge back (chroma a linear
    function of luma on either side)."""
    img = np.zeros((64, 64, 3), np.float32)
    img[:] = [0.85, 0.2, 0.15]
    img[:, 29:] = [0.1, 0.3, 0.8]
    data = _pil_jpeg(img, 95, subsampling=2)
    decoded = read_image(data, "e.jpg")[0]
    out = deblock(decoded, quant_tables(data))
    assert _psnr(out, img) > _psnr(decoded, img) + 10.0  # measured: 27.7 -> 40.7 dB


def test_deblocking_grey_and_odd_sizes():
    img = _texture(50)[:37]  # neither side a multiple of 8
    data = _pil_jpeg(img, 60, subsampling=0, mode="L")
    decoded = read_image(data, "g.jpg")[0]  # grey, expanded to RGB
    out = deblock(decoded, quant_tables(data))
    assert out.shape == decoded.shape
    np.testing.assert_array_equal(out[..., 0], out[..., 1])
    assert _psnr(out[..., 0], img[..., 0]) > _psnr(decoded[..., 0], img[..., 0])


def test_pipeline_deblocks_jpeg_maps_in_direct_and_the_cpu_presets(tmp_path: Path):
    src = make_test_asset(tmp_path / "in" / "a.glb", size=32, features={"jpeg"})
    jpegs = {im.name for im in load_asset(src).images if im.roles and im.jpeg is not None}
    assert jpegs
    fast = upscale_asset(
        src, tmp_path / "f", UpscaleOptions(method="pbrsr", preset="fast", prior="bicubic")
    )
    assert set(fast["jpeg_deblocked"]) == jpegs and "deblock" in fast["timings"]
    res = load_asset(tmp_path / "f" / "a.glb")
    for img in res.images:
        assert np.isfinite(img.pixels).all()
    direct = upscale_asset(
        src, tmp_path / "d", UpscaleOptions(method="direct", prior="bicubic", scale=2)
    )
    assert set(direct["jpeg_deblocked"]) == jpegs and "deblock" in direct["timings"]
    upscale_asset(src, tmp_path / "b", UpscaleOptions(method="bicubic", scale=2))
    by_name = {im.name: im.pixels for im in load_asset(tmp_path / "b" / "a.glb").images}
    for img in load_asset(tmp_path / "d" / "a.glb").images:  # direct upscaled the deblocked maps
        if img.name in jpegs:
            assert np.abs(img.pixels - by_name[img.name]).max() > 1e-3
    assert not get_preset("paper").deblock_jpeg  # the paper takes the LR maps as they are


def test_mangled_headers_never_raise():
    """The tables are read from every JPEG an asset holds, so no header may crash loading."""
    data = bytearray(encode_image(_texture(), 8, "jpeg"))
    rng = np.random.default_rng(0)
    for _ in range(300):
        b = bytearray(data[:700])
        for pos in rng.integers(2, len(b), size=4):
            b[pos] = int(rng.integers(0, 256))
        q = quant_tables(bytes(b[: int(rng.integers(2, len(b)))]))
        assert q is None or all(t.shape == (8, 8) and (t > 0).all() for t in q.tables)
