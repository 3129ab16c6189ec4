"""The upscale pipeline end to end on small procedural assets: bundle layout, report, the
output asset's validity and sizes, and baseline methods against their definitions."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import (
    load_asset,
    make_demo_asset,
    make_quad_asset,
    make_test_asset,
    read_image,
    validate_gltf,
)
from pbrsr_core.errors import InvalidOptions, LimitExceeded, StorageError, UnprocessableAsset
from pbrsr_core.limits import Limits
from pbrsr_core.map_table import map_rows
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.direct import bicubic_map, project_map, upscale_map


class Nearest(Prior):
    """A back-projecting "network" (nearest upsampling, x2 and x4) that records the input
    side and the factor of every call."""

    name = "nearest"
    scales = (2, 4)

    def __init__(self):
        super().__init__()
        self.calls: list[tuple[int, int]] = []

    def _forward(self, x, scale):
        self.calls.append((x.shape[-1], scale))
        return F.interpolate(x, scale_factor=scale, mode="nearest")


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    return make_demo_asset(tmp_path_factory.mktemp("demo") / "demo.glb", size=32)


def test_bicubic_bundle(demo: Path, tmp_path: Path):
    events = []
    report = upscale_asset(
        demo, tmp_path / "out", UpscaleOptions(method="bicubic", scale=2), progress=events.append
    )
    out = tmp_path / "out"
    assert (out / "demo.glb").is_file() and (out / "report.json").is_file()
    assert (out / "preview.png").is_file()
    for name in report["previews"].values():
        assert (out / name).is_file()
    assert json.loads((out / "report.json").read_text())["input"] == "demo.glb"
    assert report["threads"] == torch.get_num_threads()  # what the run used
    assert {e.stage for e in events} >= {"load", "export", "done"}
    src, res = load_asset(demo), load_asset(out / "demo.glb")
    for img in src.images:
        if not img.roles:
            continue
        hr = res.images[img.index]
        assert (hr.width, hr.height) == (2 * img.width, 2 * img.height)
        assert hr.bit_depth >= img.bit_depth
        map_file = (
            out / report["images"][[i["index"] for i in report["images"]].index(img.index)]["file"]
        )
        # maps/ holds the same image as the asset (the same encoded PNG where formats agree)
        assert np.array_equal(read_image(map_file.read_bytes(), map_file.name)[0], hr.pixels)
        kind = "normal" if "normal" in img.roles else "data"
        if kind == "data":  # bicubic maps round-trip through 8-bit PNG exactly as computed
            ref = bicubic_map(img.pixels, kind, 2)
            assert np.abs(hr.pixels - ref).max() <= 1.0 / 255 + 1e-6
    assert validate_gltf(out / "demo.glb")["numErrors"] == 0
    # nothing but the bundle is left beside it (the staging folder was renamed into place)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_gltf_keeps_form_and_direct_with_bicubic_prior(tmp_path: Path):
    src = make_test_asset(tmp_path / "in" / "a.gltf", size=16, kind="gltf")
    rb = upscale_asset(src, tmp_path / "b", UpscaleOptions(method="bicubic", scale=2))
    rd = upscale_asset(
        src, tmp_path / "d", UpscaleOptions(method="direct", prior="bicubic", scale=2)
    )
    assert (tmp_path / "d" / "a.gltf").is_file()
    assert validate_gltf(tmp_path / "d" / "a.gltf")["numErrors"] == 0
    b, d = load_asset(tmp_path / "b" / "a.gltf"), load_asset(tmp_path / "d" / "a.gltf")
    for ib, idd in zip(b.images, d.images, strict=True):  # same prior: same maps
        assert ib.pixels.shape == idd.pixels.shape
        assert np.abs(ib.pixels - idd.pixels).max() <= 2.0 / 255
    assert [i["hr_size"] for i in rb["images"]] == [i["hr_size"] for i in rd["images"]]


def test_direct_inverts_the_lr_model_the_options_name(tmp_path: Path):
    """An asset whose maps were made smaller by the area kernel: with ``lr_kernel`` "area",
    each map a network made in both runs and left off its LR map, downsampled by that kernel,
    comes closer to its LR map than with the protocol's model (back-projection inverts the
    model it is given); the report records the option, and after the run the protocol's model
    holds again."""
    from pbrsr_core.degrade import degrade_asset, degrade_image, run_kernel

    hr = make_test_asset(tmp_path / "hr.glb", size=64)
    src = degrade_asset(hr, tmp_path / "lr" / "a.glb", 4, image_format="png16", kernel="area")[0]
    lr = load_asset(src)
    err, made_by = {}, {}
    for kernel in ("gaussian", "area"):
        options = UpscaleOptions(method="direct", scale=4, lr_kernel=kernel)
        report = upscale_asset(src, tmp_path / kernel, options)
        assert report["options"]["lr_kernel"] == kernel and run_kernel() == "gaussian"
        made_by[kernel] = [img["made_by"] for img in report["images"]]
        out = load_asset(tmp_path / kernel / "a.glb")
        err[kernel] = [
            np.abs(
                degrade_image(o.pixels, 4, kernel="area", normal_map="normal" in i.roles) - i.pixels
            ).mean()
            for o, i in zip(out.images, lr.images, strict=True)
        ]
    # each map a network made in both runs and left more than a level from its LR map under
    # the protocol's model (waifu2x-photo's pick of the 16² normal map is within half a level
    # under either model: nothing for the step to correct)
    networks = [
        i
        for i, (a, b) in enumerate(zip(made_by["gaussian"], made_by["area"], strict=True))
        if "bicubic" not in a + b and err["gaussian"][i] > 1 / 255
    ]
    assert len(networks) >= 2, (made_by, err)  # the data maps at least
    for i in networks:
        assert err["area"][i] < 0.7 * err["gaussian"][i], (i, err)


def test_auto_runs_the_kernel_the_maps_point_to_and_the_report_says_so(tmp_path: Path):
    """lr_kernel "auto": the run estimates the kernel from the LR maps (what
    ``estimate_kernel`` says of them), records it, and gives the maps a run told that kernel
    gives; maps too small to tell leave the protocol's model, not marked estimated."""
    from pbrsr_core.degrade import degrade_asset
    from pbrsr_core.kernel_estimate import estimate_kernel

    hr = make_test_asset(tmp_path / "hr.glb", size=512)
    src = degrade_asset(hr, tmp_path / "lr" / "a.glb", 4, image_format="png16", kernel="area")[0]
    want = estimate_kernel([img.pixels for img in load_asset(src).images if img.roles])
    assert want.maps >= 2
    auto = upscale_asset(src, tmp_path / "auto", UpscaleOptions(method="direct", lr_kernel="auto"))
    assert auto["options"]["lr_kernel"] == "auto"
    assert auto["lr_model"] == want.to_json() and auto["lr_model"]["estimated"] is True
    assert "lr_kernel" in auto["timings"]
    told_opts = UpscaleOptions(method="direct", lr_kernel=want.kernel)
    told = upscale_asset(src, tmp_path / "told", told_opts)
    assert told["lr_model"] == {"kernel": want.kernel, "estimated": False}
    for a, b in zip(load_asset(tmp_path / "auto" / "a.glb").images,
                    load_asset(tmp_path / "told" / "a.glb").images, strict=True):  # fmt: skip
        assert np.array_equal(a.pixels, b.pixels)

    small = make_test_asset(tmp_path / "small.glb", size=64)  # LR maps of 32 texels
    lr_small = degrade_asset(small, tmp_path / "lr" / "s.glb", 2, image_format="png16")[0]
    rep = upscale_asset(
        lr_small, tmp_path / "s", UpscaleOptions(method="bicubic", lr_kernel="auto")
    )
    assert rep["lr_model"]["kernel"] == "gaussian" and rep["lr_model"]["estimated"] is False


