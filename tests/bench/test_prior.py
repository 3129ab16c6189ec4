"""`pbrsr bench prior` on the bicubic prior with a procedural texture folder (fast), and
pbr-srmd at each precision it takes."""

from __future__ import annotations

import json

import numpy as np
import OpenImageIO as oiio
import torch
from skimage.metrics import peak_signal_noise_ratio

from pbrsr_bench.prior import psnr, run, texture_crops
from pbrsr_core.prior.base import native_int8


def _write_png(path, img):
    path.parent.mkdir(parents=True, exist_ok=True)
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], oiio.UINT8)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec)
    out.write_image((img * 255).round().astype(np.uint8))
    out.close()


def test_psnr_matches_skimage():
    rng = np.random.default_rng(0)
    a = rng.random((20, 24, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1).astype(np.float32)
    ref = peak_signal_noise_ratio(a[2:-2, 2:-2].astype(np.float64), b[2:-2, 2:-2], data_range=1)
    assert abs(psnr(b, a, 2) - ref) < 1e-6


def test_bench_runs_and_writes_outputs(tmp_path):
    yy, xx = np.mgrid[0:160, 0:160] / 160.0
    tex = np.stack([0.5 + 0.4 * np.sin(20 * xx), yy, 0.5 + 0.4 * np.cos(15 * yy * xx)], -1)
    _write_png(tmp_path / "assets" / "Thing" / "Thing_baseColor.png", tex.astype(np.float32))
    _write_png(tmp_path / "assets" / "Thing" / "Thing_normal.png", tex.astype(np.float32))
    crops = texture_crops(64, tmp_path / "assets")
    assert list(crops) == ["Thing/Thing_baseColor.png", "Thing/Thing_baseColor.png@q"]
    logs = []
    result = run(
        out_dir=tmp_path / "out",
        priors=["bicubic"],
        scales=(2,),
        large_scales=(),
        crop=64,
        assets_root=tmp_path / "assets",
        log=logs.append,
    )
    (row,) = result["rows"]
    assert row["prior"] == "bicubic" and row["scale"] == 2 and row["parameters"] == 0
    assert row["gain_natural"] == 0.0 and row["gain_texture"] == 0.0
    assert 15.0 < row["psnr_natural"] < 60.0 and row["psnr_texture"] > 20.0
    assert row["s_per_256"] > 0 and row["s_per_1024"] is None
    saved = json.loads((tmp_path / "out" / "prior.json").read_text())
    assert saved["rows"][0]["psnr_texture"] == row["psnr_texture"]
    assert f"{torch.get_num_threads()} torch threads" in saved["machine"]
    assert "GFLOPS" in saved["machine"]
    assert (tmp_path / "out" / "prior.png").stat().st_size > 1000


def test_bench_says_when_assets_are_missing(tmp_path):
    logs = []
    result = run(
        out_dir=tmp_path / "out",
        priors=["bicubic"],
        scales=(4,),
        large_scales=(),
        crop=32,
        assets_root=tmp_path / "nothing",
        log=logs.append,
    )
    assert not result["assets_root_found"] and any("not found" in m for m in logs)
    assert result["rows"][0]["psnr_texture"] is None


def test_bench_runs_each_prior_once_per_precision_it_takes(tmp_path):
    from pbrsr_core.prior.registry import load_prior

    result = run(
        out_dir=tmp_path / "out",
        priors=["bicubic", "pbr-srmd"],
        scales=(4,),
        large_scales=(),
        crop=32,
        assets_root=tmp_path / "nothing",
        precisions=("auto", "fp32", "int8"),
        log=lambda m: None,
    )
    rows = {(r["prior"], r["precision"]): r for r in result["rows"]}
    assert load_prior("pbr-srmd", "cpu").precision is None  # the cached prior is left as it was
    if not native_int8(torch.device("cpu")):  # int8 takes effect on VNNI or AMX CPUs only
        assert set(rows) == {("bicubic", "fp32"), ("pbr-srmd", "fp32")}
        return
    assert set(rows) == {("bicubic", "fp32"), ("pbr-srmd", "fp32"), ("pbr-srmd", "int8")}
    fp32, q = rows["pbr-srmd", "fp32"], rows["pbr-srmd", "int8"]
    assert fp32["psnr_natural"] != q["psnr_natural"]  # int8 really ran
    assert abs(fp32["psnr_natural"] - q["psnr_natural"]) < 0.3
