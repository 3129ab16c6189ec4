"""``pbrsr bench service`` on a tiny run: a bicubic job through real API and worker processes
with a private Redis against ``pbrsr upscale`` in a subprocess, and one job on one worker in
each batch; the ratios come from the measured times."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from pbrsr_bench import cli as bench
from pbrsr_bench.service import print_table, run
from tests.service_support import require_redis_server

pytestmark = pytest.mark.slow


def test_bench_service_refuses_bad_input_before_starting_anything(tmp_path: Path):
    app = typer.Typer()
    bench.register(app)
    runner = CliRunner()
    out = tmp_path / "out"
    r = runner.invoke(app, ["bench", "service", "-o", str(out), "-a", "no-such-asset"])
    assert r.exit_code == 2 and "not found" in r.output
    r = runner.invoke(app, ["bench", "service", "-o", str(out), "--preset", "no-such-preset"])
    assert r.exit_code == 2 and "preset" in r.output
    assert not (out / "service.json").exists()


def test_a_tiny_service_run_times_the_cli_and_both_batches(tmp_path: Path, capsys):
    require_redis_server()
    out = tmp_path / "out"
    result = run(
        out,
        method="bicubic",
        scale=2,
        procedural_size=32,
        workers=1,
        jobs=1,
        duration=0,
        shared=tmp_path / "no-shared-assets",
    )
    assert result["config"]["private_redis"] is True and "mixed" not in result
    single = result["single"]
    assert single["service_seconds"] > single["service_pipeline_seconds"] > 0
    assert single["cli_seconds"] > single["cli_pipeline_seconds"] > 0
    assert single["ratio"] == pytest.approx(single["service_seconds"] / single["cli_seconds"])
    assert single["met"] == (single["ratio"] <= single["target"])
    # the CLI ran with the threads the worker chose for the service's run
    assert single["cli_threads"] == single["service_threads"] >= 1
    for name in ("sequential", "parallel"):
        batch = result[name]
        assert batch["workers"] == 1 and batch["outcomes"] == ["succeeded"]
        assert batch["seconds"] == batch["done_seconds"][-1] > batch["pipeline_seconds"][0] > 0
        assert batch["threads"][0] >= 1
        assert batch["jobs_per_minute"] == pytest.approx(60 / batch["seconds"])
    tp = result["throughput"]
    seq, par = result["sequential"], result["parallel"]
    assert tp["ratio"] > 0
    assert tp["ratio"] == pytest.approx(par["jobs_per_minute"] / seq["jobs_per_minute"])
    assert tp["met"] == (tp["ratio"] >= tp["target"])
    assert result["ok"] is True
    saved = json.loads((out / "service.json").read_text())
    assert saved["single"]["ratio"] == pytest.approx(single["ratio"]) and saved["ok"] is True
    assert (out / "service.png").stat().st_size > 1000
    print_table(result)
    printed = capsys.readouterr().out
    assert "service / CLI" in printed and "PASS" in printed
