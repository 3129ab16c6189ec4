"""Cutouts (alphaMode MASK/BLEND): the colour under alpha 0 (black here, as exporters leave
it) must not bleed into the visible edges. Transparent texels are filled from their visible
neighbours before any filter or network, the colour the input had there comes back after,
and the prior's self-check scores the visible texels only."""

from __future__ import annotations

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_cutout_asset, make_quad_asset, save_asset
from pbrsr_core.asset.procedural import leaf_maps
from pbrsr_core.degrade import degrade_asset, degrade_image
from pbrsr_core.maps import image_cutout
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.direct import bicubic_map, fill_transparent, filled_cutout, upscale_map


def leaves(size: int = 128) -> np.ndarray:
    """RGBA: leaves (alpha 1) on a transparent background with black under it."""
    return leaf_maps(size)["base_color"]


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


def test_a_cutout_over_black_is_unpremultiplied_before_the_fill():
    """Black under alpha 0 means premultiplied colour: seen texels are divided by their alpha
    (a half-covered edge texel of 0.3 at alpha 0.6 is 0.5 of the leaf's colour), hidden ones
    are filled from them; a cutout whose hidden texels carry colour is left as it was."""
    rgba = np.zeros((4, 4, 4), np.float32)
    rgba[:, :2] = (0.4, 0.2, 0.1, 1.0)
    rgba[:, 2] = (0.3, 0.15, 0.075, 0.6)  # the edge, darkened by its coverage
    filled = filled_cutout(rgba, seen_from=0.5)
    assert np.allclose(filled[:, 2, :3], (0.5, 0.25, 0.125))
    assert np.allclose(filled[..., 3], rgba[..., 3])
    assert np.allclose(filled[:, :2], rgba[:, :2])
    assert (filled[:, 3, :3].sum(-1) > 0.5).all()  # no black left where the renderer discards
    bled = rgba.copy()
    bled[:, 3, :3] = (0.4, 0.2, 0.1)  # colour under alpha 0: straight alpha, kept
    assert np.allclose(filled_cutout(bled, seen_from=0.5)[:, 2], rgba[:, 2])


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


def test_the_foliage_asset_keeps_its_visible_texels_at_or_above_bicubic(tmp_path):
    """The procedural foliage cards (three crossing double-sided quads, MASK) through every
    method: visible base-colour texels at or above a plain bicubic resize's."""
    gt_path = make_cutout_asset(tmp_path / "foliage.glb", size=128)
    base = load_asset(gt_path).materials[0].base_color.image
    assert image_cutout(load_asset(gt_path), base) == 0.5
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