def test_the_report_names_the_precision_each_map_kind_ran_in(tmp_path: Path, set_runtime):
    from pbrsr_core.prior.base import native_int8

    src = make_test_asset(tmp_path / "in" / "a.gltf", size=16, kind="gltf")
    options = UpscaleOptions(method="direct", prior="pbr-srmd", scale=4)
    set_runtime(prior_precision="fp32")
    full = upscale_asset(src, tmp_path / "fp32", options)
    kinds = set(full["prior_precision"])
    assert kinds >= {"colour", "normal"} and set(full["prior_precision"].values()) == {"fp32"}
    set_runtime(prior_precision="int8")
    report = upscale_asset(src, tmp_path / "int8", options)
    # pbr-srmd's SRMD networks (colour and normal maps at x4) are calibrated; its data network
    # is UpConv7, which stays float32; without VNNI or AMX everything runs in float32
    native = native_int8(torch.device("cpu"))
    want = {k: "int8" if native and k in ("colour", "normal") else "fp32" for k in kinds}
    assert report["prior_precision"] == want
    a, b = load_asset(tmp_path / "fp32" / "a.gltf"), load_asset(tmp_path / "int8" / "a.gltf")
    for x, y in zip(a.images, b.images, strict=True):
        top = 2**x.bit_depth - 1
        diff = np.abs(x.pixels.astype(np.float64) - y.pixels.astype(np.float64)) / top
        assert diff.max() <= 0.1 and diff.mean() < 0.01


