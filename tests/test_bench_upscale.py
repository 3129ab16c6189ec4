"""`pbrsr bench upscale` end to end on a tiny procedural asset (no shared assets)."""

from __future__ import annotations

import json
from pathlib import Path

from pbrsr_core.bench.upscale import run


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
        say=said.append,
    )
    assert any("not present" in s for s in said)
    assert [r["method"] for r in rows] == ["fast"]
    for r in rows:
        assert r["run_s"] > 0 and r["peak_rss_mib"] > 0
        assert 5.0 < r["render.psnr"] < 100.0 and "maps.albedo.psnr" in r
    fast = rows[0]
    assert fast["curve"] and fast["curve"][0]["it"] == 0
    assert [c["seconds"] for c in fast["curve"]] == sorted(c["seconds"] for c in fast["curve"])
    saved = json.loads((tmp_path / "out" / "results.json").read_text())
    assert len(saved["rows"]) == 1
    assert (tmp_path / "out" / "speed_vs_error.png").stat().st_size > 0
    assert "| procedural | fast |" in (tmp_path / "out" / "results.md").read_text()
