"""The per-map table of a run (pbrsr_core.map_table): from real runs' reports, and as the
CLI prints it."""

from __future__ import annotations

import re

from pbrsr_core.map_table import made_by_text, map_rows
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from tests.clirun import run_cli_output
from tests.core.test_pipeline import three_sizes


def test_made_by_text_names_each_channel_only_where_they_differ():
    assert made_by_text(["pbr-srmd"]) == "pbr-srmd"
    assert made_by_text(["bicubic"] * 3) == "bicubic (each channel)"
    assert made_by_text(["bicubic", "a", "bicubic (flat)"]) == "R: bicubic; G: a; B: bicubic (flat)"


def test_rows_of_a_run_with_a_kept_map_and_consistency(tmp_path):
    """x4 with max_size 32 and two steps: the 32² albedo kept, the normal map at x2, the data
    map at x4; every row says what made it and its consistency PSNR."""
    src = three_sizes(tmp_path)
    options = UpscaleOptions(prior="bicubic", iterations=2, max_size=32)
    rows = map_rows(upscale_asset(src, tmp_path / "o", options))
    assert [(r["index"], r["scale"], r["size"]) for r in rows] == [
        (0, 1, [32, 32]),
        (1, 2, [32, 32]),
        (2, 4, [32, 32]),
    ]
    assert rows[0]["made_by"] == ["kept (max_size)"] and rows[0]["consistency_db"] == {}
    assert rows[1]["made_by"] == ["bicubic"] and rows[1]["label"] == "normal"
    assert rows[2]["made_by"] == ["bicubic"] * 3
    assert rows[2]["made_from"] == "bicubic (each channel)"
    assert set(rows[2]["consistency_db"]) == {"roughness", "metallic"}
    assert all(db > 20 for r in rows[1:] for db in r["consistency_db"].values())


def test_direct_names_each_maps_network(tmp_path):
    """pbr-srmd's networks by kind (a normal map's picked between its normal network and
    waifu2x-photo, never bicubic); a data map the check sees (64², at x2 one scale down)
    named per channel, the one no material reads (R: no occlusion role) bicubic."""
    src = three_sizes(tmp_path, 64)
    report = upscale_asset(src, tmp_path / "o", UpscaleOptions(method="direct"))
    by_index = {r["index"]: r["made_by"] for r in map_rows(report)}
    assert by_index[1] in (["pbr-srmd[normal]"], ["waifu2x-photo"])
    colour = ("pbr-srmd", "pbr-srmd[colour/x2]", "waifu2x-photo", "bicubic", "bicubic (flat)")
    assert by_index[0][0] in colour
    assert len(by_index[2]) == 3 and by_index[2][0] == "bicubic"
    assert all(m in ("pbr-srmd[data]", "waifu2x-photo", "bicubic") for m in by_index[2][1:])


def test_the_cli_prints_the_table(tmp_path, capfd, monkeypatch):
    from pbrsr_core.cli import upscale as upscale_cli

    monkeypatch.setattr(upscale_cli.console, "width", 160)  # a row per line
    src = three_sizes(tmp_path)
    args = ["upscale", str(src), "--method", "bicubic", "--overwrite", "-o", str(tmp_path / "o")]
    code, out, err = run_cli_output([*args, "--max-size", "32"], capfd)
    assert code == 0, err
    table = out[out.index("maps") : out.index("stage timings")]
    lines = [line for line in table.splitlines() if re.search(r"base_color|normal|metallic", line)]
    assert len(lines) == 3, table
    assert "32² kept" in lines[0] and "kept (max_size)" in lines[0]
    assert "16² x2 = 32²" in lines[1] and "bicubic" in lines[1]
    assert "8² x4 = 32²" in lines[2] and "bicubic" in lines[2]
    code, out, err = run_cli_output([*args, "--maps", "normal, metallic_roughness"], capfd)
    assert code == 0, err
    table = out[out.index("maps") : out.index("stage timings")]
    lines = [line for line in table.splitlines() if re.search(r"base_color|normal|metallic", line)]
    assert "32² kept" in lines[0] and "kept (maps)" in lines[0], table
    assert "16² x4 = 64²" in lines[1] and "8² x4 = 32²" in lines[2]
