"""`pbrsr bench paper`: a real sample of the paper preset, extrapolated stage by stage."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from pbrsr_bench import cli as bench
from pbrsr_bench.paper import extrapolate, run
from pbrsr_core.optim.presets import PAPER


def test_extrapolate_scales_each_stage_by_its_unit():
    t = {"load": 1.0, "init": 4.0, "gbuffers": 2.0, "pseudo_gt": 3.0, "optimize": 5.0}
    full = extrapolate(t, view_factor=25.0, step_factor=100.0)
    assert full == {
        "load": 1.0,
        "init": 4.0,
        "gbuffers": 50.0,
        "pseudo_gt": 75.0,
        "optimize": 500.0,
    }


def test_bench_paper_sample_runs_the_paper_preset(tmp_path: Path):
    said: list[str] = []
    result = run(
        out_dir=tmp_path / "out",
        elev=1,
        azim=2,
        iterations=2,
        prior="bicubic",
        procedural_size=64,
        shared=tmp_path / "no-shared-assets",
        log=said.append,
    )
    s, f = result["sample"], result["full"]
    assert s["views"] == 2 and s["views_seeing_mesh"] == 2 and s["iterations"] == 2
    # the G-buffer cache is cut by the views' fraction
    assert s["gbuffer_cache_mb"] == round(PAPER.gbuffer_cache_mb * 2 / 750)
    # the sample ran its steps: the loss history ends at its last one
    assert s["history"] and s["history"][-1]["it"] == 2
    assert all(k in s["timings"] for k in ("gbuffers", "pseudo_gt", "optimize", "init"))
    assert f["views"] == 750 and f["iterations"] == 2000
    assert f["timings"]["pseudo_gt"] == pytest.approx(s["timings"]["pseudo_gt"] * 375)
    assert f["timings"]["optimize"] == pytest.approx(s["timings"]["optimize"] * 1000)
    assert f["timings"]["load"] == pytest.approx(s["timings"]["load"])
    assert f["run_s"] > s["run_s"] > 0 and s["peak_rss_mib"] > 0
    # one 1024² RGB pseudo-GT per view, at least 8 bits per channel
    assert s["pseudo_gt_bytes"] >= 2 * 1024 * 1024 * 3
    assert f["pseudo_gt_bytes"] == round(s["pseudo_gt_bytes"] * 375)
    saved = json.loads((tmp_path / "out" / "paper.json").read_text())
    assert saved["full"]["run_s"] == pytest.approx(f["run_s"])
    assert (tmp_path / "out" / "paper.png").stat().st_size > 0


def test_bench_paper_cli_refuses_bad_input(tmp_path: Path):
    app = typer.Typer()
    bench.register(app)
    runner = CliRunner()
    r = runner.invoke(app, ["bench", "paper", "-o", str(tmp_path), "--elev", "0"])
    assert r.exit_code == 2
    r = runner.invoke(app, ["bench", "paper", "-o", str(tmp_path), "-a", "no-such-asset"])
    assert r.exit_code == 2 and "not found" in r.output
