"""`pbrsr bench check` on a procedural texture folder (no shared textures)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pbrsr_bench.check import markdown_table, run
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_texture_folder(tmp_path_factory.mktemp("textures"), n=10, size=256)


def test_check_scores_each_choice_against_the_real_scale(folder, tmp_path: Path):
    said: list[str] = []
    result = run(said.append, tmp_path / "out", folder, "waifu2x-photo", 4, (256, 128))
    rows = result["rows"]
    assert said and {r["kind"] for r in rows} == {"colour", "data"}
    assert {r["size"] for r in rows} == {256, 128}
    for r in rows:
        assert all(math.isfinite(v) for v in r["gain"].values())
        assert list(r["gain"]) == ["waifu2x-photo"]
        # the check uses its pick exactly where the pick beats bicubic one scale down
        assert (r["choice"] != "bicubic") == (r["margin_db"] > 0)
        assert r["choice_gain"] == (0.0 if r["choice"] == "bicubic" else r["gain"][r["choice"]])
        assert r["oracle_gain"] == max(0.0, *r["gain"].values()) >= r["choice_gain"]
    # a greyscale-packed data crop (roughness, metallic, roughness) is scored per distinct map
    data = [r for r in rows if r["kind"] == "data" and r["size"] == 256]
    assert data and all(r["map"].endswith(("[R]", "[G]")) for r in data)
    for s in result["summary"]:
        sel = [r for r in rows if r["kind"] == s["kind"] and r["size"] == s["size"]]
        assert s["maps"] == len(sel)
        assert s["below"] == sum(r["choice_gain"] < 0 for r in sel)
        assert s["oracle"] >= s["check"] and s["oracle"] >= s["each"]["waifu2x-photo"]
        gains = sorted(r["gain"]["waifu2x-photo"] for r in sel)
        assert min(gains) <= s["each_median"]["waifu2x-photo"] <= max(gains)
    saved = json.loads((tmp_path / "out" / "check.json").read_text())
    assert saved["summary"] == result["summary"]
    assert (tmp_path / "out" / "check.png").stat().st_size > 0
    assert "| colour | 256² |" in markdown_table(result)


def test_a_prior_that_is_bicubic_never_wins(folder, tmp_path: Path):
    result = run(lambda _: None, tmp_path / "out", folder, "bicubic", 2, (128,))
    for r in result["rows"]:
        assert r["choice"] == "bicubic" and r["choice_gain"] == 0.0 and r["margin_db"] == 0.0
        assert r["gain"] == {"bicubic": 0.0} and r["oracle_gain"] == 0.0
    assert all(s["below"] == 0 and s["check"] == 0.0 for s in result["summary"])


def test_cli_refuses_what_it_cannot_score(folder, tmp_path: Path, capfd):
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(tmp_path / "none")], capfd
    )
    assert code == 2 and "texture folder" in err
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--scale", "3"], capfd
    )
    assert code == 2 and "scale must be 2, 4 or 8" in err
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--sizes", "32"], capfd
    )
    assert code == 2 and "at least 64 px" in err


def test_jpeg_lr_crops_are_scored_as_a_jpeg_file_holds_them(folder, tmp_path: Path, capfd):
    from pbrsr_bench.check import low_res, presets_low_res
    from pbrsr_core.asset.jpeg import deblock, standard_quant
    from pbrsr_core.degrade import degrade_image

    hr = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32)
    clean, jpeg = low_res(hr, 4), low_res(hr, 4, jpeg=60)
    assert (clean == degrade_image(hr, 4)).all() and jpeg.shape == clean.shape
    assert not (jpeg == clean).all() and (jpeg * 255 == (jpeg * 255).round()).all()
    # checked as the presets check it: deblocked with the file's tables, the stored map beside
    lr, stored = presets_low_res(hr, 4, jpeg=60)
    assert (stored == jpeg).all() and (lr == deblock(jpeg, standard_quant(60))).all()
    assert presets_low_res(hr, 4)[1] is None and (presets_low_res(hr, 4)[0] == clean).all()
    raw, none = presets_low_res(hr, 4, jpeg=60, deblock_jpeg=False)
    assert none is None and (raw == jpeg).all()
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--prior", "bicubic"]
        + ["--scale", "2", "--sizes", "128", "--jpeg", "60"],
        capfd,
    )
    assert code == 0, err
    saved = json.loads((tmp_path / "check.json").read_text())
    assert saved["jpeg"] == 60 and "JPEG quality 60 4:4:4, deblocked" in markdown_table(saved)
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--prior", "bicubic"]
        + ["--scale", "2", "--sizes", "128", "--jpeg", "60", "--no-deblock"],
        capfd,
    )
    assert code == 0, err
    raw = json.loads((tmp_path / "check.json").read_text())
    assert not raw["deblock"] and "JPEG quality 60 4:4:4, not deblocked" in markdown_table(raw)
    code, err = run_cli(
        ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--jpeg", "0"], capfd
    )
    assert code == 2 and "--jpeg" in err


def test_jpeg_lr_crops_can_hold_their_chroma_at_half_resolution(folder, tmp_path: Path, capfd):
    """--chroma 4:2:0: the LR crops as a 4:2:0 file holds them (the chroma averaged over 2x2),
    deblocked with that file's tables; a grey crop has no chroma to lose."""
    from pbrsr_bench.check import low_res, presets_low_res
    from pbrsr_core.asset.jpeg import compress, deblock, standard_quant
    from pbrsr_core.degrade import degrade_image

    hr = np.random.default_rng(0).random((64, 64, 3)).astype(np.float32)
    full, half = low_res(hr, 2, jpeg=90), low_res(hr, 2, jpeg=90, subsampled=True)
    t = torch.from_numpy(degrade_image(hr, 2)).permute(2, 0, 1)[None]
    want = compress(t, standard_quant(90, True))[0].permute(1, 2, 0).numpy()
    assert (half == want).all() and np.abs(half - full).mean() > 0.01
    lr, stored = presets_low_res(hr, 2, jpeg=90, subsampled=True)
    assert (stored == half).all() and (lr == deblock(half, standard_quant(90, True))).all()
    grey = np.repeat(hr[..., :1], 3, axis=2)
    assert np.abs(low_res(grey, 2, 90, True) - low_res(grey, 2, 90)).max() <= 1 / 255 + 1e-6
    base = ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--prior"]
    base += ["bicubic", "--scale", "2", "--sizes", "128", "--jpeg", "60"]
    code, err = run_cli([*base, "--chroma", "4:2:0"], capfd)
    assert code == 0, err
    saved = json.loads((tmp_path / "check.json").read_text())
    assert saved["subsampled"] and "JPEG quality 60 4:2:0, deblocked" in markdown_table(saved)
    code, err = run_cli([*base, "--chroma", "4:2:2"], capfd)
    assert code == 2 and "--chroma takes 4:4:4 or 4:2:0" in err
    code, err = run_cli([*base[:-2], "--chroma", "4:2:0"], capfd)
    assert code == 2 and "give --jpeg Q" in err


