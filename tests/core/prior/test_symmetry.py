"""The symmetries of the square on map images, and the self-ensembled prior."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import load_asset, make_quad_asset
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.bicubic import BicubicPrior
from pbrsr_core.prior.direct import upscale_map
from pbrsr_core.prior.symmetry import ORDER, SelfEnsemble, averaged, dihedral, inverse


class Leaning(Prior):
    """A "network" that is not symmetric: nearest upsampling plus a ramp that rises to the
    right, so a mirrored copy leans the other way; counts its calls."""

    name = "leaning"
    scales = (2, 4)
    back_project = False

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def _forward(self, x, scale):
        self.calls += 1
        up = F.interpolate(x, scale_factor=scale, mode="nearest")
        ramp = torch.linspace(0.0, 0.2, up.shape[-1])
        return up + ramp


def _normal_map(h: int, w: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(1, 3, h, w))
    v[:, 2] = np.abs(v[:, 2]) + 0.5
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return torch.from_numpy((v + 1.0) * 0.5).float()


@pytest.mark.parametrize("kind", ["colour", "normal"])
def test_each_symmetry_is_undone_by_its_inverse(kind: str):
    x = _normal_map(5, 7, seed=1)
    assert sorted(ORDER) == list(range(8))
    for op in range(8):
        assert torch.allclose(dihedral(dihedral(x, op, kind), inverse(op), kind), x, atol=1e-6)
    with pytest.raises(ValueError, match="op"):
        inverse(8)


def test_a_self_ensemble_of_bicubic_is_bicubic_on_colour_and_normal_maps():
    """Bicubic commutes with every symmetry: averaging its turned copies changes nothing."""
    bicubic = BicubicPrior()
    rgb = torch.rand(1, 3, 12, 9, generator=torch.Generator().manual_seed(2))
    normals = _normal_map(12, 9, seed=3)
    for kind, x in (("colour", rgb), ("normal", normals)):
        want = bicubic.upscale(x, 4)
        got = SelfEnsemble(bicubic, 8).for_kind(kind).upscale(x, 4)
        assert torch.allclose(got, want, atol=1e-5), kind


def test_a_normal_maps_copies_are_normal_maps_turned_with_their_vectors():
    """The prior sees each copy of a normal map as a normal map of the turned surface (X/Y
    turned with the pixels), which is what a normal network was trained on."""
    seen: list[torch.Tensor] = []

    class Recording(BicubicPrior):
        def _forward(self, x, scale):
            seen.append(x.clone())
            return super()._forward(x, scale)

    normals = _normal_map(6, 6, seed=4)
    SelfEnsemble(Recording(), 8, "normal").upscale(normals, 2)
    assert len(seen) == 8
    for op, x in zip(ORDER, seen, strict=True):
        assert torch.allclose(x, dihedral(normals, op, "normal"), atol=1e-6)
    flipped = dihedral(normals, 1, "normal") * 2 - 1  # a left-right mirror negates X
    assert torch.allclose(flipped[:, 0], -(normals * 2 - 1)[:, 0].flip(-1), atol=1e-6)


def test_a_self_ensemble_averages_what_a_prior_does_not_share_with_its_mirror():
    prior = Leaning()
    x = torch.full((1, 3, 4, 6), 0.4)
    one = prior.upscale(x, 2)
    assert one[0, 0, 0, -1] - one[0, 0, 0, 0] > 0.19  # leans right
    two = SelfEnsemble(prior, 2).upscale(x, 2)  # the identity and the half turn
    assert prior.calls == 3
    assert torch.allclose(two, torch.full_like(two, 0.5), atol=1e-6)  # 0.4 + the ramp's mean
    ticks: list[tuple[int, int]] = []
    SelfEnsemble(prior, 4).upscale(x, 2, progress=lambda d, t: ticks.append((d, t)))
    assert ticks[-1][0] == ticks[-1][1] and len(ticks) == 4 and prior.calls == 7
    with pytest.raises(ValueError, match="copies"):
        SelfEnsemble(prior, 3)


def test_the_preset_field_runs_every_prior_call_of_a_run_on_the_copies(tmp_path: Path, monkeypatch):
    """``self_ensemble`` 2: the init is the two copies' average, the prior runs twice per
    call, and the value is checked."""
    import pbrsr_core.pipeline as pipeline
    from pbrsr_core.optim import presets

    prior = Leaning()
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior if n == "l" else real(n, d))
    rng = np.random.default_rng(7)
    tex = np.clip(rng.random((32, 32, 3)) * 0.6 + 0.2, 0, 1).astype(np.float32)
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": tex})
    lr = load_asset(asset).images[0].pixels
    frozen = presets.FAST.with_(iterations=0, check_prior=(), max_prior_scale=None, project_lr=())
    for n in (1, 2):
        monkeypatch.setitem(presets.PRESETS, "fast", frozen.with_(self_ensemble=n))
        prior.calls = 0
        report = upscale_asset(asset, tmp_path / f"o{n}", UpscaleOptions(preset="fast", prior="l"))
        assert prior.calls == n and report["prior_used"] == "leaning"
        got = load_asset(tmp_path / f"o{n}" / "q.gltf").images[0].pixels
        want = upscale_map(SelfEnsemble(prior, n), lr, "base_color", 4)
        assert np.abs(got - want).max() <= 0.6 / 255, n
    assert np.abs(want - upscale_map(prior, lr, "base_color", 4)).max() > 0.05
    with pytest.raises(InvalidOptions, match="self_ensemble"):
        frozen.with_(self_ensemble=3)


def test_averaged_wraps_only_a_network_on_several_copies():
    net, bicubic = Leaning(), BicubicPrior()
    assert averaged(net, 1) is net and averaged(bicubic, 8) is bicubic
    four = averaged(net, 4)
    assert isinstance(four, SelfEnsemble) and four.inner is net and four.n == 4


def test_copies_per_kind_run_each_kind_on_its_own_number():
    """``by_kind`` {"normal": 2}: normal maps on two copies (the prior and its candidates),
    every other kind on ``n``; a kind given ``n`` itself, or bicubic, wraps nothing."""
    net = Leaning()
    normal = averaged(net, 1, {"normal": 2})
    assert isinstance(normal, SelfEnsemble)
    assert normal.for_kind("colour") is net and normal.candidates("data", 2) == [net]
    for made in (normal.for_kind("normal"), *normal.candidates("normal", 2)):
        assert isinstance(made, SelfEnsemble) and made.n == 2 and made.kind == "normal"
    x = _normal_map(6, 6, 3)
    net.calls = 0
    got = normal.for_kind("normal").upscale(x, 2)
    assert net.calls == 2
    assert torch.equal(got, SelfEnsemble(net, 2, "normal").upscale(x, 2))
    net.calls = 0
    normal.for_kind("colour").upscale(x, 2)
    assert net.calls == 1
    eight = averaged(net, 8, {"normal": 1, "data": 8})
    assert isinstance(eight, SelfEnsemble) and eight.by_kind == {"normal": 1}
    assert eight.for_kind("normal") is net and eight.for_kind("data").n == 8
    assert averaged(net, 2, {"colour": 2}).by_kind == {}
    assert averaged(BicubicPrior(), 1, {"normal": 8}).name == "bicubic"
    assert not isinstance(averaged(BicubicPrior(), 1, {"normal": 8}), SelfEnsemble)
    with pytest.raises(ValueError, match="copies, not 3"):
        SelfEnsemble(net, 1, by_kind={"normal": 3})


def test_the_preset_field_per_kind_runs_only_the_normal_map_on_copies(tmp_path: Path, monkeypatch):
    """``self_ensemble_by_kind`` {"normal": 2} in a preset: the colour map through the prior
    once, the normal map twice, which its init shows, and once above ``self_ensemble_max_scale``;
    unknown kinds and counts are refused."""
    import pbrsr_core.pipeline as pipeline
    from pbrsr_core.optim import presets

    prior = Leaning()
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: prior if n == "l" else real(n, d))
    rng = np.random.default_rng(8)
    tex = np.clip(rng.random((32, 32, 3)) * 0.6 + 0.2, 0, 1).astype(np.float32)
    normal = _normal_map(32, 32, 4)[0].permute(1, 2, 0).numpy()
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": tex, "normal": normal})
    frozen = presets.FAST.with_(iterations=0, check_prior=(), max_prior_scale=None, project_lr=())
    got = {}
    for by_kind in ({}, {"normal": 2}):
        monkeypatch.setitem(presets.PRESETS, "fast", frozen.with_(self_ensemble_by_kind=by_kind))
        prior.calls = 0
        out = tmp_path / f"o{len(by_kind)}"
        upscale_asset(asset, out, UpscaleOptions(preset="fast", prior="l"))
        assert prior.calls == 2 + len(by_kind)
        images = load_asset(out / "q.gltf").images
        got[len(by_kind)] = {next(iter(i.roles)): i.pixels for i in images}
    assert np.array_equal(got[0]["base_color"], got[1]["base_color"])
    assert np.abs(got[0]["normal"] - got[1]["normal"]).max() > 0.05
    assert presets.BALANCED.self_ensemble_by_kind == {"normal": 2}
    assert all(not p.self_ensemble_by_kind for p in (presets.FAST, presets.QUALITY, presets.PAPER))
    # above self_ensemble_max_scale the normal map runs once: x4 makes the maps of no copies,
    # x2 still takes its two copies
    capped = frozen.with_(self_ensemble_by_kind={"normal": 2}, self_ensemble_max_scale=2)
    monkeypatch.setitem(presets.PRESETS, "fast", capped)
    for scale, calls in ((4, 2), (2, 3)):
        prior.calls = 0
        out = tmp_path / f"capped{scale}"
        upscale_asset(asset, out, UpscaleOptions(preset="fast", prior="l", scale=scale))
        assert prior.calls == calls, scale
    images = load_asset(tmp_path / "capped4" / "q.gltf").images
    assert all(np.array_equal(i.pixels, got[0][next(iter(i.roles))]) for i in images)
    assert capped.copies(4) == (1, {}) and capped.copies(2) == (1, {"normal": 2})
    assert presets.BALANCED.copies(8) == (1, {}) and presets.BALANCED.copies(4)[1] == {"normal": 2}
    assert presets.QUALITY.copies(8) == (8, {})
    assert averaged(prior, 8, presets.QUALITY.self_ensemble_by_kind).for_kind("normal").n == 8
    for bad in ({"normal": 3}, {"normals": 2}):
        with pytest.raises(InvalidOptions, match="self_ensemble_by_kind"):
            frozen.with_(self_ensemble_by_kind=bad)
    with pytest.raises(InvalidOptions, match="self_ensemble_max_scale"):
        frozen.with_(self_ensemble_max_scale=1)
