"""Metrics by the paper's protocol: identities, known PSNR values, masks, and the evaluator."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from pbrsr_core.asset import load_asset, make_demo_asset
from pbrsr_core.metrics import (
    RenderEvaluator,
    eval_cameras,
    images_for,
    map_metrics,
    psnr,
    ssim,
    stored_like,
)
from pbrsr_core.scene import procedural_light


def test_psnr_known_values_and_mask():
    a = np.zeros((4, 4, 1), np.float32)
    b = a + 0.1
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)  # mse 0.01
    assert psnr(a, a) == math.inf
    m = np.zeros((4, 4), bool)
    m[0, 0] = True
    c = a.copy()
    c[1:, :] = 1.0  # errors outside the mask do not count
    assert psnr(a, c, m) == math.inf


def test_ssim_identity_and_order():
    rng = np.random.default_rng(0)
    x = rng.random((32, 32, 3)).astype(np.float32)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-6)
    small = np.clip(x + 0.02 * rng.standard_normal(x.shape), 0, 1)
    big = np.clip(x + 0.2 * rng.standard_normal(x.shape), 0, 1)
    assert 1.0 > ssim(small, x) > ssim(big, x)


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    return make_demo_asset(tmp_path_factory.mktemp("m") / "demo.glb", size=32)


def _perturbed(asset, delta: float):
    images = [
        dataclasses.replace(im, pixels=np.clip(im.pixels + delta, 0, 1)) if im.roles else im
        for im in asset.images
    ]
    return dataclasses.replace(asset, images=images)


def test_map_and_render_metrics(demo: Path):
    gt = load_asset(demo)
    same = map_metrics(gt, gt)
    assert {"maps.albedo.psnr", "maps.roughness.psnr", "maps.normal.psnr"} <= set(same)
    assert all(v >= 99.0 for k, v in same.items() if k.endswith("psnr"))
    assert all(v == pytest.approx(1.0) for k, v in same.items() if k.endswith("ssim"))
    ev = RenderEvaluator(gt, cameras=eval_cameras(64, 6), lights=[procedural_light()])
    assert ev(gt)["render.psnr"] == math.inf
    off1, off2 = _perturbed(gt, 0.02), _perturbed(gt, 0.08)
    m1, m2 = map_metrics(off1, gt), map_metrics(off2, gt)
    assert m1["maps.albedo.psnr"] > m2["maps.albedo.psnr"]
    r1, r2 = ev(off1)["render.psnr"], ev(off2)["render.psnr"]
    assert math.isfinite(r1) and r1 > r2


def test_render_psnr_per_light_pools_to_the_whole(demo: Path):
    """With several lights each has its own render PSNR; the pooled one is over all their
    pixels (the same views: the mean of their MSEs). One light gives the pooled key only."""
    from pbrsr_core.scene import rotated_procedural_light

    gt = load_asset(demo)
    off = _perturbed(gt, 0.05)
    cams = eval_cameras(48, 4)
    lights = [procedural_light(), rotated_procedural_light(120.0), procedural_light()]
    res = RenderEvaluator(gt, cameras=cams, lights=lights)(off)
    keys = ["render.procedural.psnr", "render.procedural-rot120.psnr", "render.procedural#2.psnr"]
    assert [k for k in res if k.startswith("render.")] == ["render.psnr", *keys]
    assert res[keys[0]] == res[keys[2]] != res[keys[1]]
    mse = [10 ** (-res[k] / 10) for k in keys]
    assert res["render.psnr"] == pytest.approx(-10 * math.log10(sum(mse) / 3), abs=1e-9)
    alone = RenderEvaluator(gt, cameras=cams, lights=lights[1:2])(off)
    assert alone == {"render.psnr": pytest.approx(res[keys[1]], abs=1e-9)}


def test_eval_cameras_subset():
    assert len(eval_cameras(32)) == 240
    assert len(eval_cameras(32, 24)) == 24


def _with_metal_mask(asset):
    """``asset`` with a crisp metallic mask (blocks of 0 and 1) in its ORM map's blue channel:
    detail that 4:2:0 storage keeps at half resolution."""
    orm = images_for(asset, "metallic_roughness")[0]
    px = asset.images[orm].pixels.copy()
    yy, xx = np.mgrid[: px.shape[0], : px.shape[1]]
    px[..., 2] = ((yy // 3 + xx // 5) % 2).astype(np.float32)
    images = list(asset.images)
    images[orm] = dataclasses.replace(images[orm], pixels=px)
    return dataclasses.replace(asset, images=images), orm


def test_stored_like_stores_the_maps_the_ground_truth_keeps_as_jpeg(demo: Path, tmp_path: Path):
    """Each map whose ground truth is a JPEG file is stored with that file's tables and chroma
    sampling; against a 4:2:0 ground truth the texture it was made from (lossless, crisp
    chroma) scores higher so stored than as it is, and a PNG ground truth changes nothing."""
    from pbrsr_core.asset.gltf_write import save_asset
    from pbrsr_core.asset.jpeg import stored_as

    source, orm = _with_metal_mask(load_asset(demo))
    every = {im.index: im.pixels for im in source.images}
    save_asset(source, tmp_path / "gt.glb", every, image_format="jpeg:90:420")
    gt = load_asset(tmp_path / "gt.glb")
    assert all(im.jpeg is not None and im.jpeg.full == (True, False, False) for im in gt.images)
    stored = stored_like(source, gt)
    for mine, ref, made in zip(source.images, gt.images, stored.images, strict=True):
        assert np.array_equal(made.pixels, stored_as(mine.pixels, ref.jpeg, deblocked=False))
    assert not np.array_equal(stored.images[orm].pixels, source.images[orm].pixels)
    as_is, so = map_metrics(source, gt), map_metrics(stored, gt)
    assert so["maps.metallic.psnr"] > as_is["maps.metallic.psnr"] + 3.0
    ev = RenderEvaluator(gt, cameras=eval_cameras(48, 4), lights=[procedural_light()])
    assert ev(stored)["render.psnr"] > ev(source)["render.psnr"]
    png = load_asset(demo)
    kept = stored_like(source, png)
    assert all(a.pixels is b.pixels for a, b in zip(kept.images, source.images, strict=True))
