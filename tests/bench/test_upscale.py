"""`pbrsr bench upscale` end to end on the tiny procedural assets (no shared assets)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pbrsr_bench.upscale import bench_assets, run, summary
from pbrsr_core.asset import load_asset, make_demo_asset, make_test_asset


def test_bench_upscale_small_run(tmp_path: Path):
    said: list[str] = []
    rows = run(
        out_dir=tmp_path / "out",
        methods=("fast",),
        prior="bicubic",
        eval_res=64,
        eval_views=4,
        procedural_size=64,
        shared=tmp_path / "no-shared-assets",
        log=said.append,
    )
    assert any("not present" in s for s in said)
    assert [(r["asset"], r["method"]) for r in rows] == [
        ("procedural", "fast"),
        ("procedural-cutout", "fast"),
    ]
    for r in rows:
        assert r["run_s"] > 0 and r["peak_rss_mib"] > 0
        assert 5.0 < r["render.psnr"] < 100.0 and "maps.albedo.psnr" in r
    assert "maps.normal.psnr" in rows[1]  # the foliage card's normal map is scored too
    fast = rows[0]
    assert fast["curve"] and fast["curve"][0]["it"] == 0
    assert [c["seconds"] for c in fast["curve"]] == sorted(c["seconds"] for c in fast["curve"])
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert len(saved["rows"]) == 2
    assert (tmp_path / "out" / "speed_vs_error.png").stat().st_size > 0
    assert "| procedural | fast |" in (tmp_path / "out" / "results.md").read_text()


def test_max_size_runs_are_scored_at_the_ground_truths_size(tmp_path: Path):
    """x4 of 64² maps with max_size 32: each map at x2, its map PSNR taken of a bicubic x2 of
    it, its renders of the map as it is; close to the uncapped run, not above it. A max_size
    that keeps every map is refused on the asset and the bench goes on."""
    said: list[str] = []
    rows = run(
        out_dir=tmp_path / "out",
        methods=("bicubic", "bicubic+max_size=32", "bicubic+max_size=8"),
        eval_res=64,
        eval_views=4,
        procedural_size=64,
        include_shared=False,
        log=said.append,
    )
    # max_size 8 keeps every 16² map: refused on each asset, said so, no row, the bench goes on
    assert [r["method"] for r in rows] == ["bicubic", "bicubic+max_size=32"] * 2
    refused = [s for s in said if "refused" in s]
    assert len(refused) == 2 and all("over max_size (8 px)" in s for s in refused)
    full, capped = rows[0], rows[1]
    assert capped["method"] == "bicubic+max_size=32"
    for key in ("render.psnr", "maps.albedo.psnr", "maps.normal.psnr"):
        assert full[key] - 3.0 < capped[key] < full[key] + 0.2, key


def test_list_changes_run_the_maps_and_preset_tuples_they_name(tmp_path: Path):
    """``+maps=`` keeps the maps it does not list (scored at the ground truth's size as a
    bicubic upscale, as max_size's are); a preset's tuple (``prior_maps``) reaches the run
    through the child process's JSON."""
    rows = run(
        out_dir=tmp_path / "out",
        methods=("bicubic", "bicubic+maps=base_color", "fast+prior_maps=base_color|normal"),
        prior="bicubic",
        eval_res=64,
        eval_views=4,
        procedural_size=64,
        include_shared=False,
        log=lambda _: None,
    )
    by = {(r["asset"], r["method"]): r for r in rows}
    full, some = by["procedural", "bicubic"], by["procedural", "bicubic+maps=base_color"]
    assert some["maps.albedo.psnr"] == full["maps.albedo.psnr"]
    assert some["maps.normal.psnr"] == pytest.approx(full["maps.normal.psnr"], abs=0.5)
    assert some["render.psnr"] != full["render.psnr"]  # the kept maps render as they are
    assert 5.0 < by["procedural", "fast+prior_maps=base_color|normal"]["render.psnr"] < 100.0
    table = (tmp_path / "out" / "results.md").read_text()
    assert "| procedural | fast+prior_maps=base_color\\|normal | " in table  # one cell


def test_at_gt_size_upscales_only_maps_smaller_by_a_whole_factor(tmp_path: Path):
    from pbrsr_bench.upscale import at_gt_size
    from pbrsr_core.maps import kind_of
    from pbrsr_core.prior.direct import bicubic_map

    gt = load_asset(make_demo_asset(tmp_path / "d.glb", size=32))
    small = dataclasses.replace(gt.images[0], pixels=gt.images[0].pixels[::2, ::2])
    pred = dataclasses.replace(gt, images=[small, *gt.images[1:]])
    out = at_gt_size(pred, gt)
    kind = kind_of(gt.images[0].roles)
    assert np.array_equal(out.images[0].pixels, bicubic_map(small.pixels, kind, 2))
    assert all(a is b for a, b in zip(out.images[1:], gt.images[1:], strict=True))
    assert at_gt_size(gt, gt) is gt


def test_each_run_takes_the_pbrsr_settings_of_the_bench(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("PBRSR_PRIOR_PRECISION", "half")  # read in the run's own process
    with pytest.raises(RuntimeError, match="PBRSR_PRIOR_PRECISION='half' is not one of"):
        run(
            out_dir=tmp_path / "out",
            methods=("direct",),
            prior="bicubic",
            eval_res=32,
            eval_views=1,
            procedural_size=32,
            shared=tmp_path / "no-shared-assets",
            log=lambda m: None,
        )


def _row(asset, method, render, albedo, run_s):
    return {
        "asset": asset,
        "method": method,
        "render.psnr": render,
        "maps.albedo.psnr": albedo,
        "maps.normal.psnr": 30.0,
        "run_s": run_s,
        "peak_rss_mib": 100.0 * run_s,
        "curve": [],
    }


def test_summary_gains_worst_map_and_fast_share():
    from pbrsr_bench.upscale import markdown_table, summary_table

    rows = [
        _row("a", "bicubic", 28.0, 27.0, 1.0),
        _row("a", "fast", 28.4, 27.5, 10.0),
        _row("a", "balanced", 29.0, 26.8, 40.0),
        _row("b", "bicubic", 30.0, 31.0, 1.0),
        _row("b", "fast", 30.2, 31.1, 10.0),
        _row("b", "balanced", 30.6, 31.2, 40.0),
        _row("procedural", "bicubic", 20.0, 20.0, 1.0),  # left out of the means
        _row("procedural", "balanced", 30.0, 10.0, 1.0),
    ]
    rows[0]["maps.emissive.psnr"], rows[1]["maps.emissive.psnr"] = 40.0, 39.0
    s = {r["method"]: r for r in summary(rows)}
    assert set(s) == {"fast", "balanced"}
    assert s["fast"]["worst_map_db"] == -1.0 and s["fast"]["worst_map_at"] == "a emissive"
    del rows[1]["maps.emissive.psnr"]
    s = {r["method"]: r for r in summary(rows)}
    assert s["balanced"]["render_gain_db"] == 0.8 and s["fast"]["render_gain_db"] == 0.3
    assert s["balanced"]["worst_map_db"] == -0.2 and s["balanced"]["worst_map_at"] == "a albedo"
    assert s["fast"]["worst_map_db"] == 0.0  # normals equal, albedo above
    assert s["balanced"]["mean_run_s"] == 40.0 and s["balanced"]["max_peak_mib"] == 4000
    table = markdown_table(rows)
    assert "| occlusion | emissive |" in table and "| 27.50 | - | - | 30.00 | - | - |" in table
    text = summary_table(rows)
    assert (
        "fast keeps 37 % of balanced's mean render-PSNR gain in 25 % of its mean run time" in text
    )


def test_summary_gives_the_gain_under_each_light():
    """The mean gain per light, over the rows that have it with their bicubic rows; the
    table says it when every method has the same lights."""
    from pbrsr_bench.upscale import summary_table

    rows = [
        _row("a", "bicubic", 30.0, 30.0, 1.0),
        _row("a", "direct", 31.0, 31.0, 2.0),
        _row("b", "bicubic", 20.0, 20.0, 1.0),
        _row("b", "direct", 23.0, 21.0, 2.0),
    ]
    studio, sunset = (29.0, 31.5, 19.0, 21.0), (31.0, 30.5, 21.0, 25.0)
    for r, a, b in zip(rows, studio, sunset, strict=True):
        r["render.studio.psnr"], r["render.sunset.psnr"] = a, b
    s = summary(rows)[0]
    assert s["render_gain_db_by_light"] == {"studio": 2.25, "sunset": 1.75}
    text = summary_table(rows)
    assert "Mean render PSNR gain per light (studio / sunset): direct +2.25 / +1.75 dB." in text
    del rows[2]["render.sunset.psnr"]  # a bicubic row without it: that light is left out
    assert summary(rows)[0]["render_gain_db_by_light"] == {"studio": 2.25}
    for r in rows:
        r.pop("render.studio.psnr")
    assert summary(rows)[0]["render_gain_db_by_light"] == {}
    assert "per light" not in summary_table(rows)


def test_a_run_that_estimates_its_kernel_says_which_it_picked(tmp_path: Path):
    """Each row keeps the run's LR model: the kernel an ``lr_kernel=auto`` run read off the
    maps, or the one a run was told; the tables name the estimated ones."""
    from pbrsr_bench.upscale import markdown_table, summary_table
    from pbrsr_core.degrade import KERNELS

    rows = run(
        out_dir=tmp_path / "out",
        methods=("direct+lr_kernel=auto", "direct+lr_kernel=area"),
        prior="bicubic",
        eval_res=64,
        eval_views=2,
        procedural_size=256,
        kernel="lanczos",
        include_shared=False,
        log=lambda _: None,
    )
    auto = [r for r in rows if r["method"] == "direct+lr_kernel=auto"]
    told = [r for r in rows if r["method"] == "direct+lr_kernel=area"]
    assert len(auto) == len(told) == 2
    for r in told:
        assert r["lr_model"] == {"kernel": "area", "estimated": False}
    for r in auto:  # 64² LR maps with texture: each asset's maps vote
        assert r["lr_model"]["estimated"] and r["lr_model"]["kernel"] in KERNELS
        assert sum(r["lr_model"]["posterior"].values()) == pytest.approx(1.0, abs=1e-3)
    saved = json.loads((tmp_path / "out" / "results.json").read_text())["rows"]
    assert [r["lr_model"] for r in saved] == [r["lr_model"] for r in rows]
    table = markdown_table(rows)
    k = auto[0]["lr_model"]["kernel"]
    assert f"| procedural | direct+lr_kernel=auto ({k}) |" in table
    assert "| procedural | direct+lr_kernel=area |" in table

    # the summary counts the picks over the assets it averages (the procedural ones renamed)
    named = [{**r, "asset": r["asset"] + "-x"} for r in rows]
    named += [
        {**r, "asset": r["asset"] + "-x", "method": "bicubic", "lr_model": None} for r in told
    ]
    s = {r["method"]: r for r in summary(named)}
    picks = [r["lr_model"]["kernel"] for r in auto]
    assert s["direct+lr_kernel=auto"]["estimated_kernels"] == {k: picks.count(k) for k in picks}
    assert s["direct+lr_kernel=area"]["estimated_kernels"] == {}
    text = summary_table(named)
    assert "direct+lr_kernel=auto estimated the LR kernel of 2 of its 2 assets: " in text
    assert "direct+lr_kernel=area estimated" not in text


def test_bench_assets_refuses_an_unknown_name(tmp_path: Path):
    shared = tmp_path / "shared"
    (shared / "Chair").mkdir(parents=True)
    make_demo_asset(shared / "Chair" / "chair.glb", size=16)
    found = bench_assets(tmp_path / "w", False, 16, shared, ["Chair"], print)
    assert [name for name, _ in found] == ["Chair"]
    with pytest.raises(ValueError, match="Chiar not found"):
        bench_assets(tmp_path / "w", False, 16, shared, ["Chair", "Chiar"], print)
    # --no-shared: the procedural assets alone, whatever the shared folder holds
    said: list[str] = []
    only = bench_assets(tmp_path / "w2", True, 16, shared, None, said.append, include_shared=False)
    assert [name for name, _ in only] == ["procedural", "procedural-cutout"] and said == []


def _bicubic_on(folder: Path, out: Path, **options) -> list[dict]:
    """The bench's bicubic rows on the assets of ``folder`` (2 views at 32²), no shared ones."""
    return run(
        out_dir=out,
        methods=("bicubic",),
        eval_res=32,
        eval_views=2,
        include_procedural=False,
        shared=out / "no-shared-assets",
        assets_dir=folder,
        log=print,
        **options,
    )


def test_an_assets_folder_runs_in_place_of_the_shared_assets(tmp_path: Path):
    """--assets-dir: each folder's glTF runs (no variants: a WaterBottle there is any asset),
    the summary names the folder and its command the option; a folder holding no asset is
    refused before anything runs (exit 2)."""
    from typer.testing import CliRunner

    from pbrsr_bench.upscale import published_summary

    mine = tmp_path / "mine"
    (mine / "WaterBottle").mkdir(parents=True)
    make_test_asset(mine / "WaterBottle" / "left.glb", size=16)
    rows = _bicubic_on(mine, tmp_path / "out")
    assert [(r["asset"], r["method"]) for r in rows] == [("WaterBottle", "bicubic")]
    text = published_summary(tmp_path / "out")
    assert f"mean over 1 assets of `{mine}` (WaterBottle)" in text
    assert f"--eval-views 2 --assets-dir {mine}`" in text
    empty = tmp_path / "empty"
    (empty / "notes").mkdir(parents=True)
    said = {
        empty: f"{empty} holds no folder with a .gltf or .glb",
        tmp_path / "absent": f"--assets-dir {tmp_path / 'absent'} is not a folder",
    }
    for folder, reason in said.items():
        out = tmp_path / "never"
        res = CliRunner().invoke(
            _bench_cli(), ["bench", "upscale", "-o", str(out), "--assets-dir", str(folder)]
        )
        assert res.exit_code == 2 and reason in res.output
        assert not out.exists()


def test_store_like_gt_scores_the_maps_as_the_ground_truths_files_store_them(tmp_path: Path):
    """--store-like-gt: with a ground truth stored as 4:2:0 JPEG, each method's maps are
    scored as stored the same way (other numbers than without), and the summary and its
    command say so."""
    from pbrsr_bench.upscale import published_summary
    from pbrsr_core.asset.gltf_write import save_asset

    mine = tmp_path / "mine"
    (mine / "jpeg").mkdir(parents=True)
    asset = load_asset(make_test_asset(tmp_path / "src.glb", size=16))
    every = {im.index: im.pixels for im in asset.images if im.pixels.shape[2] == 3}
    save_asset(asset, mine / "jpeg" / "gt.glb", every, image_format="jpeg:80:420")
    scored = {}
    for flag in (False, True):
        out = tmp_path / f"out-{flag}"
        scored[flag] = _bicubic_on(mine, out, store_like_gt=flag)[0]
        text = published_summary(out)
        assert (" --store-like-gt" in text) is flag
        assert ("scored as stored with that file's tables and chroma sampling" in text) is flag
    assert scored[True]["maps.albedo.psnr"] == scored[False]["maps.albedo.psnr"]  # RGBA: PNG
    assert scored[True]["maps.normal.psnr"] != scored[False]["maps.normal.psnr"]
    assert scored[True]["render.psnr"] != scored[False]["render.psnr"]


def test_bench_assets_adds_the_draco_variant_of_the_water_bottle(tmp_path: Path):
    shared = tmp_path / "shared"
    (shared / "WaterBottle").mkdir(parents=True)
    make_test_asset(shared / "WaterBottle" / "WaterBottle.gltf", size=16)
    said: list[str] = []
    found = dict(bench_assets(tmp_path / "w", False, 16, shared, None, said.append, variants=True))
    assert list(found) == ["WaterBottle", "WaterBottle-draco", "WaterBottle-draco-ktx2"]
    variant = found["WaterBottle-draco"]
    assert variant == tmp_path / "w" / "WaterBottle-draco" / "WaterBottle.glb"
    plain, draco = load_asset(found["WaterBottle"]), load_asset(variant)
    assert draco.document["extensionsRequired"] == ["KHR_draco_mesh_compression"]
    assert draco.geometry is not None and draco.geometry.accessors
    assert draco.mesh.num_triangles == plain.mesh.num_triangles
    assert [im.pixels.shape for im in draco.images] == [im.pixels.shape for im in plain.images]
    ktx2 = load_asset(found["WaterBottle-draco-ktx2"])
    assert set(ktx2.document["extensionsRequired"]) == {
        "KHR_draco_mesh_compression",
        "KHR_texture_basisu",
    }
    assert ktx2.mesh.num_triangles == plain.mesh.num_triangles
    for im, ref in zip(ktx2.images, plain.images, strict=True):
        assert im.pixels.shape == ref.pixels.shape
        assert im.mime == ("image/ktx2" if ref.bit_depth == 8 else "image/png")  # 16 bits kept
        # Basis on 16² test patterns: the colours kept, not the texels (ETC1S blocks)
        assert np.abs(im.pixels.mean((0, 1)) - ref.pixels.mean((0, 1))).max() < 0.05
    # named alone, the variant comes without its source; other benchmarks get none
    only = bench_assets(
        tmp_path / "w2", False, 16, shared, ["WaterBottle-draco"], print, variants=True
    )
    assert [name for name, _ in only] == ["WaterBottle-draco"]
    assert [n for n, _ in bench_assets(tmp_path / "w3", False, 16, shared, None, print)] == [
        "WaterBottle"
    ]
    # the variant repeats its source's maps: the summary means leave it out
    rows = [
        {"asset": a, "method": m, "render.psnr": p, "run_s": 1.0, "peak_rss_mib": 1.0}
        for a, m, p in [
            ("WaterBottle", "bicubic", 30.0),
            ("WaterBottle", "fast", 31.0),
            ("WaterBottle-draco", "bicubic", 20.0),
            ("WaterBottle-draco", "fast", 30.0),
        ]
    ]
    assert summary(rows)[0]["render_gain_db"] == 1.0 and summary(rows)[0]["assets"] == 1


def test_methods_may_name_their_prior_and_unknown_ones_are_refused():
    from pbrsr_bench.upscale import check_methods, method_options

    assert method_options("direct@bicubic", 4, "waifu2x-photo")["prior"] == "bicubic"
    assert method_options("direct", 4, "waifu2x-photo")["prior"] == "waifu2x-photo"
    opts = method_options("balanced@pbr-upconv7", 2, "bicubic")
    assert opts == {"method": "pbrsr", "preset": "balanced", "scale": 2, "prior": "pbr-upconv7"}
    check_methods(("bicubic", "direct@waifu2x-photo", "fast@pbr-upconv7"), "bicubic")
    with pytest.raises(ValueError, match="unknown method 'fastest'"):
        check_methods(("fastest",), "bicubic")
    with pytest.raises(ValueError, match="nosuchprior"):
        check_methods(("direct@nosuchprior",), "bicubic")


def test_methods_take_preset_changes():
    from pbrsr_bench.upscale import check_methods, method_options, parse_method, preset_changes

    name, prior, changes = parse_method("balanced@pbr-upconv7+lambda_pix=0+pseudo_gt_prior=bicubic")
    assert (name, prior) == ("balanced", "pbr-upconv7")
    assert changes == {"lambda_pix": 0, "pseudo_gt_prior": "bicubic"}
    assert parse_method("fast") == ("fast", None, {})
    check_methods(("balanced+iterations=50+pseudo_gt_prior=waifu2x-photo",), "bicubic")
    # a field that holds a dict takes a JSON object (one key: a comma separates methods)
    by_kind = 'balanced+self_ensemble_by_kind={"normal":2}'
    assert preset_changes(by_kind) == {"self_ensemble_by_kind": {"normal": 2}}
    check_methods((by_kind,), "bicubic")
    with pytest.raises(ValueError, match="self_ensemble_by_kind maps kinds"):
        check_methods(('fast+self_ensemble_by_kind={"normal":3}',), "bicubic")
    with pytest.raises(ValueError, match="not key=value"):
        check_methods(("balanced+lambda_pix",), "bicubic")
    with pytest.raises(ValueError, match="only a PBR-SR preset"):
        check_methods(("direct+lambda_pix=0",), "bicubic")
    # max_size is an upscale option: every method takes it, and it is checked as one
    check_methods(("direct+max_size=512", "bicubic+max_size=64", "fast+max_size=64"), "bicubic")
    assert method_options("direct+max_size=512", 4, "bicubic")["max_size"] == 512
    assert preset_changes("balanced+max_size=512+lambda_pix=0") == {"lambda_pix": 0}
    with pytest.raises(ValueError, match="max_size: Input should be greater than or equal to 2"):
        check_methods(("direct+max_size=1",), "bicubic")
    # so is lr_kernel, the LR model the run inverts
    check_methods(("direct+lr_kernel=area", "balanced+lr_kernel=lanczos"), "bicubic")
    assert method_options("direct+lr_kernel=area", 4, "bicubic")["lr_kernel"] == "area"
    assert preset_changes("balanced+lr_kernel=area") == {}
    with pytest.raises(ValueError, match="lr_kernel: Input should be 'gaussian'"):
        check_methods(("direct+lr_kernel=box",), "bicubic")
    # and maps, its roles joined by "|" (a comma separates methods)
    check_methods(("balanced+maps=base_color|normal", "bicubic+maps=emissive"), "bicubic")
    assert method_options("direct+maps=normal|base_color", 4, "bicubic")["maps"] == [
        "normal",
        "base_color",
    ]
    assert preset_changes("balanced+maps=normal") == {}
    # and other_maps, for the maps that maps leaves out
    rest = method_options("balanced+maps=normal+other_maps=bicubic", 4, "bicubic")
    assert (rest["maps"], rest["other_maps"]) == (["normal"], "bicubic")
    assert preset_changes("balanced+maps=normal+other_maps=bicubic") == {}
    with pytest.raises(ValueError, match="other_maps: Input should be 'keep' or 'bicubic'"):
        check_methods(("direct+maps=normal+other_maps=smear",), "bicubic")
    # a preset's tuple takes its items the same way
    assert preset_changes("fast+prior_maps=base_color|normal") == {
        "prior_maps": ("base_color", "normal")
    }
    assert preset_changes("fast+prior_maps=normal") == {"prior_maps": ("normal",)}
    with pytest.raises(ValueError, match="prior_maps must be among"):
        check_methods(("fast+prior_maps=albedo",), "bicubic")
    with pytest.raises(ValueError, match="maps: Value error, unknown map role 'albedo'"):
        check_methods(("direct+maps=albedo|normal",), "bicubic")
    with pytest.raises(ValueError, match="no_such_field"):
        check_methods(("balanced+no_such_field=1",), "bicubic")
    with pytest.raises(ValueError, match="unknown prior 'nope'"):
        check_methods(("balanced+pseudo_gt_prior=nope",), "bicubic")


def _bench_cli():
    import typer

    from pbrsr_bench import cli as bench

    app = typer.Typer()
    bench.register(app)
    return app


def _results_dir(path, rows):
    """``path`` made a finished x4 run's output folder holding ``rows``."""
    from pbrsr_core.options import DEFAULT_PRIOR

    meta = {"scale": 4, "prior": DEFAULT_PRIOR, "eval_res": 256, "eval_views": 40}
    meta.update(lights=["a.hdr", "b.hdr"], machine="a test CPU, 2 cores")
    path.mkdir()
    (path / "results.json").write_text(json.dumps({**meta, "rows": rows}))
    return path


def test_publish_writes_the_summary_between_the_markers_only(tmp_path):
    from typer.testing import CliRunner

    rows = [
        _row("procedural", "bicubic", 20.0, 20.0, 1.0),
        _row("a", "bicubic", 28.0, 27.0, 1.0),
        _row("a", "fast", 28.4, 27.5, 10.0),
        _row("b", "bicubic", 30.0, 31.0, 1.0),
        _row("b", "fast", 31.0, 31.2, 14.0),
    ]
    out = _results_dir(tmp_path / "out", rows)
    doc = tmp_path / "README.md"
    head, tail = "# Title\n\ntext before\n", "\ntext after\n"
    doc.write_text(head + "<!-- bench:upscale -->\nold numbers\n<!-- /bench:upscale -->" + tail)
    res = CliRunner().invoke(_bench_cli(), ["bench", "publish", str(out), "--docs", str(doc)])
    assert res.exit_code == 0, res.output
    text = doc.read_text()
    assert text.startswith(head + "<!-- bench:upscale -->\n") and text.endswith(tail)
    assert "old numbers" not in text
    assert "| fast | 2 | +0.70 dB |" in text  # mean of +0.4 and +1.0 over the shared a, b
    assert "2 shared assets (a, b)" in text and "a test CPU, 2 cores" in text
    assert "`pbrsr bench upscale --methods bicubic,fast --eval-views 40`" in text
    # a second run replaces the section again, nothing else
    again = CliRunner().invoke(_bench_cli(), ["bench", "publish", str(out), "--docs", str(doc)])
    assert again.exit_code == 0 and doc.read_text() == text


def test_publish_writes_the_named_section_and_leaves_the_others(tmp_path):
    from typer.testing import CliRunner

    rows = [_row("a", "bicubic", 28.0, 27.0, 1.0), _row("a", "fast", 28.4, 27.5, 10.0)]
    out = _results_dir(tmp_path / "out", rows)
    doc = tmp_path / "BENCH.md"
    first = "<!-- bench:upscale -->\nshared numbers\n<!-- /bench:upscale -->\n"
    doc.write_text(first + "<!-- bench:upscale-unseen -->\nold\n<!-- /bench:upscale-unseen -->\n")
    cli = _bench_cli()
    args = ["bench", "publish", str(out), "--docs", str(doc)]
    res = CliRunner().invoke(cli, [*args, "--section", "upscale-unseen"])
    assert res.exit_code == 0, res.output
    text = doc.read_text()
    assert text.startswith(first) and "\nold\n" not in text
    assert "| fast | 1 | +0.40 dB |" in text.split("<!-- bench:upscale-unseen -->")[1]
    for bad, message in (("nowhere", "no '<!-- bench:nowhere -->'"), ("Up Scale", "section name")):
        res = CliRunner().invoke(cli, [*args, "--section", bad])
        assert res.exit_code == 2 and message in res.output
        assert doc.read_text() == text


def test_a_list_change_stays_one_cell_and_its_command_is_quoted(tmp_path):
    from pbrsr_bench.upscale import published_summary
    from pbrsr_core.options import DEFAULT_PRIOR

    method = "fast+maps=base_color|normal"
    rows = [_row("a", "bicubic", 28.0, 27.0, 1.0), _row("a", method, 28.4, 27.5, 10.0)]
    meta = {"scale": 4, "prior": DEFAULT_PRIOR, "eval_res": 256, "eval_views": 40}
    meta.update(lights=["a.hdr", "b.hdr"], machine="a test CPU, 2 cores")
    (tmp_path / "results.json").write_text(json.dumps({**meta, "rows": rows}))
    text = published_summary(tmp_path)
    assert "| fast+maps=base_color\\|normal | 1 | +0.40 dB |" in text
    assert '`pbrsr bench upscale --methods "bicubic,fast+maps=base_color|normal" --eval' in text


def test_docs_without_markers_are_refused_before_the_bench_runs(tmp_path):
    from typer.testing import CliRunner

    doc = tmp_path / "plain.md"
    doc.write_text("# no markers\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(
        _bench_cli(), ["bench", "upscale", "-o", str(out), "--docs", str(doc), "--no-shared"]
    )
    assert res.exit_code == 2
    assert "no '<!-- bench:upscale -->'" in res.output
    assert not out.exists() and doc.read_text() == "# no markers\n"
    # a section name no marker can hold is refused before the run, with or without --docs
    res = CliRunner().invoke(
        _bench_cli(), ["bench", "upscale", "-o", str(out), "--section", "x y", "--no-shared"]
    )
    assert res.exit_code == 2 and "section name 'x y'" in res.output and not out.exists()
    res = CliRunner().invoke(_bench_cli(), ["bench", "publish", str(out), "--docs", str(doc)])
    assert res.exit_code == 2 and "no results.json" in res.output


def test_the_lr_kernel_is_checked_first_and_named_in_the_summary(tmp_path):
    """An unknown kernel is refused before anything runs; a run on LR maps made by another
    kernel than the protocol's says so, and its command names it."""
    from pbrsr_bench.upscale import published_summary
    from pbrsr_core.errors import InvalidOptions
    from pbrsr_core.options import DEFAULT_PRIOR

    with pytest.raises(InvalidOptions, match="unknown LR kernel.s. box"):
        run(out_dir=tmp_path / "never", kernel="box", include_shared=False)
    assert not (tmp_path / "never").exists()
    rows = [_row("a", "bicubic", 28.0, 27.0, 1.0), _row("a", "fast", 28.4, 27.5, 10.0)]
    meta = {"scale": 4, "prior": DEFAULT_PRIOR, "eval_res": 256, "eval_views": 40}
    meta.update(lights=["a.hdr"], machine="a test CPU")
    for kernel, named in (("area", True), ("gaussian", False), (None, False)):
        data = {**meta, "rows": rows, **({"kernel": kernel} if kernel else {})}
        (tmp_path / "results.json").write_text(json.dumps(data))
        text = published_summary(tmp_path)
        assert ("x4, LR by the area kernel" in text) is named
        assert ("--eval-views 40 --kernel area`" in text) is named


def test_the_lr_format_is_checked_first_and_named_in_the_summary(tmp_path):
    """A malformed JPEG format is refused before anything runs; a run whose LR maps were
    stored in another format than the asset's own says so, and its command names it."""
    from pbrsr_bench.upscale import published_summary
    from pbrsr_core.errors import InvalidOptions
    from pbrsr_core.options import DEFAULT_PRIOR

    with pytest.raises(InvalidOptions, match="bad JPEG format 'jpeg:85:422'"):
        run(out_dir=tmp_path / "never", lr_format="jpeg:85:422", include_shared=False)
    assert not (tmp_path / "never").exists()
    rows = [_row("a", "bicubic", 28.0, 27.0, 1.0), _row("a", "fast", 28.4, 27.5, 10.0)]
    meta = {"scale": 4, "prior": DEFAULT_PRIOR, "eval_res": 256, "eval_views": 40}
    meta.update(lights=["a.hdr"], machine="a test CPU")
    for lr_format, named in (("jpeg:85:420", True), ("same", False), (None, False)):
        data = {**meta, "rows": rows, **({"lr_format": lr_format} if lr_format else {})}
        (tmp_path / "results.json").write_text(json.dumps(data))
        text = published_summary(tmp_path)
        assert ("x4, LR maps stored as `jpeg:85:420`" in text) is named
        assert ("--eval-views 40 --lr-format jpeg:85:420`" in text) is named