def test_the_check_can_model_the_lr_crops_jpeg_storage(folder, tmp_path: Path, capfd, monkeypatch):
    """--storage: the self-check of check and blend compresses its crop one scale down with
    the LR crops' own tables and deblocks it as they were (``check_storage``); only with
    --jpeg."""
    import pbrsr_bench.blend as bench_blend
    import pbrsr_bench.check as bench_check
    from pbrsr_bench.check import storage_model
    from pbrsr_core.asset.jpeg import standard_quant, stored_as
    from pbrsr_core.prior import load_prior
    from pbrsr_core.prior.selfcheck import prior_self_check

    img = np.random.default_rng(2).random((32, 32, 3)).astype(np.float32)
    assert (
        storage_model(90, True, True, False) is None
        and storage_model(None, True, True, True) is None
    )
    for subsampled, deblocked in ((True, True), (False, False)):
        store = storage_model(90, subsampled, deblocked, True)
        want = stored_as(img, standard_quant(90, subsampled), deblocked)
        assert store is not None and (store(img) == want).all()
    stores = []

    def recorded_check(prior, lr, scale, kind, **kw):
        stores.append(kw.get("store"))
        return prior_self_check(prior, lr, scale, kind, **kw)

    monkeypatch.setattr(bench_check, "prior_self_check", recorded_check)
    monkeypatch.setattr(bench_blend, "prior_self_check", recorded_check)
    prior = load_prior("bicubic", "cpu")
    hr = np.random.default_rng(3).random((128, 128, 3)).astype(np.float32)
    bench_check.score_map(prior, hr, "colour", 4, "m", jpeg=80, subsampled=True, storage=True)
    bench_check.score_map(prior, hr, "colour", 4, "m", jpeg=80, subsampled=True)
    bench_blend.score_crop(prior, hr, hr, [1], 4, [(0.0, 0.0, None, False, None)], jpeg=80,
                           storage=True)  # fmt: skip
    assert len(stores) == 4 and stores[1] is None
    for s in (stores[0], *stores[2:]):
        assert (s(img) == stored_as(img, standard_quant(80, s is stores[0]), True)).all()
    base = ["bench", "check", "-o", str(tmp_path), "--textures", str(folder), "--prior"]
    base += ["bicubic", "--scale", "2", "--sizes", "128", "--storage"]
    code, err = run_cli(base, capfd)
    assert code == 2 and "--storage models the --jpeg files in the check: give --jpeg Q" in err
    code, err = run_cli([*base, "--jpeg", "70"], capfd)
    assert code == 0, err
    saved = json.loads((tmp_path / "check.json").read_text())
    assert saved["storage"]
    assert "JPEG quality 70 4:4:4, deblocked, that storage modelled in the check" in (
        markdown_table(saved)
    )
