"""Detail crops (pbrsr_core.crops): the region is where the LR map has detail, the LR and HR
crops show the same texels, and the index describes them."""

from __future__ import annotations

import json

import numpy as np

from pbrsr_core.asset import load_asset, make_test_asset, read_image
from pbrsr_core.crops import (
    CROPS_INDEX,
    crop_side,
    detail_origin,
    read_crop_index,
    write_map_crops,
)
from pbrsr_core.maps import map_file_stem


def test_region_is_the_detailed_patch_not_the_corner():
    rng = np.random.default_rng(0)
    px = np.full((96, 128, 3), 0.5, np.float32)
    px[60:76, 88:104] = rng.random((16, 16, 3))  # the only detail
    x, y = detail_origin(px, 16)
    assert (x, y) == (88, 60)
    # a window larger than the patch still covers all of it
    x, y = detail_origin(px, 32)
    assert x <= 88 and x + 32 >= 104 and y <= 60 and y + 32 >= 76


def test_a_large_map_is_searched_on_a_sampled_grid_and_still_finds_the_detail():
    rng = np.random.default_rng(2)
    px = np.full((2048, 2048, 3), 0.5, np.float32)  # 4 Mtexels: sampled every 2nd texel
    px[1203:1243, 517:557] = rng.random((40, 40, 3))
    # the one window on the 8-texel grid inside the patch
    assert detail_origin(px, 32) == (520, 1208)


def test_alpha_is_not_detail_and_a_flat_map_gives_the_centre():
    rng = np.random.default_rng(1)
    px = np.full((64, 64, 4), 0.25, np.float32)
    px[:16, :16, 3] = rng.random((16, 16))  # noisy alpha in a corner
    px[40:56, 40:56, 1] = rng.random((16, 16))  # colour detail elsewhere
    assert detail_origin(px, 16) == (40, 40)
    assert detail_origin(np.zeros((64, 64, 1), np.float32), 16) == (24, 24)


def test_crop_side_keeps_hr_crops_at_128_and_fits_small_maps():
    assert crop_side((512, 512, 3), 2) == 64
    assert crop_side((512, 512, 3), 4) == 32
    assert crop_side((512, 512, 3), 8) == 16
    assert crop_side((10, 40, 3), 4) == 10


def test_lr_and_hr_crops_show_the_same_region(tmp_path):
    asset = load_asset(make_test_asset(tmp_path / "a.glb", size=64))
    scale = 4
    hr = {img.index: np.repeat(np.repeat(img.pixels, scale, 0), scale, 1) for img in asset.images}
    entries = write_map_crops(asset, hr, tmp_path / "crops")
    assert read_crop_index(tmp_path / "crops") == entries
    assert json.loads((tmp_path / "crops" / CROPS_INDEX).read_text()) == entries
    assert [e["map"] for e in entries] == [map_file_stem(img) for img in asset.images]
    for img, entry in zip(asset.images, entries, strict=True):
        x, y, w, h = entry["lr_region"]
        side = min(32, img.width, img.height)  # 128 HR texels at x4, in the smaller maps
        assert (w, h) == (side, side) and entry["scale"] == scale
        assert entry["hr_region"] == [x * scale, y * scale, w * scale, h * scale]
        assert entry["lr_size"] == [img.width, img.height]
        assert entry["hr_size"] == [img.width * scale, img.height * scale]
        lr_px, _, _ = read_image(tmp_path / "crops" / entry["lr"], entry["lr"])
        hr_px, _, _ = read_image(tmp_path / "crops" / entry["hr"], entry["hr"])
        assert lr_px.shape[:2] == (side, side) and hr_px.shape[:2] == (4 * side, 4 * side)
        channels = lr_px.shape[2]
        assert channels in (1, 3)
        expected = img.pixels[y : y + h, x : x + w, :channels]
        assert np.abs(lr_px - expected).max() <= 0.5 / 255 + 1e-6
        # nearest-upscaled input: the HR crop is the LR crop's texels repeated
        assert np.array_equal(hr_px, np.repeat(np.repeat(lr_px, scale, 0), scale, 1))


def test_no_index_reads_as_no_crops(tmp_path):
    assert read_crop_index(tmp_path) == []