@pytest.mark.parametrize(
    ("preset", "iterations"), [("fast", None), ("balanced", None), ("quality", None), ("fast", 3)]
)
def test_pbrsr_method_runs_and_reports(demo: Path, tmp_path: Path, preset: str, iterations):
    """The CPU presets are PBR-SR's init and export; ``iterations`` adds optimiser steps over
    the preset's views."""
    options = UpscaleOptions(method="pbrsr", preset=preset, prior="bicubic", iterations=iterations)
    report = upscale_asset(demo, tmp_path / "out", options)
    assert set(report["timings"]) >= {"load", "init", "project", "dilate", "preview"}
    assert report["consistency_psnr_db"]
    stages = {"gbuffers", "pseudo_gt", "optimize"}
    if iterations is None:  # no optimisation steps
        assert report["num_views"] == 0 and report["history"] == []
        assert not stages & set(report["timings"])
    else:
        assert report["config"]["iterations"] == iterations
        assert report["num_views"] >= 1 and report["history"]
        assert set(report["timings"]) >= stages
    res = load_asset(tmp_path / "out" / "demo.glb")
    for img in res.images:
        assert np.isfinite(img.pixels).all()
        assert img.pixels.min() >= 0.0 and img.pixels.max() <= 1.0


def test_iterations_are_checked():
    from pydantic import ValidationError

    for bad in (-1, 100_001, "many"):
        with pytest.raises(ValidationError, match="iterations"):
            UpscaleOptions(iterations=bad)


def test_nothing_to_upscale_leaves_nothing(tmp_path: Path):
    src = make_quad_asset(tmp_path / "q" / "quad.gltf", size=8)
    doc = json.loads(src.read_text())
    for m in doc.get("materials", []):  # keep factors, drop every texture slot
        for key in ("normalTexture", "occlusionTexture", "emissiveTexture"):
            m.pop(key, None)
        for key in ("baseColorTexture", "metallicRoughnessTexture"):
            m.get("pbrMetallicRoughness", {}).pop(key, None)
    src.write_text(json.dumps(doc))
    with pytest.raises(UnprocessableAsset, match="nothing to upscale"):
        upscale_asset(src, tmp_path / "o1", UpscaleOptions(method="bicubic"))
    assert not (tmp_path / "o1").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["q"]


def test_output_limit_and_non_empty_out(demo: Path, tmp_path: Path):
    with pytest.raises(LimitExceeded, match="output limit"):
        upscale_asset(
            demo,
            tmp_path / "o",
            UpscaleOptions(method="bicubic", scale=8),
            limits=Limits(max_output_dim=128),
        )
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep me")
    with pytest.raises(StorageError, match="not empty"):
        upscale_asset(demo, tmp_path / "full", UpscaleOptions(method="bicubic"))
    assert (tmp_path / "full" / "x").read_text() == "keep me"


def _quad_with_prior(tmp_path: Path, monkeypatch, seed: int) -> tuple[Nearest, Path, np.ndarray]:
    """A quad asset with a 32² albedo, a :class:`Nearest` prior the pipeline loads by the name
    "n", and the albedo as stored (8-bit rounded)."""
    import pbrsr_core.pipeline as pipeline

    prior = Nearest()
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior if n == "n" else real(n, d))
    rng = np.random.default_rng(seed)
    tex = np.clip(rng.random((32, 32, 3)) * 0.6 + 0.2, 0, 1).astype(np.float32)
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": tex})
    return prior, asset, load_asset(asset).images[0].pixels


