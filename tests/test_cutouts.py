"""Cutouts (alphaMode MASK/BLEND): the colour under alpha 0 (black here, as exporters leave
it) must not bleed into the visible edges. Transparent texels are filled from their visible
neighbours before any filter or network, the colour the input had there comes back after,
and the prior's self-check scores the visible texels only."""

from __future__ import annotations

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_quad_asset, save_asset
from pbrsr_core.degrade import degrade_image
from pbrsr_core.maps import image_cutout
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.direct import bicubic_map, fill_transparent, upscale_map


def leaves(size: int = 128) -> np.ndarray:
    """RGBA: textured discs (alpha 1) on black, fully transparent (alpha 0) background."""
    y, x = np.mgrid[0:size, 0:size] / size
    rgb = np.stack([0.3 + 0.5 * x, 0.6 + 0.3 * np.sin(12 * y), 0.2 + 0.3 * np.cos(9 * x * y)], -1)
    alpha = np.zeros((size, size))
    for cx, cy, r in [(0.3, 0.3, 0.2), (0.7, 0.35, 0.15), (0.5, 0.72, 0.22)]:
        alpha[(x - cx) ** 2 + (y - cy) ** 2 < r * r] = 1.0
    rgb = np.clip(rgb, 0.0, 1.0)
    rgb[alpha == 0] = 0.0
    return np.concatenate([rgb, alpha[..., None]], -1).astype(np.float32)


def _visible_psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    seen = gt[..., 3] > 0.5
    err = ((pred[..., :3] - gt[..., :3]) ** 2)[seen].mean()
    return float(10 * np.log10(1.0 / err))


def test_fill_keeps_visible_texels_and_fills_the_rest_from_them():
    a = leaves(64)
    seen = a[..., 3] > 0
    filled = fill_transparent(a[..., :3], seen)
    assert np.array_equal(filled[seen], a[..., :3][seen])
    visible = a[..., :3][seen]
    # averages of visible colours only: within their range per channel, no black left
    assert (filled[~seen] >= visible.min(0) - 1e-5).all()
    assert (filled[~seen] <= visible.max(0) + 1e-5).all()
    assert filled[~seen].sum(-1).min() > 0.3


@pytest.mark.parametrize("prior", [None, "pbr-upconv7"])
def test_visible_texels_at_or_above_plain_bicubic(prior):
    gt = leaves(128)
    lr = degrade_image(gt, 4)
    plain = bicubic_map(lr, "base_color", 4)  # the smear: black pulled into the edges
    if prior is None:
        mine = bicubic_map(lr, "base_color", 4, cutout=0.5)  # a MASK material's cutoff
    else:
        mine = upscale_map(load_prior(prior, "cpu"), lr, "base_color", 4, cutout=0.5)
    assert _visible_psnr(mine, gt) >= _visible_psnr(plain, gt) + 1.0
    # under alpha 0 the result keeps what the input had there
    hidden = mine[..., 3] <= 0.5 / 255
    assert hidden.any() and np.allclose(mine[hidden, :3], plain[hidden, :3], atol=1e-6)


def _cutout_asset(tmp_path, mode="MASK"):
    src = make_quad_asset(tmp_path / "q.glb", size=32)
    asset = load_asset(src)
    asset.document["materials"][0]["alphaMode"] = mode
    base = asset.materials[0].base_color.image
    out = tmp_path / f"leaves-{mode}.glb"
    save_asset(asset, out, new_images={base: leaves(128)})
    return out, base


def test_the_pipeline_treats_a_mask_material_as_a_cutout(tmp_path):
    gt_path, base = _cutout_asset(tmp_path)
    assert image_cutout(load_asset(gt_path), base) == 0.5  # MASK: its alphaCutoff
    blend, _ = _cutout_asset(tmp_path, "BLEND")
    assert 0 < image_cutout(load_asset(blend), base) < 0.01  # BLEND: alpha 0 only
    opaque, _ = _cutout_asset(tmp_path, "OPAQUE")
    assert image_cutout(load_asset(opaque), base) is None  # alpha unused: its colour is seen
    from pbrsr_core.degrade import degrade_asset

    lr_path = degrade_asset(gt_path, tmp_path / "lr" / gt_path.name, 4)[0]
    gt = load_asset(gt_path).images[base].pixels
    lr = load_asset(lr_path).images[base].pixels
    plain = _visible_psnr(bicubic_map(lr, "base_color", 4), gt)
    for method, preset in (("bicubic", "fast"), ("direct", "fast"), ("pbrsr", "fast")):
        out = tmp_path / f"{method}-{preset}"
        options = UpscaleOptions(scale=4, method=method, preset=preset, prior="pbr-upconv7")
        report = upscale_asset(lr_path, out, options)
        got = load_asset(out / gt_path.name).images[base].pixels
        assert _visible_psnr(got, gt) >= plain, method
        if method == "pbrsr":  # the self-check compared visible texels
            check = next(c for c in report["prior_check"] if c["index"] == base)
            assert check["texels"] < (lr.shape[0] * lr.shape[1]) * 0.7
