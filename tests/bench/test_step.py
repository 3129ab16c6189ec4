"""``pbrsr bench step`` runs the optimiser's real whole-map passes and writes its outputs."""

from __future__ import annotations

import json

import pytest
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
        # the floor: Adam's 8 float32 arrays per optimised value at the measured copy rate
        moved = FLOOR_ARRAYS * 4 * 2 * r["size"] ** 2 * 3  # bytes: 2 maps of 3 channels
        floor_ms = moved / (r["copy_gb_s"] * 1e9) * 1e3
        assert r["floor_ms"] == pytest.approx(floor_ms, rel=0.06, abs=2e-3)
        assert r["total_ms"] == pytest.approx(sum(r[f"{k}_ms"] for k in PASSES), abs=0.05)
        assert r["over_floor"] == pytest.approx(r["total_ms"] / r["floor_ms"], rel=0.1)
    assert (out / "step.png").stat().st_size > 1000
    assert "optimiser step, whole-map part" in res.output


def test_copy_bandwidth_is_bytes_read_and_written_over_the_fastest_copy(monkeypatch):
    import math

    from pbrsr_bench import step

    bw = copy_bandwidth(1 << 20)
    assert math.isfinite(bw) and bw > 0  # a real copy's rate; its size depends on the load
    # each copy reads and writes numel float32 values; the fastest of the repeats counts
    ticks = iter([0.0, 0.004, 1.0, 1.002, 2.0, 2.003])
    monkeypatch.setattr(step.time, "perf_counter", lambda: next(ticks))
    assert copy_bandwidth(1000, repeats=3) == pytest.approx(2 * 4 * 1000 / 0.002)