def test_project_lr_back_projects_what_the_prior_initialised(tmp_path, monkeypatch):
    from pbrsr_core.optim import presets

    prior, asset, lr = _quad_with_prior(tmp_path, monkeypatch, seed=4)
    frozen = presets.FAST.with_(iterations=0, check_prior=(), max_prior_scale=None)
    init = upscale_map(prior, lr, "base_color", 4)
    expected = {(): init, ("colour",): project_map(init, lr, 4, "base_color")}
    assert np.abs(expected[("colour",)] - init).max() > 0.01  # the step does something
    for kinds, want in expected.items():
        monkeypatch.setitem(presets.PRESETS, "fast", frozen.with_(project_lr=kinds))
        out = tmp_path / f"out{len(kinds)}"
        report = upscale_asset(asset, out, UpscaleOptions(preset="fast", prior="n"))
        assert "project" in report["timings"]
        got = load_asset(out / "q.gltf").images[0].pixels
        assert np.abs(got - want).max() <= 0.6 / 255, kinds
    # a map bicubic initialised is not projected (bicubic is not an LR-consistent init)
    monkeypatch.setitem(presets.PRESETS, "fast", frozen.with_(project_lr=("colour",)))
    upscale_asset(asset, tmp_path / "bic", UpscaleOptions(preset="fast", prior="bicubic"))
    got = load_asset(tmp_path / "bic" / "q.gltf").images[0].pixels
    assert np.abs(got - bicubic_map(lr, "base_color", 4)).max() <= 0.6 / 255
    with pytest.raises(InvalidOptions, match="project_lr"):
        frozen.with_(project_lr=("albedo",))


def test_max_prior_scale_reaches_the_init_and_the_self_check(tmp_path, monkeypatch):
    """fast's prior runs x2 of the x4 (bicubic the rest, then projected onto its input), in
    the self-check, the init and the pseudo-GT alike."""
    from pbrsr_core.optim import presets
    from pbrsr_core.prior import selfcheck

    prior, asset, lr = _quad_with_prior(tmp_path, monkeypatch, seed=5)
    assert presets.FAST.max_prior_scale == 2 and presets.BALANCED.max_prior_scale is None
    frozen = presets.FAST.with_(iterations=0, project_lr=(), check_prior=())
    monkeypatch.setitem(presets.PRESETS, "fast", frozen)
    upscale_asset(asset, tmp_path / "a", UpscaleOptions(preset="fast", prior="n"))
    assert prior.calls == [(32, 2)]  # the init: x2
    got = load_asset(tmp_path / "a" / "q.gltf").images[0].pixels
    want = upscale_map(Nearest(), lr, "base_color", 4, max_prior_scale=2)
    assert np.abs(got - want).max() <= 0.6 / 255
    prior.calls.clear()
    checked = frozen.with_(check_prior=("colour",), iterations=1)
    monkeypatch.setitem(presets.PRESETS, "fast", checked)
    # check this 32² map at the run's x4 (by default a map this small is checked at x2)
    monkeypatch.setattr(selfcheck, "MIN_SIDE", 8)
    report = upscale_asset(asset, tmp_path / "b", UpscaleOptions(preset="fast", prior="n"))
    assert report["prior_check"][0]["texels"] == 32 * 32 and report["prior_check"][0]["scale"] == 4
    assert report["prior_check"][0]["use_prior"]
    # the check one scale down, the init and the pseudo-GT of the rendered views: x2
    assert prior.calls[:2] == [(8, 2), (32, 2)]
    assert len(prior.calls) > 2 and {f for _, f in prior.calls[2:]} == {2}
    # and the whole scale where the preset does not limit it
    prior.calls.clear()
    monkeypatch.setitem(presets.PRESETS, "fast", checked.with_(max_prior_scale=None))
    upscale_asset(asset, tmp_path / "c", UpscaleOptions(preset="fast", prior="n"))
    assert {f for _, f in prior.calls} == {4}
    with pytest.raises(InvalidOptions, match="max_prior_scale"):
        frozen.with_(max_prior_scale=1)


