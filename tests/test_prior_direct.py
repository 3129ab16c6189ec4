"""The direct-prior map helpers: channel layouts, alpha, normal renormalisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.prior import load_prior
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.direct import bicubic_map, renormalize_encoded_normals, upscale_map


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
