"""The detail gain: the scale of a prior's departure from bicubic that fits a map best one
scale down, and its share taken by direct and the presets on colour and data maps."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.degrade import degrade_image
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.optim import presets
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.bicubic import bicubic_upscale
from pbrsr_core.prior.selfcheck import GAIN_RANGE, detail_gain, prior_self_check, with_gain


class Exaggerating(Prior):
    """A real prior that sharpens too much: bicubic plus twice nearest-neighbour's departure
    from it."""

    name = "exaggerating"
    scales = (2, 4)
    back_project = False

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        b = bicubic_upscale(x, scale)
        return (b + 2.0 * (F.interpolate(x, scale_factor=scale, mode="nearest") - b)).clamp(0, 1)


class Overshooting(Exaggerating):
    """Half as much again of the truth's departure from bicubic on the self-checks of the
    given LR maps (a colour map whole, a data map's channels as the greyscale images they
    reach a prior as): closer than bicubic, with too much detail; elsewhere
    :class:`Exaggerating`."""

    name = "overshooting"
    scales = (4,)  # knows the x4 check's crops: no x2 to check a small map at

    def __init__(self, *lr_maps: np.ndarray, scale: int = 4):
        super().__init__()
        self.known = []  # (LR one scale down, the HR it came from), (3, h, w) each
        for m in lr_maps:
            small = torch.from_numpy(degrade_image(m[..., :3], scale)).permute(2, 0, 1)
            hr = torch.from_numpy(np.ascontiguousarray(m[..., :3])).permute(2, 0, 1)
            self.known.append((small, hr))
            self.known += [(small[c].expand(3, -1, -1), hr[c].expand(3, -1, -1)) for c in range(3)]

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        out = super()._forward(x, scale)
        b = bicubic_upscale(x, scale)
        for i, img in enumerate(x):
            for small, hr in self.known:
                if img.shape == small.shape and torch.allclose(img, small, atol=1e-6):
                    out[i] = b[i] + 1.5 * (hr - b[i])
        return out


def _texture(size: int, channels: int = 3, seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    base = torch.from_numpy(g.random((1, channels, size // 8, size // 8)).astype(np.float32))
    up = F.interpolate(base, size=(size, size), mode="bicubic", align_corners=False)
    return up[0].permute(1, 2, 0).clamp(0, 1).numpy()


def test_the_gain_is_the_least_squares_scale_of_the_departure():
    g = np.random.default_rng(1)
    ref, bic = g.random(500), g.random(500)
    for k in (0.6, 1.0, 1.3):  # an upscale whose departure is 1/k of the truth's
        assert detail_gain(bic + (ref - bic) / k, bic, ref) == pytest.approx(k, abs=1e-9)
    noisy = bic + 0.8 * (ref - bic) + g.normal(0, 0.05, 500)
    d = noisy - bic
    assert detail_gain(noisy, bic, ref) == pytest.approx(float(d @ (ref - bic) / (d @ d)))
    assert detail_gain(bic + 10 * (ref - bic), bic, ref) == GAIN_RANGE[0]  # kept in range
    assert detail_gain(bic - (ref - bic), bic, ref) == GAIN_RANGE[0]  # the wrong way round
    assert detail_gain(bic + 0.1 * (ref - bic), bic, ref) == GAIN_RANGE[1]
    assert detail_gain(bic, bic, ref) == 1.0  # nothing departs: nothing to scale


def test_with_gain_scales_each_entry_and_keeps_alpha_range_and_normal_maps():
    g = np.random.default_rng(2)
    bic = g.random((8, 8, 4)).astype(np.float32)
    hr = np.clip(bic + g.normal(0, 0.1, bic.shape), 0, 1).astype(np.float32)
    data = with_gain(hr, bic, [0.5, 1.0, 1.5], "data", 0.5)  # factors 0.75, 1, 1.25
    assert np.allclose(data[..., 0], bic[..., 0] + 0.75 * (hr[..., 0] - bic[..., 0]), atol=1e-6)
    assert np.array_equal(data[..., 1], hr[..., 1]) and np.array_equal(data[..., 3], hr[..., 3])
    expected = np.clip(bic[..., 2] + 1.25 * (hr[..., 2] - bic[..., 2]), 0, 1)
    assert np.allclose(data[..., 2], expected, atol=1e-6)
    assert data.min() >= 0 and data.max() <= 1
    colour = with_gain(hr, bic, [0.5], "colour", 1.0)
    half = bic[..., :3] + 0.5 * (hr[..., :3] - bic[..., :3])
    assert np.allclose(colour[..., :3], half, atol=1e-6)
    assert np.array_equal(colour[..., 3], hr[..., 3])
    assert np.array_equal(with_gain(bic, bic, [0.5], "colour", 1.0), bic)  # bicubic stays
    assert with_gain(hr, bic, [0.5], "normal", 1.0) is hr  # normal maps take no gain
    assert with_gain(hr, bic, [0.5], "colour", 0.0) is hr
    with pytest.raises(ValueError, match="3 channel entries"):
        with_gain(hr, bic, [0.5], "data", 0.5)
    with pytest.raises(InvalidOptions, match="detail_gain"):
        presets.BALANCED.with_(detail_gain=1.5)


def test_the_check_reports_the_gain_of_each_entrys_pick():
    tex = _texture(96)
    check = prior_self_check(Exaggerating(), tex, 4)
    assert len(check["gains"]) == 1 and GAIN_RANGE[0] <= check["gains"][0] < 0.95
    data = prior_self_check(Exaggerating(), _texture(96, seed=3), 4, "data")
    assert len(data["gains"]) == 3 and all(k < 0.95 for k in data["gains"])


@pytest.mark.parametrize("method", ["direct", "pbrsr"])
def test_direct_and_the_presets_take_their_share_of_the_gain(tmp_path, monkeypatch, method):
    """The HR map with the gain is bicubic's plus the gain times the prior's departure from
    it, the gain the one the run reports; without it, the prior's map as it is."""
    import pbrsr_core.pipeline as pipeline

    maps = {"base_color": _texture(64, seed=4), "metallic_roughness": _texture(64, seed=5)}
    asset = make_quad_asset(tmp_path / "q.gltf", maps)
    prior = Overshooting(*(np.asarray(img.pixels, np.float32) for img in load_asset(asset).images))
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior if n == "x" else real(n, d))

    def run(name: str, share: float, prior: str = "x") -> tuple[dict, dict]:
        # fast at the full scale, its maps exported as initialised
        fast = presets.FAST.with_(max_prior_scale=None, project_lr=(), detail_gain=share)
        monkeypatch.setitem(presets.PRESETS, "fast", fast)
        monkeypatch.setattr(presets, "BALANCED", presets.BALANCED.with_(detail_gain=share))
        out = tmp_path / name
        m = "bicubic" if prior == "bicubic" else method
        report = upscale_asset(asset, out, UpscaleOptions(prior=prior, preset="fast", method=m))
        images = load_asset(next(out.glob("*.gltf"))).images
        return report, {img.name: img.pixels[8:-8, 8:-8] for img in images}

    report, gained = run("gain", 0.5)
    _, plain = run("plain", 0.0)
    _, bicubic = run("bicubic", 0.0, "bicubic")
    checks = {c["image"]: c for c in report["prior_check"]}
    for name, kind in (("base_color.png", "colour"), ("metallic_roughness.png", "data")):
        gains = checks[name]["gains"]
        assert all(k < 0.95 for k in gains)  # the prior overshoots: the gain tones it down
        expected = with_gain(plain[name], bicubic[name], gains, kind, 0.5)
        assert np.abs(gained[name] - expected).max() <= 2 / 255
        assert np.abs(gained[name] - plain[name]).max() >= 4 / 255
    if method == "direct":  # a prior of one candidate: checked for its gain alone
        assert "only candidate" in checks["base_color.png"]["note"]
        assert checks["base_color.png"]["channels"] == [True]
