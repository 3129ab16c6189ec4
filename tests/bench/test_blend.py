"""`pbrsr bench blend` on a procedural texture folder (no shared textures)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pbrsr_bench.blend import PACKED, markdown_table, packed_crops, run
from pbrsr_core.prior.train.data import Material
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_texture_folder(tmp_path_factory.mktemp("textures"), n=10, size=256)


def test_a_material_is_packed_as_an_exporter_writes_it():
    rng = np.random.default_rng(0)
    maps = {k: rng.integers(0, 256, (64, 64, c), dtype=np.uint8)
            for k, c in (("basecolor", 3), ("roughness", 1))}  # fmt: skip
    crops = packed_crops(Material("m", maps), 32)
    assert [n for n, _, _ in crops] == ["m@0,0", "m@0,32", "m@32,0", "m@32,32"]
    name, colour, packed = crops[3]
    assert colour.dtype == packed.dtype == np.float32 and packed.shape == (32, 32, 3)
    assert (colour == maps["basecolor"][32:, 32:] / np.float32(255)).all()
    assert (packed[..., 1] == maps["roughness"][32:, 32:, 0] / np.float32(255)).all()
    assert (packed[..., 0] == 1.0).all() and (packed[..., 2] == 0.0).all()  # glTF's defaults
    assert packed_crops(Material("m", {"basecolor": maps["basecolor"]}), 32) == []
    assert packed_crops(Material("m", maps), 128) == []


def test_each_rule_is_scored_against_the_real_scale(folder, tmp_path: Path):
    said: list[str] = []
    result = run(said.append, tmp_path / "out", folder, "waifu2x-photo", 4, 128,
                 margins=(0.0, 0.5), network_dbs=(0.0, 1e3), pick_dbs=(None, 0.05))  # fmt: skip
    rows, rules = result["rows"], result["rules"]
    assert said and rows and len(rules) == 8
    # the procedural metallic is a step (checked, not flat); roughness follows the colour
    assert {r["channel"] for r in rows} <= set(PACKED[1:]) and "roughness" in {
        r["channel"] for r in rows
    }
    for r in rows:
        assert set(r["gain"]) == set(r["check_gain"]) == {"waifu2x-photo", "guided"}
        if r["margin_db"] > 0:  # the check's pick is the network: its margin one scale down
            assert r["check_gain"]["waifu2x-photo"] == pytest.approx(r["margin_db"], abs=2e-3)
        assert all(math.isfinite(v) for v in (*r["gain"].values(), *r["rules"].values()))
        assert r["oracle"] == max(0.0, *r["gain"].values())
        assert r["direct"] == (r["gain"]["waifu2x-photo"] if r["margin_db"] > 0 else 0.0)
        for key in rules:
            margin = float(key.split(",")[0].split()[1])
            if "over the pick" in key and r["margin_db"] > 0:
                # the check's pick beats bicubic: it stays unless the blend beats it by 0.05
                if r["fit_db"][key] <= r["margin_db"] + 0.05:
                    assert r["rules"][key] == pytest.approx(r["direct"], abs=1e-6)
                continue
            # otherwise a channel is blended exactly where its fit beats the margin
            assert (r["rules"][key] != 0.0) <= (r["fit_db"][key] > margin)
            if r["fit_db"][key] <= margin:
                assert r["rules"][key] == 0.0
    for c in result["crops"]:  # no network adds 1000 dB: only the guided fit is blended
        assert c["networks"]["margin 0, networks 1000"] == 0
        assert c["networks"]["margin 0, networks 0"] <= 1 and c["networks"]["direct"] <= 1
    by_rule = {s["rule"]: s for s in result["summary"]}
    assert set(by_rule) == {*rules, "direct"}
    for s in by_rule.values():
        gains = [r["direct"] if s["rule"] == "direct" else r["rules"][s["rule"]] for r in rows]
        assert s["channels"] == len(rows) and s["mean"] == pytest.approx(np.mean(gains))
        assert s["worst"] == min(gains) and s["below"] == sum(g < 0 for g in gains)
    assert by_rule["margin 0, networks 0"]["mean"] > 0  # roughness is the colour's
    saved = json.loads((tmp_path / "out" / "blend.json").read_text())
    assert saved["summary"] == result["summary"]
    assert (tmp_path / "out" / "blend.png").stat().st_size > 0
    assert "| margin 0.5, networks 0 | " in markdown_table(result)
    assert "| margin 0.5, networks 0, over the pick 0.05 | " in markdown_table(result)

    def best(gains):
        return max({"bicubic": 0.0, **gains}.items(), key=lambda kv: kv[1])[0]

    same = sum(best(r["check_gain"]) == best(r["gain"]) for r in rows)
    assert f"real scale's best in {same} of {len(rows)}" in markdown_table(result)
    kept = [
        r
        for r in rows
        if r["margin_db"] > 0 and r["fit_db"]["margin 0, networks 0"] <= r["margin_db"] + 0.05
    ]
    assert kept  # the rule is exercised: some pick stays


def test_the_pick_floor_holds_each_channel_at_its_pick(folder, tmp_path: Path):
    result = run(lambda _: None, tmp_path / "out", folder, "waifu2x-photo", 4, 128,
                 margins=(0.0,), network_dbs=(0.0, 1e3), pick_floors=(False, True))  # fmt: skip
    every, rule, floor = ("margin 0, networks 0", "margin 0, networks 1000",
                          "margin 0, networks 1000, pick floor")  # fmt: skip
    assert result["rules"] == [every, f"{every}, pick floor", rule, floor]
    for r in result["rows"]:
        if r["margin_db"] > 0:  # the check's pick beats bicubic one scale down
            assert r["fit_db"][floor] >= min(r["margin_db"], r["fit_db"][every]) - 1e-3
        assert r["fit_db"][floor] >= r["fit_db"][rule] - 1e-3
    nets = {k: sum(c["networks"][k] for c in result["crops"]) for k in (rule, floor)}
    assert nets[rule] == 0 and nets[floor] > 0  # the floor runs the network somewhere
    assert "| margin 0, networks 1000, pick floor | " in markdown_table(result)


def test_the_per_channel_rule_runs_networks_on_fewer_channels(folder, tmp_path: Path):
    result = run(lambda _: None, tmp_path / "out", folder, "waifu2x-photo", 4, 128,
                 margins=(0.0,), network_dbs=(0.0,), channel_dbs=(None, 0.0, 1e3))  # fmt: skip
    every, zero, none = ("margin 0, networks 0", "margin 0, networks 0, per channel 0",
                         "margin 0, networks 0, per channel 1000")  # fmt: skip
    assert result["rules"] == [every, zero, none]
    by_rule = {s["rule"]: s for s in result["summary"]}
    # a network runs once per channel its blend weighs, at most once per channel
    for c in result["crops"]:
        n, runs = c["networks"], c["runs"]
        assert n[every] <= runs[every] <= 3 * n[every]
        assert runs[zero] == runs[every] and runs[none] == 0 and runs["direct"] <= 3
    assert by_rule[every]["runs"] > 0 and by_rule[none]["runs"] == 0
    # a network that costs nothing to leave out of a channel was not weighed there
    for r in result["rows"]:
        assert r["rules"][zero] == r["rules"][every]
    assert "| margin 0, networks 0, per channel 1000 | " in markdown_table(result)
    assert "network runs per map |" in markdown_table(result)


def test_cli_refuses_what_it_cannot_score(folder, tmp_path: Path, capfd):
    base = ["bench", "blend", "-o", str(tmp_path), "--textures", str(folder)]
    code, err = run_cli(["bench", "blend", "--textures", str(tmp_path / "none")], capfd)
    assert code == 2 and "texture folder" in err
    code, err = run_cli(base + ["--scale", "3"], capfd)
    assert code == 2 and "scale must be 2, 4 or 8" in err
    code, err = run_cli(base + ["--size", "32"], capfd)
    assert code == 2 and "at least 64 px" in err
    code, err = run_cli(base + ["--margins", "a"], capfd)
    assert code == 2 and "comma-separated numbers" in err
    code, err = run_cli(base + ["--network-db", "-1"], capfd)
    assert code == 2 and "not negative" in err
    code, err = run_cli(base + ["--pick-db", "-1"], capfd)
    assert code == 2 and "not negative" in err
    code, err = run_cli(base + ["--pick-db", "of"], capfd)
    assert code == 2 and "comma-separated numbers" in err
    code, err = run_cli(base + ["--channel-db", "-0.1"], capfd)
    assert code == 2 and "not negative" in err
    code, err = run_cli(base + ["--pick-floor", "yes"], capfd)
    assert code == 2 and "--pick-floor off, on or both" in err
    code, err = run_cli(base + ["--size", "512"], capfd)
    assert code == 2 and "no held-out material" in err


def test_jpeg_lr_crops_are_deblocked_as_the_presets_deblock_them(
    folder, tmp_path: Path, capfd, monkeypatch
):
    import pbrsr_bench.blend as bench_blend
    import pbrsr_bench.check as bench_check
    from pbrsr_bench.check import low_res
    from pbrsr_core.asset.jpeg import deblock, standard_quant
    from pbrsr_core.prior import load_prior
    from pbrsr_core.prior.selfcheck import prior_self_check

    mat = Material("m", {"basecolor": np.full((128, 128, 3), 90, np.uint8)})
    rng = np.random.default_rng(1)
    mat.maps["roughness"] = (rng.random((128, 128, 1)) * 255).astype(np.uint8)
    (_, colour, packed), *_ = packed_crops(mat, 128)
    seen, checked = [], []

    def recorded(pixels, quant):
        seen.append((pixels, quant))
        return deblock(pixels, quant)

    def recorded_check(prior, lr, scale, kind, **kw):
        checked.append((lr, kw.get("stored")))
        return prior_self_check(prior, lr, scale, kind, **kw)

    monkeypatch.setattr(bench_check, "deblock", recorded)
    monkeypatch.setattr(bench_blend, "prior_self_check", recorded_check)
    prior = load_prior("bicubic", "cpu")
    rules = [(0.0, 0.0, None, False, None)]
    clean, *_ = bench_blend.score_crop(prior, colour, packed, [1], 4, rules)
    assert not seen and all(stored is None for _, stored in checked)
    checked.clear()
    jpeg, *_ = bench_blend.score_crop(prior, colour, packed, [1], 4, rules, jpeg=50)
    # both LR crops as a quality-50 file holds them, deblocked with its tables
    want = standard_quant(50)
    assert len(seen) == 2 and all(
        all((a == b).all() for a, b in zip(q.tables, want.tables, strict=True)) for _, q in seen
    )
    assert (seen[0][0] == low_res(colour, 4, 50)).all() and (
        seen[1][0] == low_res(packed, 4, 50)
    ).all()
    # each check sees the deblocked map and is told the map as stored
    assert len(checked) == 2
    for (lr, stored), (pixels, quant) in zip(checked, seen, strict=True):
        assert (stored == pixels).all() and (lr == deblock(pixels, quant)).all()
    assert clean[0]["gain"]["guided"] != jpeg[0]["gain"]["guided"]
    code, err = run_cli(
        ["bench", "blend", "-o", str(tmp_path), "--textures", str(folder), "--prior", "bicubic"]
        + [
            "--scale",
            "2",
            "--size",
            "128",
            "--jpeg",
            "60",
            "--network-db",
            "0.1",
            "--pick-db",
            "off",
        ],
        capfd,
    )
    assert code == 0, err
    saved = json.loads((tmp_path / "blend.json").read_text())
    assert saved["jpeg"] == 60 and "JPEG quality 60 4:4:4, deblocked" in markdown_table(saved)
    assert saved["rules"] == ["margin 0, networks 0.1", "margin 0.1, networks 0.1"]
