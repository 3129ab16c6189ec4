"""The LR protocol: shapes, constants preserved, normals unit, assets degraded end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_test_asset
from pbrsr_core.degrade import degrade_asset, degrade_image, degrade_sigma


@pytest.mark.parametrize("scale", [2, 4, 8])
@pytest.mark.parametrize("shape", [(64, 48, 3), (30, 17, 4), (5, 3, 1)])
def test_shapes_and_constant(scale, shape):
    img = np.full(shape, 0.3125, np.float32)
    out = degrade_image(img, scale)
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