def test_pseudo_gt_prior_makes_the_render_targets(tmp_path, monkeypatch):
    """pseudo_gt_prior: the init comes from the run's prior, the pseudo-GT from the one named
    (bicubic: the HR renders of the init maps)."""
    from pbrsr_core.optim import presets

    prior, asset, _ = _quad_with_prior(tmp_path, monkeypatch, seed=6)
    one_step = presets.FAST.with_(iterations=1, check_prior=(), max_prior_scale=None)
    monkeypatch.setitem(presets.PRESETS, "fast", one_step)
    upscale_asset(asset, tmp_path / "a", UpscaleOptions(preset="fast", prior="n"))
    assert prior.calls[0] == (32, 4) and len(prior.calls) > 1  # init, then the renders
    prior.calls.clear()
    monkeypatch.setitem(presets.PRESETS, "fast", one_step.with_(pseudo_gt_prior="bicubic"))
    report = upscale_asset(asset, tmp_path / "b", UpscaleOptions(preset="fast", prior="n"))
    assert prior.calls == [(32, 4)] and report["config"]["pseudo_gt_prior"] == "bicubic"
    with pytest.raises(InvalidOptions, match="unknown prior"):
        one_step.with_(pseudo_gt_prior="photo")


def test_pseudo_gt_self_ensemble_runs_the_prior_on_copies_of_each_render(tmp_path, monkeypatch):
    """pseudo_gt_self_ensemble 2: the init runs the prior once, each view's render twice (the
    identity and the half turn), and the targets are not the single copy's cached ones."""
    from pbrsr_core.optim import presets

    prior, asset, _ = _quad_with_prior(tmp_path, monkeypatch, seed=7)
    one_step = presets.FAST.with_(iterations=1, check_prior=(), max_prior_scale=None)
    calls = []
    for n in (1, 2):
        monkeypatch.setitem(presets.PRESETS, "fast", one_step.with_(pseudo_gt_self_ensemble=n))
        prior.calls.clear()
        upscale_asset(asset, tmp_path / f"o{n}", UpscaleOptions(preset="fast", prior="n"))
        assert prior.calls[0] == (32, 4)
        calls.append(len(prior.calls) - 1)
    assert calls[0] > 0 and calls[1] == 2 * calls[0]
    with pytest.raises(InvalidOptions, match="pseudo_gt_self_ensemble"):
        one_step.with_(pseudo_gt_self_ensemble=3)


@pytest.mark.parametrize("method", ["bicubic", "direct", "pbrsr"])
def test_normal_maps_come_out_at_the_inputs_length(tmp_path: Path, method: str):
    """A normal map stored at |n| = 0.9 comes back at 0.9 from every method (the optimiser
    steps on unit normals; its export, projection and island padding keep the length)."""
    y, x = np.mgrid[0:32, 0:32] / 32 * 2 * np.pi
    n = np.stack([0.3 * np.sin(x), 0.3 * np.cos(y), np.ones_like(x)], -1)
    n *= 0.9 / np.linalg.norm(n, axis=-1, keepdims=True)
    base = np.full((32, 32, 3), 0.6, np.float32)
    asset = make_quad_asset(
        tmp_path / "q.gltf", {"base_color": base, "normal": ((n + 1) / 2).astype(np.float32)}
    )
    opts = {"bicubic": {"method": "bicubic"}, "direct": {"method": "direct", "prior": "bicubic"}}
    options = UpscaleOptions(**opts.get(method, {"preset": "fast", "prior": "bicubic"}), scale=2)
    upscale_asset(asset, tmp_path / "out", options)
    out = load_asset(tmp_path / "out" / "q.gltf")
    img = next(i for i in out.images if "normal" in i.roles)
    length = np.linalg.norm(img.pixels[..., :3] * 2 - 1, axis=-1)
    assert img.pixels.shape[:2] == (64, 64)
    assert abs(float(length.mean()) - 0.9) < 0.01 and float(np.abs(length - 0.9).max()) < 0.03


