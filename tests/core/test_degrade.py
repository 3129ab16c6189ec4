"""The LR protocol: shapes, constants preserved, normals unit, assets degraded end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pbrsr_core.asset import load_asset, make_test_asset
from pbrsr_core.asset.jpeg import standard_quant
from pbrsr_core.degrade import (
    KERNELS,
    degrade_asset,
    degrade_image,
    degrade_sigma,
    degrade_tensor,
    downsample,
    lr_downsample,
    lr_model,
    resize_matrix,
    run_kernel,
)
from pbrsr_core.errors import InvalidOptions


@pytest.mark.parametrize("scale", [2, 4, 8])
@pytest.mark.parametrize("shape", [(64, 48, 3), (30, 17, 4), (5, 3, 1)])
@pytest.mark.parametrize("kernel", KERNELS)
def test_shapes_and_constant(scale, shape, kernel):
    img = np.full(shape, 0.3125, np.float32)
    out = degrade_image(img, scale, kernel=kernel)
    assert out.shape == (max(1, round(shape[0] / scale)), max(1, round(shape[1] / scale)), shape[2])
    np.testing.assert_allclose(out, 0.3125, atol=1e-6)


@pytest.mark.parametrize("scale", [2, 4, 8])
@pytest.mark.parametrize("shape", [(70, 45), (9, 40), (3, 2)])
def test_blur_against_scipy(scale, shape):
    """The blur against scipy's correlation with the same taps (reflected borders, or the
    edge repeated where the image is shorter than the kernel's radius), then the same
    bicubic decimation."""
    import torch
    import torch.nn.functional as F
    from scipy.ndimage import correlate1d

    from pbrsr_core.degrade import _gaussian_kernel, degrade_tensor

    x = np.random.default_rng(scale).random((2, *shape)).astype(np.float64)
    k = _gaussian_kernel(degrade_sigma(scale)).double().numpy()
    r = len(k) // 2
    ref = x
    for axis in (1, 2):
        if x.shape[axis] > 1:
            mode = "mirror" if x.shape[axis] > r else "nearest"
            ref = correlate1d(ref, k, axis=axis, mode=mode)
    size = (max(1, round(shape[0] / scale)), max(1, round(shape[1] / scale)))
    ref = F.interpolate(torch.from_numpy(ref)[None], size=size, mode="bicubic")
    got = degrade_tensor(torch.from_numpy(x)[None], scale)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)


def test_sigma_half_response_at_lr_nyquist():
    for s in (2, 4, 8):
        sigma = degrade_sigma(s)
        f = 1.0 / (2 * s)
        assert math.isclose(math.exp(-2 * math.pi**2 * sigma**2 * f**2), 0.5, rel_tol=1e-12)


def test_removes_aliasing_frequencies():
    # a stripe pattern at the HR Nyquist frequency must not survive as LR contrast
    x = np.arange(64)
    stripes = np.tile(((x % 2) * 1.0)[None, :, None], (64, 1, 3)).astype(np.float32)
    out = degrade_image(stripes, 4)
    assert out[2:-2, 2:-2].std() < 1e-3 and abs(out.mean() - 0.5) < 1e-3
    # while a slow ramp survives
    ramp = np.tile((x / 63.0)[None, :, None], (64, 1, 3)).astype(np.float32)
    lr = degrade_image(ramp, 4)
    assert np.all(np.diff(lr[8, 2:-2, 0]) > 0)


def test_normal_maps_renormalised():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(32, 32, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.2
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    out = degrade_image((n * 0.5 + 0.5).astype(np.float32), 4, normal_map=True)
    dec = out * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(dec, axis=-1), 1.0, atol=1e-5)
    assert (dec[..., 2] >= 0).all()


def test_degrade_asset(tmp_path):
    src = make_test_asset(tmp_path / "hr.glb", size=32)
    written = degrade_asset(src, tmp_path / "lr" / "lr.glb", 4)
    hr, lr = load_asset(src), load_asset(written[0])
    for a, b in zip(hr.images, lr.images, strict=True):
        assert b.height == a.height // 4 and b.width == a.width // 4
        assert b.bit_depth >= a.bit_depth
    assert hr.mesh.v_pos.equal(lr.mesh.v_pos)


def test_degrade_asset_format(tmp_path):
    """JPEG textures: "same" compresses the LR maps again as JPEG; "png" stores the protocol's
    values losslessly (8-bit), which the benchmark uses to separate the method's error from
    the LR file's compression."""
    src = make_test_asset(tmp_path / "hr.glb", size=32, features={"jpeg"})
    hr = load_asset(src)
    jpegs = [im.index for im in hr.images if im.roles and im.mime == "image/jpeg"]
    assert jpegs
    same = load_asset(degrade_asset(src, tmp_path / "same" / "lr.glb", 4)[0])
    png = load_asset(degrade_asset(src, tmp_path / "png" / "lr.glb", 4, image_format="png")[0])
    for i in jpegs:
        a, b, c = hr.images[i], same.images[i], png.images[i]
        assert b.mime == "image/jpeg" and c.mime == "image/png"
        want = degrade_image(a.pixels, 4, normal_map="normal" in a.roles)
        assert np.abs(c.pixels - want).max() <= 0.5 / 255 + 1e-6  # 8-bit rounding only
        assert np.abs(b.pixels - want).max() > 0.5 / 255  # JPEG changes more than rounding


