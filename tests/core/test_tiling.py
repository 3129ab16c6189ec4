"""Seamless tiling: a map whose sampler repeats (or mirrors) is upscaled with wrapped (or
mirrored) context at its edges, by bicubic and the prior alike, and its seam (the step across
the wrap edge against the steps inside) stays as small as inside; the report gives it."""

from __future__ import annotations

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_quad_asset, save_asset
from pbrsr_core.asset.model import CLAMP_TO_EDGE, MIRRORED_REPEAT, REPEAT
from pbrsr_core.maps import image_wrap
from pbrsr_core.metrics import seam_ratio
from pbrsr_core.optim import presets
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.direct import bicubic_map, upscale_map


def tile(size: int = 32) -> np.ndarray:
    """A colourful texture that repeats seamlessly: whole periods of sines across it."""
    y, x = np.mgrid[0:size, 0:size] / size
    chans = [
        0.5 + 0.4 * np.sin(2 * np.pi * (3 * x + 2 * y)),
        0.5 + 0.4 * np.cos(2 * np.pi * (5 * x)) * np.sin(2 * np.pi * 4 * y),
        0.5 + 0.3 * np.sin(2 * np.pi * (x - 3 * y)),
    ]
    return np.stack(chans, -1).astype(np.float32)


def test_seam_ratio_sees_a_seam():
    t = tile()
    assert max(seam_ratio(t)) < 1.5
    shifted = np.roll(t, 5, axis=1)[:, :-5]  # cut: the repeat no longer lines up
    assert seam_ratio(shifted)[0] > 2


@pytest.mark.parametrize("prior", [None, "pbr-upconv7"])
def test_a_repeating_map_upscales_without_a_seam(prior):
    lr = tile(32)

    def up(wrap):
        if prior is None:
            return bicubic_map(lr, "base_color", 4, wrap)
        return upscale_map(load_prior(prior, "cpu"), lr, "base_color", 4, wrap=wrap)

    wrapped, clamped = up(("repeat", "repeat")), up(None)
    assert wrapped.shape == clamped.shape == (128, 128, 3)
    assert max(seam_ratio(wrapped)) <= 1.25, seam_ratio(wrapped)
    assert min(seam_ratio(clamped)) > max(seam_ratio(wrapped))
    # inside, away from the edges, the context changes nothing that matters
    mid = slice(32, 96)
    assert np.abs(wrapped[mid, mid] - clamped[mid, mid]).max() < 0.02


def test_mirrored_context_keeps_the_shape_and_one_axis_only():
    lr = tile(16)
    out = bicubic_map(lr, "base_color", 2, ("mirror", None))
    assert out.shape == (32, 32, 3) and np.isfinite(out).all()
    only_x = bicubic_map(lr, "base_color", 2, ("repeat", None))
    assert seam_ratio(only_x)[0] < seam_ratio(bicubic_map(lr, "base_color", 2))[0]


def _asset_with_sampler(tmp_path, wrap_s, wrap_t, repeats=2.0):
    """The quad with its base colour a seamless tile, the samplers given, and the texture
    repeated ``repeats`` times across the quad (KHR_texture_transform; 1: UVs in [0, 1])."""
    src = make_quad_asset(tmp_path / "q.glb", size=32)
    asset = load_asset(src)
    doc = asset.document
    doc["samplers"] = [{"wrapS": wrap_s, "wrapT": wrap_t}]
    for t in doc["textures"]:
        t["sampler"] = 0
    if repeats != 1.0:
        info = doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]
        info["extensions"] = {"KHR_texture_transform": {"scale": [repeats, repeats]}}
        doc.setdefault("extensionsUsed", []).append("KHR_texture_transform")
    base = asset.materials[0].base_color.image
    out = tmp_path / f"tiled-{wrap_s}-{wrap_t}-{repeats}.glb"
    save_asset(asset, out, new_images={base: tile(32)})
    return out, base


def test_the_samplers_say_how_an_image_wraps(tmp_path):
    for (s, t), repeats, want in [
        ((REPEAT, REPEAT), 2.0, ("repeat", "repeat")),
        ((MIRRORED_REPEAT, CLAMP_TO_EDGE), 2.0, ("mirror", None)),
        ((CLAMP_TO_EDGE, CLAMP_TO_EDGE), 2.0, None),
        ((REPEAT, REPEAT), 1.0, None),  # repeats by its sampler, but the mesh never shows it
    ]:
        path, base = _asset_with_sampler(tmp_path, s, t, repeats)
        assert image_wrap(load_asset(path), base) == want


@pytest.mark.parametrize("method", ["bicubic", "direct", "pbrsr"])
def test_the_report_gives_a_tiling_maps_seam(tmp_path, method):
    """Bicubic, the prior and the optimiser (its TV wraps around a repeating map) keep a
    tiling map's seam as small as inside it."""
    path, base = _asset_with_sampler(tmp_path, REPEAT, REPEAT)
    options = UpscaleOptions(scale=4, method=method, prior="pbr-upconv7")
    config = presets.FAST.with_(iterations=8, check_prior=(), max_prior_scale=None)
    report = upscale_asset(path, tmp_path / method, options, config=config)
    entry = next(e for e in report["images"] if e["index"] == base)
    assert entry["wrap"] == ["repeat", "repeat"]
    lr, hr = entry["seam"]["lr"], entry["seam"]["hr"]
    assert max(hr) <= max(1.25, 1.1 * max(lr)), entry["seam"]
    clamped, _ = _asset_with_sampler(tmp_path, CLAMP_TO_EDGE, CLAMP_TO_EDGE)
    report = upscale_asset(clamped, tmp_path / f"{method}-clamped", options, config=config)
    assert "seam" not in next(e for e in report["images"] if e["index"] == base)


def test_eval_reports_the_seam_against_the_ground_truths(tmp_path):
    from pbrsr_core.degrade import degrade_asset
    from pbrsr_core.metrics import evaluate

    gt, base = _asset_with_sampler(tmp_path, REPEAT, REPEAT)
    lr = degrade_asset(gt, tmp_path / "lr" / gt.name, 2)[0]
    upscale_asset(lr, tmp_path / "up", UpscaleOptions(scale=2, method="bicubic"))
    res = evaluate(tmp_path / "up" / gt.name, gt, resolution=32, num_views=2)
    assert {f"seam.{base}.x", f"seam.{base}.y"} <= res.keys()
    assert res[f"seam.{base}.x"] < 1.5 and res[f"seam.{base}.y"] < 1.5