def test_prior_stages_report_tiles_with_an_eta(tmp_path, set_runtime):
    """direct and PBR-SR's init report progress per tile of the prior (the longest stages on
    big maps), as a fraction of all the maps' pixels with an ETA."""
    from pbrsr_core.progress import Progress

    set_runtime(prior_tile=16)  # several tiles per 32² map
    src = make_demo_asset(tmp_path / "demo.glb", size=32)
    for method, stage in (("direct", "prior"), ("pbrsr", "init")):
        events: list[Progress] = []
        options = UpscaleOptions(scale=2, method=method, preset="fast", prior="pbr-upconv7")
        upscale_asset(src, tmp_path / method, options, progress=events.append)
        mine = [e for e in events if e.stage == stage]
        steps = [e.step for e in mine]
        assert steps == sorted(steps) and steps[0] == 0 and steps[-1] == 1000, steps
        assert len({e.message.split(":")[0] for e in mine if e.message}) == 3  # three maps
        assert sum("tile" in e.message for e in mine) > 6
        assert all(e.total == 1000 for e in mine)
        assert any(e.eta_s is not None and e.eta_s >= 0 for e in mine)


def three_sizes(tmp_path: Path, data_side: int = 8) -> Path:
    """A quad whose albedo is 32², normal map 16² and metallic-roughness map ``data_side``²."""
    rng = np.random.default_rng(5)
    n = rng.normal(0, 0.3, (16, 16, 3))
    n[..., 2] = 1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    maps = {
        "base_color": rng.random((32, 32, 3)).astype(np.float32),
        "normal": ((n + 1) / 2).astype(np.float32),
        "metallic_roughness": rng.random((data_side, data_side, 3)).astype(np.float32),
    }
    return make_quad_asset(tmp_path / "in" / "q.gltf", maps)


each_method = pytest.mark.parametrize(
    "options",
    [
        UpscaleOptions(method="direct", prior="pbr-srmd"),
        UpscaleOptions(method="pbrsr", preset="balanced", prior="pbr-srmd"),
        UpscaleOptions(method="bicubic"),
    ],
    ids=["direct", "balanced", "bicubic"],
)


@each_method
def test_max_size_upscales_each_map_by_the_largest_factor_that_fits(tmp_path, options):
    """x4 with max_size 64: the 32² albedo at x2, the 16² normal and 8² data maps at x4, each
    map as a run at its own factor makes it; with max_size 32 the albedo keeps its file."""
    src = three_sizes(tmp_path)
    capped = upscale_asset(src, tmp_path / "c", options.model_copy(update={"max_size": 64}))
    assert [(i["lr_size"][0], i["scale"]) for i in capped["images"]] == [(32, 2), (16, 4), (8, 4)]
    assert capped["kept"] == []
    runs = {}
    for f in (2, 4):
        upscale_asset(src, tmp_path / f"x{f}", options.model_copy(update={"scale": f}))
        runs[f] = load_asset(tmp_path / f"x{f}" / "q.gltf")
    out = load_asset(tmp_path / "c" / "q.gltf")
    for img, f in zip(out.images, (2, 4, 4), strict=True):
        assert np.array_equal(img.pixels, runs[f].images[img.index].pixels), (img.name, f)
    assert validate_gltf(tmp_path / "c" / "q.gltf")["numErrors"] == 0

    kept = upscale_asset(src, tmp_path / "k", options.model_copy(update={"max_size": 32}))
    assert [(i["lr_size"][0], i["scale"]) for i in kept["images"]] == [(16, 2), (8, 4)]
    assert [k["size"] for k in kept["kept"]] == [[32, 32]]
    uri = json.loads(src.read_text())["images"][0]["uri"]
    assert json.loads((tmp_path / "k" / "q.gltf").read_text())["images"][0]["uri"] == uri
    assert (tmp_path / "k" / uri).read_bytes() == (src.parent / uri).read_bytes()
    assert len(list((tmp_path / "k" / "maps").iterdir())) == 2


def test_max_size_refuses_what_it_cannot_run(tmp_path):
    src = three_sizes(tmp_path)
    with pytest.raises(UnprocessableAsset, match=r"over max_size \(15 px\) at x2"):
        upscale_asset(src, tmp_path / "a", UpscaleOptions(method="bicubic", max_size=15))
    assert not (tmp_path / "a").exists()
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="max_size"):
        UpscaleOptions(max_size=1)