@pytest.mark.parametrize(("request_", "quality", "subsampled"), [
    ("jpeg:85:420", 85, True), ("jpeg:60", 60, False), ("jpeg:90:444", 90, False),
])  # fmt: skip
def test_degrade_asset_stores_jpeg_at_a_quality_and_chroma(tmp_path, request_, quality, subsampled):
    """``jpeg:Q[:420]`` writes every LR map without alpha as a JPEG with the standard tables of
    quality Q, its chroma at half resolution with 420 (as real assets often ship their maps);
    the file says so, and its pixels are the protocol's values within that compression."""
    src = make_test_asset(tmp_path / "hr.glb", size=128)
    hr = load_asset(src)
    lr = load_asset(degrade_asset(src, tmp_path / "lr" / "lr.glb", 4, image_format=request_)[0])
    want_quant = standard_quant(quality, subsampled)
    jpegs = 0
    for a, b in zip(hr.images, lr.images, strict=True):
        if a.channels == 4 or a.bit_depth > 8:  # no alpha, 8 bits only in JPEG: kept lossless
            assert b.mime == "image/png" and b.bit_depth == a.bit_depth
            continue
        jpegs += 1
        assert b.mime == "image/jpeg" and b.jpeg is not None
        assert b.jpeg.full == ((True, False, False) if subsampled else (True, True, True))
        for got, want in zip(b.jpeg.tables, want_quant.tables, strict=True):
            np.testing.assert_array_equal(got, want)
        values = degrade_image(a.pixels, 4, normal_map="normal" in a.roles)
        err = np.sqrt(np.mean((b.pixels - values) ** 2))
        luma = np.array([0.299, 0.587, 0.114], np.float32)  # JPEG's Y, kept at full resolution
        luma_err = np.sqrt(np.mean(((b.pixels - values) @ luma) ** 2))
        assert 0.5 / 255 < err < values.std()  # compressed, not another image
        assert luma_err < 0.04
    assert jpegs == 3  # normal, occlusion, emissive


def test_a_malformed_jpeg_request_is_refused(tmp_path):
    src = make_test_asset(tmp_path / "hr.glb", size=32)
    for bad in ("jpeg:", "jpeg:0", "jpeg:101", "jpeg:85:422", "jpeg:85:420:1", "jpeg:high"):
        with pytest.raises(InvalidOptions, match="bad JPEG format"):
            degrade_asset(src, tmp_path / "lr" / "lr.glb", 4, image_format=bad)
    assert not (tmp_path / "lr").exists()


@pytest.mark.parametrize("scale", [2, 3, 4, 8])
@pytest.mark.parametrize("shape", [(64, 48), (37, 29), (9, 17)])
@pytest.mark.parametrize("kernel", ["bicubic", "lanczos"])
def test_resize_kernels_against_pillow(scale, shape, kernel):
    """The antialiased kernels are Pillow's BICUBIC and LANCZOS resizes (float images), to
    float32 rounding, borders included."""
    from PIL import Image

    img = np.random.default_rng(scale).random(shape, dtype=np.float32)
    ours = degrade_image(img[..., None], scale, kernel=kernel)[..., 0]
    filt = {"bicubic": Image.Resampling.BICUBIC, "lanczos": Image.Resampling.LANCZOS}[kernel]
    size = (ours.shape[1], ours.shape[0])
    pil = np.asarray(Image.fromarray(img, mode="F").resize(size, filt)).clip(0.0, 1.0)
    np.testing.assert_allclose(ours, pil, atol=1e-6)


