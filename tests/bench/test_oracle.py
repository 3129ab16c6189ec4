"""`pbrsr bench oracle` on a tiny procedural asset (no shared assets)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from pbrsr_bench.oracle import markdown_table, run, with_gt_maps
from pbrsr_core.asset import load_asset, make_demo_asset
from pbrsr_core.metrics import MAP_CHANNELS, images_for


def test_bench_oracle_small_run(tmp_path: Path):
    said: list[str] = []
    rows = run(
        out_dir=tmp_path / "out",
        eval_res=64,
        eval_views=6,
        procedural_size=64,
        shared=tmp_path / "no-shared-assets",
        log=said.append,
    )
    assert any("not present" in s for s in said)
    by_asset = {r["asset"]: r for r in rows}
    assert list(by_asset) == ["procedural", "procedural-cutout"]
    row = by_asset["procedural"]
    assert 5.0 < row["bicubic"] < 60.0
    assert set(row["maps"]) <= set(MAP_CHANNELS) and "albedo" in row["maps"]
    assert all(math.isfinite(v) for v in row["maps"].values())
    assert row["maps"]["albedo"] > row["bicubic"]  # the true albedo renders closer
    assert row["all"] == math.inf  # every map from the ground truth: the ground truth's render
    saved = json.loads((tmp_path / "out" / "oracle.json").read_text())
    assert saved["rows"][0]["maps"] == row["maps"]
    assert (tmp_path / "out" / "oracle.png").stat().st_size > 0
    table = markdown_table(rows)
    assert "| procedural |" in table and "GT albedo" in table


def test_with_gt_maps_replaces_only_the_named_channels(tmp_path: Path):
    gt = load_asset(make_demo_asset(tmp_path / "demo.glb", size=16))
    rng = np.random.default_rng(0)
    noisy = dataclasses.replace(
        gt,
        images=[
            dataclasses.replace(im, pixels=rng.random(im.pixels.shape, dtype=np.float32))
            for im in gt.images
        ],
    )
    assert with_gt_maps(noisy, gt, []).images[0].pixels is noisy.images[0].pixels
    out = with_gt_maps(noisy, gt, ["roughness"])
    (mr,) = images_for(gt, "metallic_roughness")
    for im, before in zip(out.images, noisy.images, strict=True):
        if im.index == mr:
            np.testing.assert_array_equal(im.pixels[..., 1], gt.images[mr].pixels[..., 1])
            np.testing.assert_array_equal(im.pixels[..., 2], before.pixels[..., 2])
        else:
            np.testing.assert_array_equal(im.pixels, before.pixels)