@each_method
def test_maps_upscales_the_listed_roles_and_keeps_the_other_files(tmp_path, options):
    """maps=[base_color, normal]: those two maps as a run of every map makes them, the
    metallic-roughness map's file byte for byte the input's, reported kept for ``maps``."""
    src = three_sizes(tmp_path)
    everything = upscale_asset(src, tmp_path / "all", options)
    some_maps = UpscaleOptions.model_validate(
        {**options.model_dump(), "maps": ["normal", "base_color"]}
    )
    report = upscale_asset(src, tmp_path / "some", some_maps)
    assert report["options"]["maps"] == ["base_color", "normal"]
    assert [(i["label"], i["scale"]) for i in report["images"]] == [
        ("base_color", 4),
        ("normal", 4),
    ]
    assert report["kept"] == [
        {"index": 2, "name": "metallic_roughness.png", "label": "metallic_roughness",
         "size": [8, 8], "reason": "maps"}
    ]  # fmt: skip
    full, some = load_asset(tmp_path / "all" / "q.gltf"), load_asset(tmp_path / "some" / "q.gltf")
    for i in (0, 1):
        assert np.array_equal(some.images[i].pixels, full.images[i].pixels), i
    uri = json.loads(src.read_text())["images"][2]["uri"]
    assert json.loads((tmp_path / "some" / "q.gltf").read_text())["images"][2]["uri"] == uri
    assert (tmp_path / "some" / uri).read_bytes() == (src.parent / uri).read_bytes()
    assert len(list((tmp_path / "some" / "maps").iterdir())) == 2
    assert len(everything["images"]) == 3 and everything["kept"] == []
    rows = map_rows(report)
    assert rows[2]["made_by"] == ["kept (maps)"] and rows[2]["scale"] == 1


@each_method
def test_other_maps_bicubic_upscales_the_unlisted_roles_by_bicubic(tmp_path, options):
    """maps=[base_color, normal] with other_maps bicubic: those two maps as a run of every map
    makes them, the metallic-roughness map as ``--method bicubic`` makes it, nothing kept."""
    src = three_sizes(tmp_path)
    upscale_asset(src, tmp_path / "all", options)
    upscale_asset(src, tmp_path / "bic", UpscaleOptions(method="bicubic"))
    rest_bicubic = UpscaleOptions.model_validate(
        {**options.model_dump(), "maps": ["base_color", "normal"], "other_maps": "bicubic"}
    )
    report = upscale_asset(src, tmp_path / "some", rest_bicubic)
    assert [(i["label"], i["scale"]) for i in report["images"]] == [
        ("base_color", 4),
        ("normal", 4),
        ("metallic_roughness", 4),
    ]
    assert report["kept"] == []
    full, some = load_asset(tmp_path / "all" / "q.gltf"), load_asset(tmp_path / "some" / "q.gltf")
    bicubic = load_asset(tmp_path / "bic" / "q.gltf")
    for i in (0, 1):
        assert np.array_equal(some.images[i].pixels, full.images[i].pixels), i
    assert np.array_equal(some.images[2].pixels, bicubic.images[2].pixels)
    if options.method != "bicubic":
        assert map_rows(report)[2]["made_from"] == "bicubic (maps)"
        assert not np.array_equal(some.images[0].pixels, bicubic.images[0].pixels)


def test_other_maps_bicubic_keeps_a_listed_map_over_max_size(tmp_path):
    """The listed albedo over max_size keeps its file (reason max_size); the unlisted maps
    get bicubic's upscale at the factor max_size leaves them (16² x2, 8² x4)."""
    src = three_sizes(tmp_path)
    capped = UpscaleOptions(method="direct", prior="pbr-srmd", maps=["base_color"],
                            max_size=63, other_maps="bicubic")  # fmt: skip
    report = upscale_asset(src, tmp_path / "a", capped)
    assert [(i["lr_size"][0], i["scale"]) for i in report["images"]] == [(16, 2), (8, 4)]
    assert [(k["label"], k["reason"]) for k in report["kept"]] == [("base_color", "max_size")]
    assert [r["made_from"] for r in map_rows(report)] == ["kept (max_size)", "bicubic (maps)",
                                                          "bicubic (maps)"]  # fmt: skip
    assert "load_prior" not in report["timings"]  # no listed map to run the prior on