def test_area_is_the_mean_of_each_texels_footprint():
    """area: at a whole factor the mean of each s x s block; at any ratio each row of the
    resize matrix holds the fractions of the input texels inside the output texel, so the
    image's mean is kept exactly."""
    img = np.random.default_rng(0).random((64, 48, 2), dtype=np.float32)
    out = degrade_image(img, 4, kernel="area")
    np.testing.assert_allclose(out, img.reshape(16, 4, 12, 4, 2).mean(axis=(1, 3)), atol=1e-6)
    m = resize_matrix(10, 4, "area").numpy()  # footprints of 2.5 input texels
    np.testing.assert_allclose(m[0], [0.4, 0.4, 0.2] + [0.0] * 7)
    np.testing.assert_allclose(m[1], [0.0, 0.0, 0.2, 0.4, 0.4] + [0.0] * 5)
    np.testing.assert_allclose(m.sum(axis=0), 0.4)  # every input texel weighs the same
    odd = np.random.default_rng(1).random((33, 47, 1), dtype=np.float32)
    assert degrade_image(odd, 3, kernel="area").mean() == pytest.approx(odd.mean(), abs=1e-6)


def test_kernels_keep_less_blur_than_the_protocol():
    """A sinusoid at half the LR Nyquist frequency keeps 0.84 of its amplitude through the
    protocol's Gaussian, 0.90 through area and more through the antialiased kernels (the
    inputs their priors were not trained for are sharper)."""
    n, s = 256, 4
    x = np.arange(n)
    wave = 0.5 + 0.25 * np.cos(2 * np.pi * x / (4 * s))  # 1/(4s) cycles per HR texel
    img = np.repeat(wave[None, :, None], 32, axis=0).astype(np.float32)
    centres = ((np.arange(n // s) + 0.5) * s - 0.5)[8:-8]  # whole periods, away from borders
    phase = np.exp(-2j * np.pi * centres / (4 * s))
    amp = {}
    for k in KERNELS:
        row = degrade_image(img, s, kernel=k)[4, 8:-8, 0]
        amp[k] = abs(2 * np.mean((row - row.mean()) * phase)) / 0.25
    assert amp["gaussian"] == pytest.approx(
        math.exp(-2 * math.pi**2 * degrade_sigma(s) ** 2 / (4 * s) ** 2), abs=0.02
    )
    assert amp["area"] == pytest.approx(math.sin(math.pi / 4) / (math.pi / 4), abs=0.02)
    assert amp["gaussian"] < amp["area"] < amp["bicubic"] < amp["lanczos"] <= 1.05


def test_unknown_kernel_is_refused(tmp_path):
    with pytest.raises(InvalidOptions, match="unknown LR kernel.s. nearest"):
        degrade_image(np.zeros((8, 8, 3), np.float32), 2, kernel="nearest")
    with pytest.raises(InvalidOptions, match="unknown LR kernel.s. nearest"):  # not Lanczos
        downsample(torch.zeros(1, 3, 8, 8), 2, "nearest")
    src = make_test_asset(tmp_path / "hr.glb", size=32)
    with pytest.raises(InvalidOptions, match="use gaussian, area, bicubic, lanczos"):
        degrade_asset(src, tmp_path / "lr" / "lr.glb", 4, kernel="nearest")
    assert not (tmp_path / "lr").exists()


def test_degrade_asset_with_a_kernel(tmp_path):
    """Every map of the asset made by the kernel (normal maps renormalised as the protocol's)."""
    src = make_test_asset(tmp_path / "hr.glb", size=32)
    lr = load_asset(
        degrade_asset(src, tmp_path / "lr.glb", 4, image_format="png16", kernel="area")[0]
    )
    for a, b in zip(load_asset(src).images, lr.images, strict=True):
        want = degrade_image(a.pixels, 4, normal_map="normal" in a.roles, kernel="area")
        assert np.abs(b.pixels - want).max() <= 0.5 / 65535 + 1e-6


def test_the_runs_lr_model_holds_within_its_scope_only():
    """Outside :func:`lr_model` the run's LR model is the protocol's; within, the kernel it
    names, nested scopes restoring the outer one on the way out, errors included."""
    import torch

    x = torch.rand(1, 3, 32, 24)
    assert run_kernel() == "gaussian" and torch.equal(lr_downsample(x, 4), degrade_tensor(x, 4))
    with lr_model("area"):
        assert run_kernel() == "area"
        blocks = x.reshape(1, 3, 8, 4, 6, 4).mean(dim=(3, 5))
        assert torch.allclose(lr_downsample(x, 4), blocks, atol=1e-6)
        with pytest.raises(RuntimeError), lr_model("lanczos"):
            assert run_kernel() == "lanczos"
            raise RuntimeError
        assert run_kernel() == "area"
    assert run_kernel() == "gaussian"
    with pytest.raises(InvalidOptions, match="unknown LR kernel.s. box"), lr_model("box"):
        pass
    assert run_kernel() == "gaussian"
