"""The memory estimate a worker checks a job against, before anything is allocated."""

from __future__ import annotations

import pytest

from pbrsr_core.errors import LimitExceeded
from pbrsr_core.footprint import (
    MIB,
    available_bytes,
    check_memory,
    estimate_peak_bytes,
    memory_budget,
)
from pbrsr_core.optim.presets import get_preset

# peak RSS (MiB) of `pbrsr upscale`'s process (/usr/bin/time -f %M, 2 cores, about 20 GiB
# free) on the Avocado degraded to three 512² RGB maps (`pbrsr degrade --scale 4`), x4:
# `--method bicubic`, `--preset fast`, `--method direct`, `--preset balanced`, `--preset
# quality`, and `--preset quality --iterations 25` (STEPS)
AVOCADO = [(512, 512, 3)] * 3
MEASURED = {"bicubic": 1014, "fast": 1349, "direct": 2743, "balanced": 2696, "quality": 3178}
STEPS = 3194
# larger maps, the same way: the cabinet's three 1024² maps at x4 (ph_painted_wooden_cabinet
# as shared), the Avocado's three 2048² maps at x2 and the BoomBox's four 2048² (and one 32²)
# at x2
LARGE = [
    ([(1024, 1024, 3)] * 3, 4, "bicubic", 2245),
    ([(1024, 1024, 3)] * 3, 4, "fast", 3961),
    ([(1024, 1024, 3)] * 3, 4, "direct", 3367),
    ([(1024, 1024, 3)] * 3, 4, "balanced", 4496),
    ([(2048, 2048, 3)] * 3, 2, "direct", 3306),
    ([(2048, 2048, 3)] * 3, 2, "balanced", 4209),
    ([(2048, 2048, 3)] * 4 + [(32, 32, 3)], 2, "fast", 5336),
]


def _estimate(method: str) -> int:
    if method in ("bicubic", "direct"):
        return estimate_peak_bytes(AVOCADO, 4, method)
    return estimate_peak_bytes(AVOCADO, 4, "pbrsr", get_preset(method))


@pytest.mark.parametrize("method", sorted(MEASURED))
def test_the_estimate_is_above_the_measured_peak_and_not_far_above(method):
    estimate = _estimate(method) / MIB
    assert MEASURED[method] <= estimate <= 2.0 * MEASURED[method], estimate


@pytest.mark.parametrize(("sizes", "scale", "method", "peak"), LARGE)
def test_the_estimate_is_above_the_peak_of_large_maps_and_not_far_above(sizes, scale, method, peak):
    meth, config = (method, None) if method in ("bicubic", "direct") else ("pbrsr", method)
    estimate = estimate_peak_bytes(sizes, scale, meth, config and get_preset(config)) / MIB
    assert peak <= estimate <= 1.7 * peak, estimate


def test_the_estimate_with_steps_is_above_the_measured_peak():
    estimate = estimate_peak_bytes(AVOCADO, 4, "pbrsr", get_preset("quality").with_(iterations=25))
    assert STEPS <= estimate / MIB <= 2.0 * STEPS, estimate / MIB


def test_more_output_costs_more():
    sizes = [(256, 256, 3)]
    for method in ("bicubic", "direct"):
        x2, x4 = (estimate_peak_bytes(sizes, s, method) for s in (2, 4))
        assert x2 < x4
    assert _estimate("bicubic") < _estimate("fast") < _estimate("direct") <= _estimate("quality")
    steps = get_preset("quality").with_(iterations=25)
    assert _estimate("quality") < estimate_peak_bytes(AVOCADO, 4, "pbrsr", steps)


def test_a_run_over_the_budget_is_refused_with_what_to_do():
    check_memory(10 * MIB, None, "anything")  # no budget known: no check
    check_memory(10 * MIB, 10 * MIB, "anything")
    with pytest.raises(LimitExceeded, match=r"x8 of 3 maps needs about 1\.5 GiB .* has 1\.0 GiB"):
        check_memory(1536 * MIB, 1024 * MIB, "x8 of 3 maps")


def test_the_budget_is_the_setting_or_what_the_machine_has():
    assert memory_budget(512) == 512 * MIB
    have = available_bytes()
    assert have is not None and 64 * MIB < have < 2**50
    auto = memory_budget(0)
    assert auto is not None and abs(auto - have) < 512 * MIB  # read again a moment later


def test_the_pipeline_refuses_before_writing_anything(tmp_path):
    from pbrsr_core.asset import make_demo_asset
    from pbrsr_core.options import UpscaleOptions
    from pbrsr_core.pipeline import upscale_asset

    src = make_demo_asset(tmp_path / "demo.glb", size=32)
    out = tmp_path / "out"
    options = UpscaleOptions(scale=2, method="bicubic")
    with pytest.raises(LimitExceeded, match="x2 of 3 maps"):
        upscale_asset(src, out, options, memory_budget=100 * MIB)
    assert not out.exists() or not any(out.iterdir())
    report = upscale_asset(src, out, options, memory_budget=available_bytes())
    assert report["images"]


def test_max_size_counts_each_map_at_its_own_factor(tmp_path):
    """x8 of the demo's 32² maps is refused under a budget that x2 (what max_size 64 leaves
    of it) fits in, and runs with max_size."""
    from pbrsr_core.asset import load_asset, make_demo_asset
    from pbrsr_core.options import UpscaleOptions
    from pbrsr_core.pipeline import upscale_asset

    src = make_demo_asset(tmp_path / "demo.glb", size=32)
    sizes = [(i.width, i.height, i.pixels.shape[2]) for i in load_asset(src).images if i.roles]
    assert {w for w, _, _ in sizes} == {32}
    budget = (
        estimate_peak_bytes(sizes, 2, "bicubic") + estimate_peak_bytes(sizes, 8, "bicubic")
    ) // 2
    with pytest.raises(LimitExceeded, match="x8 of 3 maps"):
        upscale_asset(
            src, tmp_path / "a", UpscaleOptions(scale=8, method="bicubic"), memory_budget=budget
        )
    options = UpscaleOptions(scale=8, method="bicubic", max_size=64)
    report = upscale_asset(src, tmp_path / "b", options, memory_budget=budget)
    assert [i["hr_size"] for i in report["images"]] == [[64, 64]] * 3
