"""Texture sampling: glTF texel centres, wrap modes, KHR_texture_transform, gradients."""

import math

import pytest
import torch

from pbrsr_core.asset.model import CLAMP_TO_EDGE, MIRRORED_REPEAT, REPEAT, TextureRef
from pbrsr_core.render.texture import sample, sample_reference

MODES = [REPEAT, CLAMP_TO_EDGE, MIRRORED_REPEAT]


def test_texel_centres_return_texel_values():
    g = torch.Generator().manual_seed(0)
    tex = torch.rand(5, 7, 3, generator=g)
    ys, xs = torch.meshgrid(torch.arange(5), torch.arange(7), indexing="ij")
    uv = torch.stack([(xs.reshape(-1) + 0.5) / 7, (ys.reshape(-1) + 0.5) / 5], 1)
    out = sample(tex, uv)
    torch.testing.assert_close(out, tex.reshape(-1, 3), atol=1e-6, rtol=0)


@pytest.mark.parametrize("ws", MODES)
@pytest.mark.parametrize("wt", MODES)
def test_matches_reference_loop_with_transform(ws, wt):
    g = torch.Generator().manual_seed(1)
    tex = torch.rand(4, 6, 2, generator=g, dtype=torch.float64)
    uv = torch.rand(50, 2, generator=g, dtype=torch.float64) * 5.0 - 2.5
    c, s = math.cos(0.3), math.sin(0.3)
    # KHR_texture_transform: T * R * S, row-major 3x3
    m = (1.5 * c, 2.0 * s, 0.1, -1.5 * s, 2.0 * c, -0.2, 0.0, 0.0, 1.0)
    ref = TextureRef(image=0, uv_transform=m, wrap_s=ws, wrap_t=wt)
    torch.testing.assert_close(sample(tex, uv, ref), sample_reference(tex, uv, ref))


def test_wrap_modes_at_known_points():
    tex = torch.arange(4, dtype=torch.float64).view(1, 4, 1)  # texel x holds value x
    uv = torch.tensor([[1.125, 0.5], [-0.125, 0.5]], dtype=torch.float64)
    rep = sample(tex, uv, TextureRef(0, wrap_s=REPEAT)).squeeze(1)
    clamp = sample(tex, uv, TextureRef(0, wrap_s=CLAMP_TO_EDGE)).squeeze(1)
    mirror = sample(tex, uv, TextureRef(0, wrap_s=MIRRORED_REPEAT)).squeeze(1)
    # u = 1.125 -> x = 4.0 (texel 4): repeat -> texel 0, clamp -> 3, mirror -> 3
    torch.testing.assert_close(rep, torch.tensor([0.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(clamp, torch.tensor([3.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(mirror, torch.tensor([3.0, 0.0], dtype=torch.float64))


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck_float64(mode):
    g = torch.Generator().manual_seed(2)
    tex = torch.rand(3, 4, 2, generator=g, dtype=torch.float64, requires_grad=True)
    uv = torch.rand(12, 2, generator=g, dtype=torch.float64) * 3.0 - 1.0
    ref = TextureRef(
        0, uv_transform=(1.2, 0.1, 0.05, -0.1, 0.9, 0.0, 0.0, 0.0, 1.0), wrap_s=mode, wrap_t=mode
    )
    assert torch.autograd.gradcheck(lambda t: sample(t, uv, ref), (tex,))


def test_gradient_sums_weights_into_texels():
    tex = torch.zeros(2, 2, 1, dtype=torch.float64, requires_grad=True)
    uv = torch.tensor([[0.5, 0.5]], dtype=torch.float64)  # centre: 1/4 of each texel
    sample(tex, uv).sum().backward()
    torch.testing.assert_close(tex.grad, torch.full((2, 2, 1), 0.25, dtype=torch.float64))


def test_non_finite_uvs_give_finite_values():
    tex = torch.rand(3, 3, 3, requires_grad=True)
    uv = torch.tensor([[float("nan"), 0.2], [float("inf"), -float("inf")], [1e30, 1e-30]])
    out = sample(tex, uv, TextureRef(0))
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(tex.grad).all()


def test_shape_errors():
    with pytest.raises(ValueError, match="texture must be"):
        sample(torch.zeros(3, 3), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="uv must be"):
        sample(torch.zeros(3, 3, 1), torch.zeros(1, 3))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_numba_gather_and_scatter_match_torch(dtype):
    from pbrsr_core.render.texture import _Bilinear, gather_torch, prepare, scatter_torch

    g = torch.Generator().manual_seed(7)
    tex = torch.rand(13, 9, 3, generator=g, dtype=dtype)
    uv = torch.rand(500, 2, generator=g, dtype=dtype) * 2 - 0.5
    idx, w = prepare(uv, 13, 9, TextureRef(0))
    w = w.to(dtype)
    flat = tex.reshape(-1, 3).requires_grad_()
    out = _Bilinear.apply(flat, idx, w)
    torch.testing.assert_close(out, gather_torch(flat.detach(), idx, w))
    go = torch.rand(500, 3, generator=g, dtype=dtype)
    out.backward(go)
    torch.testing.assert_close(flat.grad, scatter_torch(go, idx, w, flat.shape[0]))
