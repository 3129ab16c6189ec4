"""The direct-prior map helpers: channel layouts, alpha, normal directions and lengths."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.degrade import degrade_tensor
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.direct import (
    bicubic_map,
    keep_normal_length,
    prior_factor,
    project_map,
    renormalize_encoded_normals,
    upscale_map,
)


class Nearest(Prior):
    """A trivially checkable prior: nearest-neighbour x2."""

    name = "nearest"
    scales = (2,)
    back_project = False  # these tests check the channel conventions on exact outputs

    def _forward(self, x, scale):
        return F.interpolate(x, scale_factor=scale, mode="nearest")


def _bicubic_np(a: np.ndarray, s: int) -> np.ndarray:
    t = torch.from_numpy(a).permute(2, 0, 1)[None]
    return F.interpolate(t, scale_factor=s, mode="bicubic")[0].permute(1, 2, 0).numpy()


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_layouts_and_alpha(channels):
    rng = np.random.default_rng(0)
    px = rng.random((6, 7, channels), dtype=np.float32)
    out = upscale_map(Nearest(), px, "base_color", 2)
    assert out.shape == (12, 14, channels) and out.dtype == np.float32
    n_colour = 3 if channels >= 3 else 1
    # colour channels went through the prior (nearest here)
    np.testing.assert_allclose(out[::2, ::2, :n_colour], px[:, :, :n_colour], atol=1e-6)
    np.testing.assert_allclose(out[1::2, 1::2, :n_colour], px[:, :, :n_colour], atol=1e-6)
    if channels in (2, 4):  # alpha: bicubic on its own, clamped
        ref = np.clip(_bicubic_np(px[:, :, -1:], 2), 0, 1)
        np.testing.assert_allclose(out[:, :, -1:], ref, atol=1e-5)


def test_normal_maps_are_renormalised_with_positive_z():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(8, 8, 3)).astype(np.float32)
    n[..., 2] = np.abs(n[..., 2]) + 0.2
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    enc = (n + 1) / 2
    for out in (
        bicubic_map(enc, "normal", 4),
        upscale_map(load_prior("bicubic"), enc, "normal", 4),
    ):
        dec = out * 2 - 1
        np.testing.assert_allclose(np.linalg.norm(dec, axis=-1), 1.0, atol=1e-5)
        assert (dec[..., 2] > 0).all()
        # texel centres of the input are kept (up to renormalisation of a near-unit vector)
        assert np.abs(dec[1::4, 1::4] - n).max() < 0.25
    # a flat-but-flipped normal becomes z >= 1e-3
    flipped = renormalize_encoded_normals(torch.tensor([[[[0.5]], [[0.5]], [[0.0]]]]))
    assert torch.allclose(flipped.flatten(), torch.tensor([0.5, 0.5, 1.0]))


def _normal_field(size: int, length: float) -> np.ndarray:
    """A smooth encoded normal map (size, size, 3) whose vectors are ``length`` long."""
    y, x = np.mgrid[0:size, 0:size] / size * 2 * np.pi
    n = np.stack([0.4 * np.sin(x + 0.5 * y), 0.3 * np.cos(2 * y), np.ones_like(x)], -1)
    n *= length / np.linalg.norm(n, axis=-1, keepdims=True)
    return ((n + 1) / 2).astype(np.float32)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a.astype(np.float64) - b) ** 2)))


@pytest.mark.parametrize("length", [0.9, 0.97])
def test_normal_maps_keep_the_inputs_length(length):
    """A normal map stored at |n| < 1 (as JPEG-compressed and mipmapped bakes are) comes out
    at that length, directions as upscaled: closer to the HR map than unit vectors are."""
    hr = _normal_field(128, length)
    lr = degrade_tensor(torch.from_numpy(hr).permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    lr = lr.clamp(0, 1).numpy()
    unit = renormalize_encoded_normals(torch.from_numpy(hr).permute(2, 0, 1)[None])
    unit_ref = unit[0].permute(1, 2, 0).numpy()
    for out in (
        bicubic_map(lr, "normal", 4),
        upscale_map(load_prior("bicubic"), lr, "normal", 4),
        project_map(bicubic_map(lr, "normal", 4), lr, 4, "normal"),
        keep_normal_length(unit_ref, lr, 4),
    ):
        dec = out * 2 - 1
        got = np.linalg.norm(dec, axis=-1)
        assert abs(float(got.mean()) - length) < 0.01 and got.std() < 0.01
        assert (dec[..., 2] > 0).all()
        unit_out = dec / got[..., None] / 2 + 0.5
        # the length is the input's, the PSNR is that of the directions plus nothing
        assert _psnr(out, hr) > _psnr(unit_out, hr) + 3.0
    # directions are those of the unit-length result
    np.testing.assert_allclose(
        keep_normal_length(unit_ref, lr, 4) * 2 - 1,
        (unit_ref * 2 - 1)
        * np.linalg.norm(bicubic_map(lr, "normal", 4) * 2 - 1, axis=-1)[..., None],
        atol=1e-5,
    )


def test_bicubic_map_matches_torch_for_data_maps():
    rng = np.random.default_rng(2)
    px = rng.random((9, 5, 3), dtype=np.float32)
    out = bicubic_map(px, "metallic_roughness", 2)
    np.testing.assert_allclose(out, np.clip(_bicubic_np(px, 2), 0, 1), atol=1e-6)
    assert bicubic_map(px, "data", 2).shape == (18, 10, 3)
    with pytest.raises(ValueError, match="unknown map role"):
        bicubic_map(px, "albedo-ish", 2)
    with pytest.raises(ValueError):
        bicubic_map(np.zeros((4, 4, 5), np.float32), "data", 2)


def test_direct_stays_in_range():
    """NaNs and out-of-range values in a stored map never reach the output."""
    px = np.full((8, 8, 4), 0.5, np.float32)
    px[2, 2, 0] = np.nan
    px[3, 3, 1] = 7.0
    out = upscale_map(load_prior("bicubic"), px, "colour", 2)
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1


class RecordingNearest(Prior):
    """Nearest-neighbour x2 / x4 / x8 that records the factors it was asked for; it
    back-projects like a network prior."""

    name = "recording-nearest"
    scales = (2, 4, 8)

    def __init__(self):
        super().__init__()
        self.calls: list[int] = []

    def _forward(self, x, scale):
        self.calls.append(scale)
        return F.interpolate(x, scale_factor=scale, mode="nearest")


@pytest.mark.parametrize(
    ("scales", "scale", "max_scale", "factor", "one_pass"),
    [
        ((2, 4, 8), 4, None, 4, ()),
        ((2, 4, 8), 4, 2, 2, ()),
        ((2, 4, 8), 4, 2, 4, (2, 4)),  # one pass makes x4: it costs what an x2 pass does
        ((2, 4, 8), 8, 2, 4, (2, 4)),  # x8 is two passes: one of them
        ((2, 4, 8), 4, 8, 4, ()),
        ((2, 4, 8), 8, 2, 2, (2,)),
        ((2, 4, 8), 8, 4, 4, ()),
        ((2, 4, 8), 8, 3, 2, ()),
        ((2, 3, 4, 8), 3, 2, 3, ()),  # nothing at most 2 divides 3: the whole scale
        ((4,), 4, 2, 4, ()),  # a x4-only network does the whole scale
    ],
)
def test_prior_factor(scales, scale, max_scale, factor, one_pass):
    prior = RecordingNearest()
    prior.scales, prior.one_pass_scales = scales, one_pass
    assert prior_factor(prior, scale, max_scale) == factor
    assert prior_factor(load_prior("bicubic"), scale, max_scale) == scale  # not a network


def test_max_prior_scale_runs_the_prior_at_part_of_the_scale():
    """x4 with the prior at most x2: one x2 call, bicubic the rest, then the result is
    projected onto the LR map at x4 (one step: the LR model gives the LR map back closer than
    the unprojected bicubic of the prior's x2 does)."""
    rng = np.random.default_rng(3)
    smooth = F.avg_pool2d(torch.from_numpy(rng.random((1, 3, 64, 64), dtype=np.float32)), 4)
    px = smooth[0].permute(1, 2, 0).numpy().copy()  # (16, 16, 3), in [0, 1]
    prior = RecordingNearest()
    out = upscale_map(prior, px, "base_color", 4, max_prior_scale=2)
    assert prior.calls == [2] and out.shape == (64, 64, 3)
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1

    def lr_error(hr: np.ndarray) -> float:
        t = torch.from_numpy(np.ascontiguousarray(hr)).permute(2, 0, 1)[None]
        back = degrade_tensor(t, 4)[0].permute(1, 2, 0).numpy()
        return float(np.abs(back - px).mean())

    plain = prior.upscale(torch.from_numpy(px).permute(2, 0, 1)[None], 2)
    plain = F.interpolate(plain, scale_factor=2, mode="bicubic").clamp(0, 1)
    assert lr_error(out) < 0.7 * lr_error(plain[0].permute(1, 2, 0).numpy())
    prior.calls.clear()
    assert upscale_map(prior, px, "base_color", 4).shape == (64, 64, 3)
    assert prior.calls == [4]  # no limit: the whole scale


class MixingNearest(Prior):
    """Nearest x2 whose every output channel is the mean of the input's channels: a network
    that lets colour channels bleed into each other, at its worst. Records the images it sees."""

    name = "mixing-nearest"
    scales = (2,)
    back_project = False

    def __init__(self):
        super().__init__()
        self.images = 0

    def _forward(self, x, scale):
        self.images += x.shape[0]
        up = F.interpolate(x.mean(1, keepdim=True), scale_factor=scale, mode="nearest")
        return up.expand(-1, 3, -1, -1)


def test_data_maps_run_channel_by_channel_as_greyscale_images():
    """An ORM image's channels are unrelated maps: each goes through the prior on its own, so
    a prior that mixes colour channels leaves them apart; a colour map goes through whole."""
    rng = np.random.default_rng(4)
    px = rng.random((6, 7, 3), dtype=np.float32)
    out = upscale_map(MixingNearest(), px, "metallic_roughness", 2)
    np.testing.assert_allclose(out[::2, ::2], px, atol=1e-6)
    np.testing.assert_allclose(out[1::2, 1::2], px, atol=1e-6)
    mixed = upscale_map(MixingNearest(), px, "base_color", 2)
    np.testing.assert_allclose(mixed[::2, ::2], px.mean(2, keepdims=True).repeat(3, 2), atol=1e-6)


def test_a_data_maps_prior_runs_on_the_channels_named_only():
    """``channels``: the prior sees those channels alone; the others are bicubic's."""
    rng = np.random.default_rng(5)
    px = rng.random((6, 7, 3), dtype=np.float32)
    prior = MixingNearest()
    out = upscale_map(prior, px, "data", 2, channels=[2])
    assert prior.images == 1
    np.testing.assert_allclose(out[::2, ::2, 2], px[..., 2], atol=1e-6)
    np.testing.assert_allclose(out[..., :2], bicubic_map(px, "data", 2)[..., :2], atol=1e-6)
    prior.images = 0
    np.testing.assert_allclose(upscale_map(prior, px, "data", 2, channels=[]),
                               bicubic_map(px, "data", 2), atol=1e-6)  # fmt: skip
    assert prior.images == 0


def test_equal_channels_of_a_data_map_run_the_prior_once():
    """A grey image is read as three equal channels: the prior runs on one of each set of
    equal channels, and the others take its output (what the prior makes of the same input)."""
    rng = np.random.default_rng(6)
    grey = rng.random((6, 7, 1), dtype=np.float32)
    px = np.concatenate([grey, rng.random((6, 7, 1), dtype=np.float32), grey], -1)
    ticks: list[tuple[int, int]] = []
    prior = MixingNearest()
    out = upscale_map(prior, px, "data", 2, progress=lambda d, t: ticks.append((d, t)))
    assert prior.images == 2  # R and B are equal: one run for both
    assert np.array_equal(out[..., 0], out[..., 2])
    each = MixingNearest()
    for c in range(3):  # the same as each channel run on its own
        alone = upscale_map(each, px, "data", 2, channels=[c])[..., c]
        assert np.array_equal(out[..., c], alone)
    assert ticks[-1][0] == ticks[-1][1] and ticks == sorted(ticks)  # the copy ends the map
    prior.images = 0
    out = upscale_map(prior, np.repeat(grey, 3, -1), "data", 2)
    assert prior.images == 1 and np.array_equal(out[..., 0], out[..., 1])
    # channels a run leaves to bicubic are not copied from the prior's
    prior.images = 0
    out = upscale_map(prior, np.repeat(grey, 3, -1), "data", 2, channels=[0])
    assert prior.images == 1
    np.testing.assert_allclose(out[..., 1:], bicubic_map(px, "data", 2)[..., [0, 0]], atol=1e-6)
