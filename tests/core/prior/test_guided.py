"""Roughness and metallic upscaled with the colour map as guide (prior/guided.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.degrade import degrade_image
from pbrsr_core.metrics import psnr
from pbrsr_core.optim import presets
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior import selfcheck
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.direct import bicubic_map
from pbrsr_core.prior.guided import guide_pairs, guided_check_upscale, guided_upscale
from pbrsr_core.progress import Progress


def _blocks(size: int, block: int, seed: int) -> np.ndarray:
    """A colour map of flat blocks with sharp edges (paint regions), values in [0.1, 0.9]."""
    g = np.random.default_rng(seed)
    cells = g.random((size // block, size // block, 3)) * 0.8 + 0.1
    return np.repeat(np.repeat(cells, block, 0), block, 1).astype(np.float32)


def _follows(colour: np.ndarray) -> np.ndarray:
    """Roughness and metallic as affine functions of the colour, in [0, 1]."""
    r, g, b = colour[..., 0], colour[..., 1], colour[..., 2]
    rough = 0.1 + 0.5 * r + 0.3 * b
    metal = 0.9 - 0.4 * g - 0.4 * b
    return np.stack([rough, metal], -1).astype(np.float32)


def test_a_channel_affine_in_the_colour_is_recovered_from_the_hr_guide():
    hr_colour = _blocks(128, 8, seed=1)
    hr_data = _follows(hr_colour)
    lr_colour, lr_data = degrade_image(hr_colour, 4), degrade_image(hr_data, 4)
    up = guided_upscale(lr_data, lr_colour, hr_colour, 4)
    assert up.shape == (128, 128, 2) and up.dtype == np.float32
    bic = bicubic_map(lr_data, "data", 4)
    for c in range(2):
        exact, plain = psnr(up[..., c], hr_data[..., c]), psnr(bic[..., c], hr_data[..., c])
        assert exact > 40.0 and exact > plain + 15.0, (c, exact, plain)


def test_flat_and_degenerate_inputs_stay_finite_and_flat():
    lr_colour = _blocks(32, 4, seed=2)
    flat = np.full((32, 32, 2), 0.37, np.float32)
    up = guided_upscale(flat, lr_colour, _blocks(128, 16, seed=2), 4)
    assert np.abs(up - 0.37).max() < 1e-5
    # a flat guide carries nothing: the fit's regularisation gives a smooth interpolation
    data = _follows(_blocks(32, 4, seed=3))
    up = guided_upscale(data, np.full((32, 32, 3), 0.5, np.float32), np.zeros((7, 9, 3)), 4)
    assert np.isfinite(up).all() and up.min() >= 0.0 and up.max() <= 1.0
    assert psnr(up, bicubic_map(data, "data", 4)) > 30.0
    # a guide of another size is resampled to the channel's grid
    up = guided_upscale(data, _blocks(64, 8, seed=3), _blocks(256, 32, seed=3), 4)
    assert up.shape == (128, 128, 2) and np.isfinite(up).all()
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        guided_upscale(data[..., 0], lr_colour, lr_colour, 4)


def test_the_check_upscales_the_crop_one_scale_down_with_the_guide_degraded_alike():
    lr_colour = _blocks(64, 8, seed=4)
    orm = np.concatenate([np.random.default_rng(4).random((64, 64, 1)), _follows(lr_colour)], -1)
    orm = orm.astype(np.float32)
    small = degrade_image(orm, 4)
    kept = {"small": small, "factor": 4, "mask": np.ones((64, 64), bool)}

    def exact_guide(px: np.ndarray, f: int) -> np.ndarray:  # the colour map it was degraded from
        assert px.shape[:2] == (64 // f, 64 // f) and f == 4
        return lr_colour

    bicubic_guide = lambda px, f: bicubic_map(px, "colour", f)  # noqa: E731
    up = guided_check_upscale(kept, (64, 64), lr_colour, exact_guide, [1, 2])
    assert up.shape == (64, 64, 2)
    bic = bicubic_map(small, "data", 4)
    for k, c in enumerate((1, 2)):
        assert psnr(up[..., k], orm[..., c]) > psnr(bic[..., c], orm[..., c]) + 10.0
    # with a guide upscaled by bicubic the guided upscale gains little over bicubic
    blurred = guided_check_upscale(kept, (64, 64), lr_colour, bicubic_guide, [1])
    assert psnr(blurred[..., 0], orm[..., 1]) < psnr(up[..., 0], orm[..., 1]) - 5.0
    # a guide of another size is resampled to the map's grid first; cut to the mask's shape
    kept["mask"] = np.ones((60, 62), bool)
    up = guided_check_upscale(kept, (64, 64), _blocks(128, 16, seed=4), bicubic_guide, [2])
    assert up.shape == (60, 62, 1) and np.isfinite(up).all()


def _material_asset(tmp_path):
    """A quad whose material has a colour map and a metallic-roughness map."""
    colour = _blocks(32, 4, seed=5)
    orm = np.concatenate([np.full((32, 32, 1), 1.0), _follows(colour)], -1).astype(np.float32)
    path = make_quad_asset(tmp_path / "q.gltf", {"base_color": colour, "metallic_roughness": orm})
    return load_asset(path)


def test_guide_pairs_follow_the_materials_uvs(tmp_path):
    import dataclasses

    asset = _material_asset(tmp_path)
    (bc, mr) = (asset.materials[0].base_color, asset.materials[0].metallic_roughness)
    assert bc is not None and mr is not None
    assert guide_pairs(asset, {bc.image, mr.image}) == {mr.image: bc.image}
    assert guide_pairs(asset, {mr.image}) == {}  # the colour map is not upscaled: no guide
    other_uvs = dataclasses.replace(mr, texcoord=1)
    m = dataclasses.replace(asset.materials[0], metallic_roughness=other_uvs)
    assert guide_pairs(dataclasses.replace(asset, materials=[m]), {bc.image, mr.image}) == {}
    moved = dataclasses.replace(mr, uv_transform=(2, 0, 0, 0, 2, 0, 0, 0, 1))
    m = dataclasses.replace(asset.materials[0], metallic_roughness=moved)
    assert guide_pairs(dataclasses.replace(asset, materials=[m]), {bc.image, mr.image}) == {}
    # one metallic-roughness map shared by two materials of different colour maps: no guide
    second = dataclasses.replace(
        asset.materials[0], index=1, base_color=dataclasses.replace(bc, image=mr.image + 7)
    )
    two = dataclasses.replace(asset, materials=[asset.materials[0], second])
    assert guide_pairs(two, {bc.image, mr.image, mr.image + 7}) == {}


class KnowsTheColourMap(Prior):
    """Exact on one colour map: its LR map degraded once more gives the LR map back (the
    self-check one scale down), the LR map gives its HR map; any other input is blurred
    (nearest, then a box filter: loses to bicubic)."""

    name = "knows"
    scales = (4,)
    back_project = False

    def __init__(self, lr: np.ndarray, hr: np.ndarray):
        super().__init__()

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a[..., :3])).permute(2, 0, 1)

        self.pairs = [(t(degrade_image(lr, 4)), t(lr)), (t(lr), t(hr))]

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        for src, out in self.pairs:
            if x.shape[1:] == src.shape and torch.allclose(x[0], src, atol=1e-5):
                return out[None].clone()
        up = F.interpolate(x, scale_factor=scale, mode="nearest")
        return F.avg_pool2d(up, 2 * scale + 1, stride=1, padding=scale, count_include_pad=False)


def test_balanced_blends_roughness_and_metallic_with_the_guided_upscale(tmp_path, monkeypatch):
    import pbrsr_core.pipeline as pipeline

    hr_colour = _blocks(128, 8, seed=6)
    hr_data = _follows(hr_colour)
    rng = np.random.default_rng(6)
    occlusion = (rng.random((32, 32, 1)) * 0.5 + 0.5).astype(np.float32)
    lr_orm = np.concatenate([occlusion, degrade_image(hr_data, 4)], -1)
    path = make_quad_asset(  # the metallic-roughness image first: its guide is made first
        tmp_path / "q.gltf",
        {"metallic_roughness": lr_orm, "base_color": degrade_image(hr_colour, 4)},
    )
    lr = load_asset(path)
    mat = lr.materials[0]
    assert mat.base_color is not None and mat.metallic_roughness is not None
    lr_colour = lr.images[mat.base_color.image].pixels
    stored_orm = lr.images[mat.metallic_roughness.image].pixels
    prior = KnowsTheColourMap(lr_colour, hr_colour)
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior)
    monkeypatch.setattr(selfcheck, "MIN_SIDE", 8)  # check the 32² maps at x4
    monkeypatch.setitem(presets.PRESETS, "balanced", presets.BALANCED.with_(project_lr=()))

    def run(name: str) -> tuple[np.ndarray, dict]:
        events: list[Progress] = []
        options = UpscaleOptions(preset="balanced")
        report = upscale_asset(path, tmp_path / name, options, progress=events.append)
        steps = [e.step for e in events if e.stage == "init"]
        assert steps == sorted(steps) and steps[-1] == 1000, steps
        out = load_asset(tmp_path / name / "q.gltf")
        return out.images[out.materials[0].metallic_roughness.image].pixels, report

    orm, report = run("blended")
    (entry,) = [c for c in report["prior_check"] if c["index"] == mat.metallic_roughness.image]
    blended = entry["blend"]
    assert blended["guide"] == lr.images[mat.base_color.image].name
    assert blended["sources"][-1] == "guided"  # with only the upscales some channel weighs
    k = blended["sources"].index("guided")
    # roughness and metallic: the guided upscale, exact one scale down; occlusion (noise the
    # prior blurs and no guide follows) stays bicubic's
    assert min(blended["margins"][1:]) > 5.0
    assert [w[k] > 0.9 for w in blended["weights"]] == [False, True, True]
    assert all(any(w[m] for w in blended["weights"]) for m in range(len(blended["sources"])))
    assert entry["channels"] == [False, True, True]
    bic = bicubic_map(stored_orm, "metallic_roughness", 4)
    for c in (1, 2):
        got, plain = psnr(orm[..., c], hr_data[..., c - 1]), psnr(bic[..., c], hr_data[..., c - 1])
        assert got > plain + 10.0, (c, got, plain)
    assert np.abs(orm[..., 0] - bic[..., 0]).max() <= 1 / 255  # occlusion: bicubic's
    # the preset's margin decides: no blend beats bicubic by 1000 dB one scale down
    monkeypatch.setitem(
        presets.PRESETS, "balanced", presets.BALANCED.with_(project_lr=(), blend_margin=1e3)
    )
    orm, report = run("margin")
    (entry,) = [c for c in report["prior_check"] if c["index"] == mat.metallic_roughness.image]
    assert entry["channels"] == [False, False, False] and entry["blend"]["sources"] == []
    assert np.abs(orm[..., :3] - bic[..., :3]).max() <= 1 / 255
    # without blend_data the check picks per channel: bicubic (the prior loses on them)
    monkeypatch.setitem(
        presets.PRESETS, "balanced", presets.BALANCED.with_(project_lr=(), blend_data=False)
    )
    orm, report = run("plain")
    assert all("blend" not in c for c in report["prior_check"])
    assert np.abs(orm[..., :3] - bic[..., :3]).max() <= 1 / 255
    # nor where data maps are not checked: the prior initialises each channel
    monkeypatch.setitem(
        presets.PRESETS, "balanced", presets.BALANCED.with_(project_lr=(), check_prior=("colour",))
    )
    orm, report = run("unchecked")
    assert all("blend" not in c for c in report["prior_check"])
    assert np.abs(orm[..., 1:3] - bic[..., 1:3]).max() > 0.05  # the prior's blur, unchecked


class KnowsRoughly(KnowsTheColourMap):
    """KnowsTheColourMap, and on each channel of one data map (run as a grey image) its
    upscale from one scale down and to the HR map, each with a fixed noise of 0.03 RMS: it
    beats bicubic on sharp blocks, and loses to a guide that follows them exactly."""

    def __init__(self, lr: np.ndarray, hr: np.ndarray, lr_data: np.ndarray, hr_data: np.ndarray):
        super().__init__(lr, hr)
        rng = np.random.default_rng(9)

        def grey(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(np.repeat(a[..., None], 3, -1))).permute(
                2, 0, 1
            )

        def noisy(a: np.ndarray) -> np.ndarray:
            return np.clip(a + rng.normal(0, 0.03, a.shape), 0, 1).astype(np.float32)

        small = degrade_image(lr_data, 4)
        for c in range(lr_data.shape[-1]):
            self.pairs.append((grey(small[..., c]), grey(noisy(lr_data[..., c]))))
            self.pairs.append((grey(lr_data[..., c]), grey(noisy(hr_data[..., c]))))


def _roughly_known_quad(tmp_path, monkeypatch, hr_colour, hr_data):
    """A quad of the two maps degraded x4, run with KnowsRoughly as the prior: its path and
    the index of its metallic-roughness image."""
    import pbrsr_core.pipeline as pipeline

    path = make_quad_asset(
        tmp_path / "q.gltf",
        {
            "metallic_roughness": degrade_image(hr_data, 4),
            "base_color": degrade_image(hr_colour, 4),
        },
    )
    lr = load_asset(path)
    mat = lr.materials[0]
    assert mat.base_color is not None and mat.metallic_roughness is not None
    stored_orm = lr.images[mat.metallic_roughness.image].pixels
    prior = KnowsRoughly(lr.images[mat.base_color.image].pixels, hr_colour, stored_orm, hr_data)
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior)
    monkeypatch.setattr(selfcheck, "MIN_SIDE", 8)
    return path, mat.metallic_roughness.image


def test_a_channel_keeps_the_checks_pick_unless_its_blend_beats_it(tmp_path, monkeypatch):
    hr_colour = _blocks(128, 8, seed=7)
    hr_data = np.concatenate([_blocks(128, 8, seed=8)[..., :1], _follows(hr_colour)], -1)
    path, orm_index = _roughly_known_quad(tmp_path, monkeypatch, hr_colour, hr_data)

    def run(name: str, pick_db: float | None) -> dict:
        preset = presets.BALANCED.with_(project_lr=(), iterations=0, blend_pick_db=pick_db)
        monkeypatch.setitem(presets.PRESETS, "balanced", preset)
        report = upscale_asset(path, tmp_path / name, UpscaleOptions(preset="balanced"))
        (entry,) = [c for c in report["prior_check"] if c["index"] == orm_index]
        return entry

    # the prior's noisy upscale beats bicubic one scale down on roughness and metallic (the
    # red channel is no map's): the check's pick
    entry = run("picks", 1e3)
    assert entry["priors"][1:] == ["knows"] * 2 and min(entry["margins"][1:]) > 5.0
    blended = entry["blend"]  # no blend beats the pick by 1000 dB: each channel takes the pick
    assert blended["sources"] == ["knows"] and blended["weights"] == [[0.0], [1.0], [1.0]]
    assert entry["channels"] == [False, True, True]
    # the guided upscale follows roughness and metallic exactly: their blends beat the pick
    for pick_db in (0.05, None):
        blended = run(f"blend-{pick_db}", pick_db)["blend"]
        k = blended["sources"].index("guided")
        assert [w[k] > 0.5 for w in blended["weights"]] == [False, True, True], blended


def test_the_pick_floor_keeps_a_network_the_guide_cannot_replace(tmp_path, monkeypatch):
    hr_colour = _blocks(128, 8, seed=7)
    hr_data = np.roll(_blocks(128, 8, seed=8), 4, axis=(0, 1))  # no edge the colour has
    path, orm_index = _roughly_known_quad(tmp_path, monkeypatch, hr_colour, hr_data)

    def run(name: str, floor: bool) -> dict:
        preset = presets.BALANCED.with_(project_lr=(), iterations=0, blend_network_db=1e3,
                                        blend_pick_floor=floor)  # fmt: skip
        monkeypatch.setitem(presets.PRESETS, "balanced", preset)
        report = upscale_asset(path, tmp_path / name, UpscaleOptions(preset="balanced"))
        (entry,) = [c for c in report["prior_check"] if c["index"] == orm_index]
        return entry

    # the network's pick beats bicubic by far one scale down; no network adds 1000 dB
    entry = run("rule", False)
    assert entry["priors"][1:] == ["knows"] * 2 and min(entry["margins"][1:]) > 5.0
    assert "knows" not in entry["blend"]["sources"]
    assert max(m for m in entry["blend"]["margins"][1:]) < min(entry["margins"][1:])
    # with the floor the network stays where the guided fit alone falls below its pick
    entry = run("floor", True)
    blended = entry["blend"]
    assert blended["sources"][0] == "knows" and entry["channels"][1:] == [True, True]
    k = blended["sources"].index("knows")
    assert all(w[k] > 0.5 for w in blended["weights"][1:]), blended
    pairs = zip(blended["margins"][1:], entry["margins"][1:], strict=True)
    assert all(b >= m - 1e-3 for b, m in pairs)


def test_a_network_is_not_run_on_the_channels_it_adds_little_to(tmp_path, monkeypatch):
    import pbrsr_core.pipeline as pipeline

    hr_colour = _blocks(128, 8, seed=7)
    hr_data = np.roll(_blocks(128, 8, seed=8), 4, axis=(0, 1))  # no edge the colour has
    path, orm_index = _roughly_known_quad(tmp_path, monkeypatch, hr_colour, hr_data)
    prior = pipeline.load_prior("knows", "cpu")
    runs: list[tuple[int, ...]] = []
    forward = prior._forward

    def counted(x: torch.Tensor, scale: int) -> torch.Tensor:
        if torch.equal(x[:, 0], x[:, 1]) and torch.equal(x[:, 0], x[:, 2]):  # a data channel
            runs.append(tuple(x.shape[-2:]))
        return forward(x, scale)

    monkeypatch.setattr(prior, "_forward", counted)

    def run(name: str, channel_db: float | None) -> tuple[dict, list]:
        runs.clear()
        preset = presets.BALANCED.with_(project_lr=(), iterations=0, blend_network_db=0.0,
                                        blend_channel_db=channel_db)  # fmt: skip
        monkeypatch.setitem(presets.PRESETS, "balanced", preset)
        report = upscale_asset(path, tmp_path / name, UpscaleOptions(preset="balanced"))
        (entry,) = [c for c in report["prior_check"] if c["index"] == orm_index]
        return entry, [r for r in runs if r == (32, 32)]  # the real scale's runs (LR 32²)

    # the network beats bicubic and the guide on both channels: it runs on both
    entry, real = run("every", None)
    k = entry["blend"]["sources"].index("knows")
    assert [w[k] > 0.5 for w in entry["blend"]["weights"]] == [False, True, True]
    assert len(real) == 2
    assert run("some", 0.1) == (entry, real)
    # no channel gains 1000 dB from it: it runs on none, and each channel keeps what is left
    entry, real = run("none", 1e3)
    assert real == [] and "knows" not in entry["blend"]["sources"]
