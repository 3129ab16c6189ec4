"""Which maps' errors reach the renders (render_reach.py): the margins against full renders of
each swapped asset, a map the renders cannot show, and what the pipeline does with it."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pbrsr_core.asset import load_asset, make_quad_asset, make_test_asset
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.initial_maps import prior_channels
from pbrsr_core.maps import upscalable_images
from pbrsr_core.optim import presets
from pbrsr_core.optim.groups import map_groups
from pbrsr_core.optim.presets import BALANCED as PLAIN
from pbrsr_core.optim.presets import PAPER
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.direct import bicubic_map
from pbrsr_core.render import raster
from pbrsr_core.render_reach import reach_cameras, render_reach, round_trip
from pbrsr_core.scene import (
    asset_textures,
    make_scene,
    procedural_light,
    render_views,
    rotated_procedural_light,
)

CPU = torch.device("cpu")
BALANCED = PLAIN.with_(reach_db=25.0)
"""balanced with the measurement on (no preset turns it on: docs/METHOD.md, "Maps the renders
do not show")."""


def _rng_map(seed: int, size: int = 32, lo: float = 0.2, span: float = 0.6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(rng.random((size, size, 3)) * span + lo, 0, 1).astype(np.float32)


def _all_channels(asset):
    return {img.index: prior_channels(img, BALANCED) for img in upscalable_images(asset)}


def _full_render_error(asset, swap: dict[int, list[int]]) -> float:
    """The squared render error of the asset with ``swap``'s channels from their round trips,
    rendered in full (every texture sampled again under every light)."""
    from pbrsr_core.maps import encoded_to_param, kind_of

    scene = make_scene(asset, CPU)
    cams = reach_cameras()
    gbs = [raster.rasterize(scene.mesh, c) for c in cams]
    own = asset_textures(asset, CPU)
    mixed = dict(own)
    for i, chans in swap.items():
        img = asset.images[i]
        trip = encoded_to_param(torch.from_numpy(round_trip(img, asset)), kind_of(img.roles))
        t = own[i].clone()
        t[..., chans] = trip[..., chans]
        mixed[i] = t
    total = 0.0
    for light in (procedural_light(), rotated_procedural_light(150.0)):
        a, masks = render_views(scene, own, cams, light, gbuffers=gbs)
        b, _ = render_views(scene, mixed, cams, light, gbuffers=gbs)
        for x, y, m in zip(a, b, masks, strict=True):
            total += float(((x - y)[m] ** 2).double().sum())
    return total


def test_margins_equal_those_of_full_renders_of_each_swapped_asset(tmp_path: Path):
    """Two materials, a shared ORM image, occlusion, emissive: each margin is 10 log10 of the
    error with every map swapped over the error with that map alone, as full renders of the
    swapped assets give them (the measurement samples each texture once per view)."""
    asset = load_asset(make_test_asset(tmp_path / "t.glb", size=32))
    reach = render_reach(asset, _all_channels(asset), BALANCED, CPU)
    assert {r["map"] for r in reach} >= {"base_color", "normal", "roughness", "metallic"}
    every: dict[int, list[int]] = {}
    for img in upscalable_images(asset):
        n = 3 if img.pixels.shape[2] >= 3 else 1
        for g in map_groups(set(img.roles), n, BALANCED):
            every.setdefault(img.index, []).extend(g.channels)
    total = _full_render_error(asset, every)
    assert total > 0
    for r in reach:
        own = _full_render_error(asset, {r["index"]: r["channels"]})
        want = None if own == 0 else 10 * math.log10(total / own)
        got = r["margin_db"]
        assert (got is None) == (want is None), r
        if want is not None:
            assert got == pytest.approx(want, abs=0.011), r
        assert r["unseen"] == (want is None or want >= BALANCED.reach_db), r


def test_a_map_the_renders_cannot_show_is_unseen_and_the_rest_are_not(tmp_path: Path):
    """metallicFactor 0 multiplies the metallic channel away: its error is none (margin None,
    unseen). The base colour and the roughness a viewer sees are measured and kept."""
    mr = _rng_map(2)
    src = make_quad_asset(
        tmp_path / "q.gltf",
        {"base_color": _rng_map(1), "metallic_roughness": mr},
        factors={"metallicFactor": 0.0},
    )
    asset = load_asset(src)
    reach = {r["map"]: r for r in render_reach(asset, _all_channels(asset), BALANCED, CPU)}
    assert reach["metallic"]["margin_db"] is None and reach["metallic"]["unseen"]
    assert not reach["base_color"]["unseen"] and reach["base_color"]["margin_db"] < 10
    assert not reach["roughness"]["unseen"]
    # the margin is the asset's: the same whichever maps the prior would run on
    only_mr = {i: c for i, c in _all_channels(asset).items() if "metallic_roughness" in
               asset.images[i].roles}  # fmt: skip
    again = {r["map"]: r for r in render_reach(asset, only_mr, BALANCED, CPU)}
    assert set(again) == {"roughness", "metallic"}
    assert again["roughness"]["margin_db"] == reach["roughness"]["margin_db"]
    # not measured: no threshold (every preset), nothing the prior would run on, or maps that
    # change no render
    for config in (PAPER, PLAIN):
        assert render_reach(asset, _all_channels(asset), config, CPU) == []
    assert render_reach(asset, {}, BALANCED, CPU) == []
    flat = dataclasses.replace(
        asset, images=[dataclasses.replace(im, pixels=np.full_like(im.pixels, 0.5))
                       for im in asset.images]
    )  # fmt: skip
    assert render_reach(flat, _all_channels(flat), BALANCED, CPU) == []
    with pytest.raises(InvalidOptions, match="reach_db"):
        BALANCED.with_(reach_db=0.0)


@pytest.mark.parametrize("method", ["direct", "pbrsr"])
def test_an_unseen_map_gets_bicubics_upscale_and_says_so(tmp_path, monkeypatch, method: str):
    """direct and balanced with the measurement on: the metallic channel the factor hides
    comes out as bicubic's, named ``bicubic (unseen)``, and the report lists the measurement;
    the roughness channel of the same image still gets the prior. Off (the presets as they
    ship), nothing is measured."""
    src = make_quad_asset(
        tmp_path / "q.gltf",
        {"base_color": _rng_map(1), "metallic_roughness": _rng_map(2, lo=0.1, span=0.8)},
        factors={"metallicFactor": 0.0},
    )
    plain = upscale_asset(src, tmp_path / "plain", UpscaleOptions(method=method, scale=2))
    assert "render_reach" not in plain and "render_reach" not in plain["timings"]
    monkeypatch.setattr(presets, "BALANCED", BALANCED)  # direct takes balanced's settings
    monkeypatch.setitem(presets.PRESETS, "balanced", BALANCED)
    report = upscale_asset(src, tmp_path / "out", UpscaleOptions(method=method, scale=2))
    assert "render_reach" in report["timings"]
    reach = {r["map"]: r for r in report["render_reach"]}
    assert reach["metallic"]["unseen"] and not reach["roughness"]["unseen"]
    row = next(i for i in report["images"] if i["label"] == "metallic_roughness")
    assert row["made_by"][2] == "bicubic (unseen)"
    assert not row["made_by"][1].startswith("bicubic"), row["made_by"]
    lr = load_asset(src).images[row["index"]].pixels
    hr = load_asset(tmp_path / "out" / "q.gltf").images[row["index"]].pixels
    want = bicubic_map(lr, "data", 2)[..., 2]
    assert np.abs(hr[..., 2] - want).max() <= 0.6 / 255
