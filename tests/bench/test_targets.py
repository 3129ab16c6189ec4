"""The targets of the texture priors and the optimiser, read off a bench run's rows
(pbrsr_bench/targets.py) and published with its summary at x4."""

from __future__ import annotations

import json

from pbrsr_bench.targets import targets, targets_table
from pbrsr_bench.upscale import published_summary, results_text, targets_text
from pbrsr_core.options import DEFAULT_PRIOR


def _row(asset, method, render, **maps):
    return {
        "asset": asset,
        "method": method,
        "render.psnr": render,
        **{f"maps.{m}.psnr": v for m, v in maps.items()},
        "run_s": 1.0,
        "peak_rss_mib": 100.0,
        "curve": [],
    }


def _rows(balanced_b: float = 31.2, metal: float = 40.0) -> list[dict]:
    return [
        _row("a", "bicubic", 28.0, albedo=30.0, emissive=40.0),
        _row("a", "direct@waifu2x-photo", 29.0, albedo=31.0, emissive=41.0),
        _row("a", "direct", 29.8, albedo=32.0, emissive=39.95, normal=30.0, metallic=36.0),
        _row("a", "balanced", 30.0, albedo=32.0, emissive=40.0, normal=30.4, metallic=metal),
        _row("b", "bicubic", 30.0, albedo=33.0),
        _row("b", "direct@waifu2x-photo", 31.2, albedo=34.0),
        _row("b", "direct", 31.0, albedo=33.5, normal=30.0),
        _row("b", "balanced", balanced_b, albedo=33.5, normal=30.2),
        # a procedural asset is left out of every target
        _row("procedural", "bicubic", 20.0, albedo=20.0),
        _row("procedural", "direct", 10.0, albedo=5.0),
    ]


def test_each_target_is_measured_and_judged():
    got = {t["target"]: t for t in targets(_rows(), exclude=("procedural",))}
    prior = got["prior"]  # direct leads the photo prior by +0.8 on a, -0.2 on b
    assert prior["value_db"] == 0.3 and not prior["met"] and prior["assets"] == 2
    assert prior["detail"] == "ahead on 1 of 2 assets"
    maps = got["maps"]  # a's emissive is direct's worst map against bicubic
    assert maps["value_db"] == -0.05 and not maps["met"] and maps["detail"] == "a emissive"
    opt = got["optimiser"]  # balanced +0.2 and +0.2 on renders; its maps +0.4, +4.0, +0.2
    assert opt["value_db"] == 0.2 and opt["met"]  # +1.53 dB on the three maps, renders higher
    assert (
        opt["detail"]
        == "ahead on 2 of 2 assets; +1.53 dB on their 3 normal, metallic and roughness maps"
    )
    # the maps without their renders do not count: balanced's render on b drops below direct's
    opt = {t["target"]: t for t in targets(_rows(balanced_b=30.0))}["optimiser"]
    assert opt["value_db"] == -0.4 and not opt["met"]
    # the renders alone meet it
    opt = {t["target"]: t for t in targets(_rows(balanced_b=31.6, metal=36.0))}["optimiser"]
    assert opt["value_db"] == 0.4 and opt["met"]
    # the procedural rows count unless left out: direct's albedo there is 15 dB below bicubic's
    assert {t["target"]: t for t in targets(_rows())}["maps"]["value_db"] == -15.0


def test_only_the_targets_whose_methods_ran_are_given():
    rows = [r for r in _rows() if r["method"] in ("bicubic", "direct")]
    assert [t["target"] for t in targets(rows)] == ["maps"]
    assert targets([r for r in _rows() if r["method"] == "balanced"]) == []
    assert targets_table([]) == ""
    table = targets_table(_rows(), ("procedural",))
    assert "| direct >= direct@waifu2x-photo + 0.5 dB (mean render PSNR) | +0.30 dB" in table
    assert table.count("| no |") == 2 and table.count("| yes |") == 1


def test_the_summary_of_an_x4_run_states_the_targets(tmp_path):
    meta = {"prior": DEFAULT_PRIOR, "eval_res": 256, "eval_views": 40, "lights": ["a.hdr"]}
    for scale, stated in ((4, True), (2, False)):
        data = {**meta, "scale": scale, "machine": "a test CPU", "rows": _rows()}
        (tmp_path / "results.json").write_text(json.dumps(data))
        text = published_summary(tmp_path)
        assert ("The targets of the texture priors and the optimiser at x4" in text) is stated
        assert (
            "| no map of direct below bicubic on any asset | -0.05 dB (a emissive)" in text
        ) is (stated)
    assert targets_text(_rows(), 8) == ""
    # results.md and the command's printout: every row, the summary, the targets at x4
    text = results_text(_rows(), 4)
    assert "| a | direct |" in text and "| direct | 2 |" in text
    assert text.endswith(targets_text(_rows(), 4)) and "at x4" not in results_text(_rows(), 2)


def test_methods_that_ran_on_different_assets_give_no_target():
    rows = [r for r in _rows() if (r["asset"], r["method"]) != ("a", "direct")]
    rows = [
        r for r in rows if (r["asset"], r["method"]) not in {("b", "bicubic"), ("b", "balanced")}
    ]
    rows = [r for r in rows if (r["asset"], r["method"]) != ("a", "direct@waifu2x-photo")]
    # direct ran on b only, waifu2x-photo on b, bicubic and balanced on a only
    got = {t["target"]: t for t in targets(rows, exclude=("procedural",))}
    assert set(got) == {"prior"} and got["prior"]["assets"] == 1
    assert got["prior"]["value_db"] == -0.2
