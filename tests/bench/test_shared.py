"""The one setting that says where the benchmarks find the shared assets."""

from __future__ import annotations

from pathlib import Path

from pbrsr_bench import fuzz, prior, render, upscale
from pbrsr_bench.shared import SHARED_ASSETS, shared_assets_dir


def test_the_variable_names_the_folder_else_the_one_beside_the_repository(monkeypatch, tmp_path):
    monkeypatch.setenv("PBRSR_SHARED_ASSETS", str(tmp_path))
    assert shared_assets_dir() == tmp_path
    monkeypatch.delenv("PBRSR_SHARED_ASSETS")
    repo = Path(__file__).resolve().parents[2]
    assert shared_assets_dir() == repo.parent / "shared" / "assets"


def test_every_benchmark_reads_the_same_setting():
    for module in (fuzz, prior, render, upscale):
        assert module.SHARED_ASSETS is SHARED_ASSETS
