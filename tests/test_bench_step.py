"""``pbrsr bench step`` runs the optimiser's real whole-map passes and writes its outputs."""

from __future__ import annotations

import json

import typer
from typer.testing import CliRunner

from pbrsr_bench import cli as bench
from pbrsr_bench.step import FLOOR_ARRAYS, PASSES, copy_bandwidth


def test_bench_step_cli_writes_table_json_and_plot(tmp_path):
    out = tmp_path / "step"
    app = typer.Typer()
    bench.register(app)
    res = CliRunner().invoke(
        app, ["bench", "step", "-o", str(out), "--sizes", "64,128", "--images", "2", "--steps", "2"]
    )
    assert res.exit_code == 0, res.output
    data = json.loads((out / "step.json").read_text())
    assert [r["size"] for r in data["rows"]] == [64, 128]
    for r in data["rows"]:
        assert r["values_m"] == round(2 * r["size"] ** 2 * 3 / 1e6, 2)
        assert all(r[f"{k}_ms"] >= 0 for k in PASSES)
        assert r["floor_ms"] > 0 and r["copy_gb_s"] > 0
    assert (out / "step.png").stat().st_size > 1000
    assert "optimiser step, whole-map part" in res.output


def test_floor_counts_eight_arrays_at_copy_bandwidth():
    bw = copy_bandwidth(1 << 20)
    assert 1e8 < bw < 1e13  # bytes/s of a real copy: between 0.1 GB/s and 10 TB/s
    assert FLOOR_ARRAYS == 8