def test_maps_refuses_roles_it_does_not_know_or_the_asset_lacks(tmp_path):
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="unknown map role 'albedo'"):
        UpscaleOptions(maps=["albedo"])
    with pytest.raises(ValidationError, match="maps"):
        UpscaleOptions(maps=[])
    src = three_sizes(tmp_path)
    with pytest.raises(UnprocessableAsset, match=r"no map of this asset has a role in maps "
                       r"\(occlusion, emissive\); its maps' roles: base_color, "
                       r"metallic_roughness, normal"):  # fmt: skip
        missing = UpscaleOptions(method="bicubic", maps=["emissive", "occlusion"])
        upscale_asset(src, tmp_path / "a", missing)
    assert not (tmp_path / "a").exists()
    # the listed maps all over max_size: refused for max_size, though the others would fit
    capped = UpscaleOptions(method="bicubic", maps=["base_color"], max_size=63)
    with pytest.raises(UnprocessableAsset, match=r"over max_size \(63 px\) at x2"):
        upscale_asset(src, tmp_path / "b", capped)
    assert not (tmp_path / "b").exists()


def test_optimiser_steps_take_every_map_at_its_own_factor(tmp_path):
    """With steps, max_size's factors meet in one optimisation: each map held to its LR map at
    its own factor, a kept map rendered as it is and its file left alone."""
    src = three_sizes(tmp_path)
    options = UpscaleOptions(prior="bicubic", iterations=3, max_size=64)
    report = upscale_asset(src, tmp_path / "a", options)
    assert [i["scale"] for i in report["images"]] == [2, 4, 4] and len(report["history"]) >= 1
    # each map as close to its LR map as in a run with every map at its factor
    for f, keys in ((2, ["0:base_color"]), (4, ["1:normal", "2:roughness", "2:metallic"])):
        uniform = options.model_copy(update={"scale": f, "max_size": None})
        alone = upscale_asset(src, tmp_path / f"x{f}", uniform)
        for k in keys:
            assert report["consistency_psnr_db"][k] == pytest.approx(
                alone["consistency_psnr_db"][k], abs=0.1
            ), (k, f)
    out, lr = load_asset(tmp_path / "a" / "q.gltf"), load_asset(src)
    for img, f in zip(out.images, (2, 4, 4), strict=True):
        assert img.pixels.shape[:2] == tuple(f * n for n in lr.images[img.index].pixels.shape[:2])
        assert np.isfinite(img.pixels).all()

    kept = upscale_asset(src, tmp_path / "k", options.model_copy(update={"max_size": 32}))
    assert [i["scale"] for i in kept["images"]] == [2, 4] and kept["history"]
    assert [k["size"] for k in kept["kept"]] == [[32, 32]]
    uri = json.loads(src.read_text())["images"][0]["uri"]
    assert (tmp_path / "k" / uri).read_bytes() == (src.parent / uri).read_bytes()


def test_optimiser_steps_render_a_bicubic_only_map_and_leave_it_bicubics(tmp_path):
    """other_maps bicubic with steps: the albedo, unlisted, is rendered at its bicubic x4
    and comes out as ``--method bicubic`` makes it; the listed maps are optimised."""
    src = three_sizes(tmp_path)
    options = UpscaleOptions(prior="bicubic", iterations=3, maps=["normal", "metallic_roughness"],
                             other_maps="bicubic")  # fmt: skip
    report = upscale_asset(src, tmp_path / "a", options)
    assert report["history"] and [i["scale"] for i in report["images"]] == [4, 4, 4]
    assert sorted(report["consistency_psnr_db"]) == ["1:normal", "2:metallic", "2:roughness"]
    upscale_asset(src, tmp_path / "b", UpscaleOptions(method="bicubic"))
    out, bicubic = load_asset(tmp_path / "a" / "q.gltf"), load_asset(tmp_path / "b" / "q.gltf")
    assert np.array_equal(out.images[0].pixels, bicubic.images[0].pixels)
    assert not np.array_equal(out.images[1].pixels, bicubic.images[1].pixels)
    assert all(np.isfinite(img.pixels).all() for img in out.images)
