"""``closest:A|B`` in `pbrsr bench upscale`: per map entry the run closest to the ground truth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from pbrsr_bench.closest import check, closest_maps, parts
from pbrsr_bench.upscale import run
from pbrsr_core.asset import load_asset, make_test_asset
from pbrsr_core.maps import kind_of
from pbrsr_core.metrics import map_metrics


def _noisy(asset, index: int, channels: list[int], sigma: float, seed: int):
    """``asset`` with Gaussian noise of ``sigma`` in ``channels`` of image ``index``."""
    rng = np.random.default_rng(seed)
    images = []
    for im in asset.images:
        if im.index == index:
            px = im.pixels.astype(np.float32).copy()
            for c in channels:
                px[..., c] = np.clip(px[..., c] + rng.normal(0, sigma, px.shape[:2]), 0, 1)
            im = dataclasses.replace(im, pixels=px)
        images.append(im)
    return dataclasses.replace(asset, images=images)


def test_each_data_channel_comes_from_the_output_closest_in_it(tmp_path: Path):
    """Two outputs, each with one channel of the metallic-roughness image spoilt: the bound
    takes each channel from the other, so that image matches the truth exactly. A colour map
    spoilt in one channel in one output and in all three in the other goes whole to the
    first. Images that share a name keep a pick each."""
    gt = load_asset(make_test_asset(tmp_path / "gt.glb", size=32))
    data = next(im.index for im in gt.images if kind_of(im.roles) == "data")
    colour = next(im.index for im in gt.images if "base_color" in im.roles)
    a = _noisy(_noisy(gt, data, [1], 0.2, 1), colour, [0], 0.1, 2)
    b = _noisy(_noisy(gt, data, [2], 0.2, 3), colour, [0, 1, 2], 0.1, 4)
    best, picks = closest_maps({"a": a, "b": b}, gt)
    name = {im.index: f"{im.index}:{im.name}" for im in gt.images}
    assert picks[name[data]][1:3] == ["b", "a"]
    assert picks[name[colour]] == ["a"]
    same = dataclasses.replace(gt, images=[dataclasses.replace(i, name="map") for i in gt.images])
    _, named = closest_maps({"a": a, "b": b}, same)  # images sharing a name keep their picks
    assert named == {k.split(":")[0] + ":map": v for k, v in picks.items()}
    np.testing.assert_array_equal(
        best.images[data].pixels[..., 1:3], gt.images[data].pixels[..., 1:3]
    )
    np.testing.assert_array_equal(best.images[colour].pixels, a.images[colour].pixels)
    scores = {k: map_metrics(x, gt) for k, x in {"a": a, "b": b, "best": best}.items()}
    for key in ("maps.roughness.psnr", "maps.metallic.psnr", "maps.albedo.psnr"):
        assert scores["best"][key] >= max(scores["a"][key], scores["b"][key]), key
    assert scores["best"]["maps.roughness.psnr"] > scores["a"]["maps.roughness.psnr"] + 10


def test_closest_must_pick_among_methods_listed_before_it():
    assert parts("direct") is None
    assert parts("closest:direct|direct@waifu2x-photo") == ("direct", "direct@waifu2x-photo")
    check(("bicubic", "direct", "closest:bicubic|direct"))
    with pytest.raises(ValueError, match="must be listed before it"):
        check(("bicubic", "closest:bicubic|direct", "direct"))
    with pytest.raises(ValueError, match="two or more"):
        check(("bicubic", "closest:bicubic"))
    with pytest.raises(ValueError, match="must be listed before it"):
        check(("bicubic", "direct", "closest:bicubic|closest:bicubic|direct"))


def test_the_bench_scores_the_bound_beside_the_runs_it_picks_from(tmp_path: Path):
    rows = run(
        out_dir=tmp_path / "out",
        methods=("bicubic", "fast", "closest:bicubic|fast"),
        prior="bicubic",
        eval_res=64,
        eval_views=4,
        procedural_size=64,
        include_shared=False,
        log=lambda _: None,
    )
    by = {(r["asset"], r["method"]): r for r in rows}
    for asset in ("procedural", "procedural-cutout"):
        bic, fast = by[asset, "bicubic"], by[asset, "fast"]
        bound = by[asset, "closest:bicubic|fast"]
        assert bound["run_s"] == pytest.approx(bic["run_s"] + fast["run_s"], abs=0.02)
        assert bound["peak_rss_mib"] == max(bic["peak_rss_mib"], fast["peak_rss_mib"])
        assert all(set(p) <= {"bicubic", "fast"} for p in bound["picks"].values())
        for key in (k for k in bic if k.startswith("maps.") and k.endswith(".psnr")):
            assert bound[key] >= max(bic[key], fast[key]) - 1e-3, (asset, key)
        assert 5.0 < bound["render.psnr"] < 100.0
    table = (tmp_path / "out" / "results.md").read_text()
    assert "| procedural | closest:bicubic\\|fast | " in table
