"""Normal maps picked between the prior's candidates (``normal_pick_max_scale``): where the
prior offers several, a normal map takes the one closest one scale down, never bicubic and
whatever the flat rule says; beyond the factor, and with one candidate, its first."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.initial_maps import checked_kinds
from pbrsr_core.optim import presets
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.selfcheck import prior_self_check
from tests.core.prior.test_selfcheck import BlurringPrior, Offering, _made_by, _texture
from tests.core.prior.test_train import normals_from_height


class NearestPrior(Prior):
    """Nearest-neighbour upscaling: closer to a smooth map than the blurring prior, further
    than bicubic."""

    name = "nearest"
    scales = (2, 4)
    back_project = False

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        return F.interpolate(x, scale_factor=scale, mode="nearest")


def _normal_map(size: int = 64) -> np.ndarray:
    return normals_from_height(_texture(size, seed=6)[..., 0], strength=0.5)


def _two() -> Offering:
    return Offering(BlurringPrior(), NearestPrior())


def test_the_pick_takes_the_closest_candidate_even_below_bicubic():
    normal = _normal_map(128)
    checked = prior_self_check(_two(), normal, 4, "normal")
    picked = prior_self_check(_two(), normal, 4, "normal", pick_only=True)
    # both candidates lose to bicubic: the check keeps bicubic, the pick the closer one
    assert checked["margins"][0] < 0 and checked["channels"] == [False]
    cands = picked["candidates"]
    assert cands["nearest"] > cands["blurring"] and picked["priors"] == ["nearest"]
    assert picked["channels"] == [True] and picked["use_prior"]
    assert picked["margins"] == checked["margins"]  # the same comparison, reported alike
    # a flat map (one direction and 8-bit noise) is picked too: no flat rule
    flat = np.zeros_like(normal) + np.float32([0.5, 0.5, 1.0])
    flat[..., :2] += np.random.default_rng(1).normal(0.0, 0.3 / 255, flat.shape[:2] + (2,))
    check = prior_self_check(_two(), flat, 4, "normal", pick_only=True)
    assert check["flat"] == [True] and check["channels"] == [True]


def test_the_kinds_checked_follow_the_factor_the_candidates_and_check_prior():
    two, one = _two(), BlurringPrior()
    cpu = presets.BALANCED
    assert cpu.normal_pick_max_scale == 4 and presets.FAST.normal_pick_max_scale == 4
    for s in (2, 4):
        assert checked_kinds(two, s, cpu) == ({"colour", "data", "normal"}, {"normal"})
    assert checked_kinds(two, 8, cpu) == ({"colour", "data"}, set())
    assert checked_kinds(one, 4, cpu) == ({"colour", "data"}, set())  # nothing to pick from
    off = cpu.with_(normal_pick_max_scale=None)
    assert checked_kinds(two, 4, off) == ({"colour", "data"}, set())
    every = cpu.with_(check_prior=("colour", "data", "normal"))  # the full check wins
    assert checked_kinds(two, 4, every) == ({"colour", "data", "normal"}, set())
    assert checked_kinds(two, 4, presets.PAPER) == (set(), set())
    with pytest.raises(InvalidOptions, match="normal_pick_max_scale"):
        cpu.with_(normal_pick_max_scale=1)


def test_direct_and_the_presets_upscale_a_normal_map_with_the_pick(tmp_path, monkeypatch):
    import pbrsr_core.pipeline as pipeline

    maps = {"base_color": _texture(64, seed=4), "normal": _normal_map(64)}
    asset = make_quad_asset(tmp_path / "q.gltf", maps)
    priors = {"two": _two(), "nearest": NearestPrior(), "blurring": BlurringPrior()}
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: priors.get(n) or real(n, d))
    full = presets.FAST.with_(max_prior_scale=None)
    runs = iter(range(100))

    def normal_out(prior: str, config=full, **kw) -> tuple[np.ndarray, dict]:
        monkeypatch.setitem(presets.PRESETS, "fast", config)
        monkeypatch.setattr(presets, "BALANCED", config)  # direct follows balanced's
        out = tmp_path / f"run{next(runs)}"
        report = upscale_asset(asset, out, UpscaleOptions(prior=prior, preset="fast", **kw))
        (img,) = [im for im in load_asset(next(out.glob("*.gltf"))).images if "normal" in im.roles]
        return img.pixels, report

    for method in ("direct", "pbrsr"):
        picked, report = normal_out("two", method=method)
        assert _made_by(report, "normal.png") == ["nearest"]
        (check,) = [c for c in report["prior_check"] if c["image"] == "normal.png"]
        assert check["priors"] == ["nearest"] and check["channels"] == [True]
        assert check["margins"][0] < 0  # below bicubic one scale down, and still the pick's
        alone = normal_out("nearest", method=method)[0]
        np.testing.assert_array_equal(picked, alone)
        # no pick: the prior's first candidate, unchecked
        off = full.with_(normal_pick_max_scale=None)
        first, report = normal_out("two", off, method=method)
        assert _made_by(report, "normal.png") == ["blurring"]
        assert not np.array_equal(first, picked)
