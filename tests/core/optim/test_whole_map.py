"""The fused whole-map kernels (numba, CPU) against plain torch references: TV value and
gradient (float64 gradcheck), projection, Adam fused with projection, gradient masking and
island dilation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pbrsr_core.optim.losses import MapGroup
from pbrsr_core.optim.whole_map import (
    MapAdam,
    accumulate_map_grad_,
    dilate_islands,
    mask_grad_,
    project_,
    tv_loss,
)

REPEATS = [(False, False), (True, False), (False, True), (True, True)]


def _tv_reference(
    t: torch.Tensor, groups: list[MapGroup], repeats: tuple[bool, bool] = (False, False)
) -> torch.Tensor:
    """Mean |difference| per axis and group; along a repeating axis the last texel's
    neighbour is the first (torch.roll)."""
    total = t.new_zeros(())
    for g in groups:
        x = t[..., list(g.channels)]
        for dim, rep in ((1, repeats[0]), (0, repeats[1])):
            if x.shape[dim] < 2:
                continue
            if rep:
                total = total + (torch.roll(x, -1, dims=dim) - x).abs().mean()
            else:
                n = x.shape[dim]
                total = total + (x.narrow(dim, 1, n - 1) - x.narrow(dim, 0, n - 1)).abs().mean()
    return total


@pytest.mark.parametrize("repeats", REPEATS)
def test_tv_matches_torch_value_and_gradient(repeats):
    g = torch.Generator().manual_seed(3)
    groups = [MapGroup("base_color", (0, 1, 2)), MapGroup("metallic", (3,), 0.1)]
    for shape in [(17, 23, 4), (1, 9, 4), (9, 1, 4), (1, 1, 4), (64, 48, 5)]:
        for dtype in (torch.float32, torch.float64):
            t = torch.rand(shape, generator=g, dtype=dtype)
            t[:2, :2] = 0.5  # exact zeros among the differences (subgradient 0, as torch)
            a = t.clone().requires_grad_()
            b = t.clone().requires_grad_()
            va = tv_loss(a, groups, repeats)
            vb = _tv_reference(b, groups, repeats) + 0.0 * b.sum()
            va.backward()
            vb.backward()
            tol = 1e-12 if dtype == torch.float64 else 1e-5
            va, vb = va.item(), vb.item()
            assert abs(va - vb) <= tol * max(1.0, vb)
            assert torch.allclose(a.grad, b.grad, atol=tol, rtol=0)
            assert a.grad[..., 4:].abs().sum() == 0  # a channel no group reads gets nothing


@pytest.mark.parametrize("repeats", REPEATS)
def test_tv_overlapping_groups_add_and_gradcheck(repeats):
    g = torch.Generator().manual_seed(4)
    t = torch.rand(6, 7, 3, generator=g, dtype=torch.float64).requires_grad_()
    groups = [MapGroup("a", (0, 1)), MapGroup("b", (1, 2))]
    assert torch.allclose(tv_loss(t, groups, repeats), _tv_reference(t, groups, repeats))
    assert torch.autograd.gradcheck(lambda x: tv_loss(x, groups, repeats) * 3.0, (t,))


def test_tv_of_a_repeating_ramp_counts_the_wrap_edge():
    """A ramp 0, 1/3, 2/3, 1 along x: without repeat mean |dx| = 1/3; repeating, the step from
    1 back to 0 counts too: (3 * 1/3 + 1) / 4 = 1/2. Along y it is constant either way."""
    t = torch.linspace(0, 1, 4, dtype=torch.float64).view(1, 4, 1).expand(3, 4, 1).contiguous()
    r = [MapGroup("r", (0,))]
    assert float(tv_loss(t, r)) == pytest.approx(1 / 3)
    assert float(tv_loss(t, r, (True, False))) == pytest.approx(0.5)
    assert float(tv_loss(t, r, (False, True))) == pytest.approx(1 / 3)
    # a map that tiles seamlessly along x (0, 1, 1, 0) has no extra cost from repeating
    seamless = torch.tensor([0.0, 1.0, 1.0, 0.0], dtype=torch.float64).view(1, 4, 1)
    assert float(tv_loss(seamless, r)) == pytest.approx(2 / 3)
    assert float(tv_loss(seamless, r, (True, False))) == pytest.approx(2 / 4)


def test_project_matches_reference_and_sanitises():
    g = torch.Generator().manual_seed(5)
    t = torch.rand(8, 9, 3, generator=g) * 1.6 - 0.3
    t[0, 0] = float("nan")
    t[0, 1] = torch.tensor([float("inf"), float("-inf"), 0.5])
    t[0, 2] = 0.5  # zero-length normal -> (0, 0, 1)
    t[0, 3] = torch.tensor([0.5, 0.5, 0.0])  # pointing inwards -> z clamped up
    ref = torch.nan_to_num(t.clone(), nan=0.0, posinf=1.0, neginf=0.0).clamp(0, 1)
    col = t.clone()
    project_(col, is_normal=False)
    assert torch.equal(col, ref)
    n = ref * 2 - 1
    n[..., 2].clamp_(min=1e-3)
    n = (n / n.norm(dim=-1, keepdim=True) * 0.5 + 0.5).clamp(0, 1)
    nm = t.clone()
    project_(nm, is_normal=True)
    assert torch.allclose(nm, n, atol=1e-6)
    dec = nm * 2 - 1
    assert torch.allclose(dec.norm(dim=-1), torch.ones(8, 9), atol=1e-5)
    assert (dec[..., 2] > 0).all() and torch.isfinite(nm).all()
    assert torch.allclose(nm[0, 2], torch.tensor([0.5, 0.5, 1.0]))
    strided = t.clone().permute(1, 0, 2)  # not contiguous: the torch path, same numbers
    project_(strided, is_normal=True)
    assert torch.allclose(strided.permute(1, 0, 2), n, atol=1e-6)


def test_map_adam_is_torch_adam_then_projection():
    """Equal rates: torch's Adam followed by project_. Mixed rates: each channel's update is
    Adam's at the largest rate times its share (Adam's step does not depend on the rate
    otherwise). A rate of 0 freezes a channel; a map with only zero rates is not optimised."""
    gen = torch.Generator().manual_seed(5)
    owned = torch.ones(4, dtype=torch.bool)
    for normal, shape in [(False, (33, 21, 4)), (True, (16, 40, 3))]:
        init = torch.rand(shape, generator=gen)
        project_(init, normal)
        grads = [torch.randn(shape, generator=gen) * 10.0**-k for k in (2, 4, 6, 3, 5)]
        ref = init.clone().requires_grad_()
        opt = torch.optim.Adam([ref], lr=3e-2)
        for g in grads:
            ref.grad = g.clone()
            opt.step()
            with torch.no_grad():
                project_(ref, normal)
        p = init.clone().requires_grad_()
        c = shape[2]
        adam = MapAdam({0: p}, {0: torch.full((c,), 3e-2)}, {0: normal}, {0: owned[:c]})
        for g in grads:
            p.grad = g.clone()
            adam.step()
        assert torch.allclose(p.detach(), ref.detach(), atol=2e-6), normal
    # mixed rates: one step from a fresh Adam moves each channel by rate * m / (sqrt(v) + eps)
    init = torch.rand(8, 8, 4, generator=gen) * 0.5 + 0.25
    g = torch.randn(8, 8, 4, generator=gen)
    rates = torch.tensor([1e-2, 0.0, 5e-3, 1e-2])
    p = init.clone().requires_grad_()
    adam = MapAdam({0: p}, {0: rates}, {0: False}, {0: owned})
    p.grad = g.clone()
    adam.step()
    want = init - rates * g / (g.abs() + 1e-8)  # Adam's first step: lr * sign(g)
    assert torch.allclose(p.detach(), want, atol=1e-6)
    assert torch.equal(p.detach()[..., 1], init[..., 1])
    # unowned channels do not make a map "mixed"; all-zero rates leave it out
    q = torch.rand(4, 4, 3, generator=gen).requires_grad_()
    r = torch.rand(4, 4, 1, generator=gen).requires_grad_()
    adam = MapAdam(
        {0: q, 1: r},
        {0: torch.tensor([0.0, 1e-3, 1e-3]), 1: torch.zeros(1)},
        {0: False, 1: False},
        {0: torch.tensor([False, True, True]), 1: torch.ones(1, dtype=torch.bool)},
    )
    assert adam.scale == {} and adam.opt.lrs == pytest.approx([1e-3])
    # NaN gradients never reach a map: non-finite values are projected into [0, 1]
    p.grad = torch.full((8, 8, 4), float("nan"))
    MapAdam({0: p}, {0: rates}, {0: False}, {0: owned}).step()
    assert torch.isfinite(p.detach()).all() and p.min() >= 0 and p.max() <= 1


def test_mask_grad_zeroes_masked_and_non_finite():
    g = torch.randn(5, 6, 3, generator=torch.Generator().manual_seed(6))
    g[1, 1, 0] = float("nan")
    g[2, 2, 1] = float("inf")
    texels = torch.rand(5, 6, generator=torch.Generator().manual_seed(7)) > 0.3
    channels = torch.tensor([True, True, False])
    want = torch.nan_to_num(g.clone(), nan=0.0, posinf=0.0, neginf=0.0)
    want = want * (texels[..., None] & channels)
    mask_grad_(g, texels, channels)
    assert torch.equal(g, want)


def _dilate_reference(x: np.ndarray, m: np.ndarray, rings: int) -> np.ndarray:
    out = x.astype(np.float64).copy()
    filled = m.copy()
    h, w, _ = x.shape
    for _ in range(rings):
        new = {}
        for i in range(h):
            for j in range(w):
                if filled[i, j]:
                    continue
                nb = [
                    out[a, b]
                    for a in range(max(0, i - 1), min(h, i + 2))
                    for b in range(max(0, j - 1), min(w, j + 2))
                    if filled[a, b]
                ]
                if nb:
                    new[i, j] = np.mean(nb, axis=0)
        for (i, j), v in new.items():
            out[i, j] = v
            filled[i, j] = True
    return out.astype(x.dtype)


def test_dilate_matches_ring_by_ring_reference():
    rng = np.random.default_rng(8)
    x = rng.random((13, 11, 2), dtype=np.float32)
    m = np.zeros((13, 11), bool)
    m[2:4, 2:5] = True
    m[9, 8] = True
    for rings in (0, 1, 3, 20):
        got = dilate_islands(x, m, rings)
        assert np.allclose(got, _dilate_reference(x, m, rings), atol=1e-6)
        assert np.array_equal(got[m], x[m])
    t = torch.from_numpy(x).double()
    assert torch.allclose(
        dilate_islands(t, torch.from_numpy(m), 2),
        torch.from_numpy(_dilate_reference(x.astype(np.float64), m, 2)),
    )


@pytest.mark.parametrize("repeats", REPEATS)
def test_accumulate_map_grad_equals_autograd_of_tv_and_consistency(repeats):
    from pbrsr_core.optim.losses import avg_pool_map, pbr_consistency, pooled_consistency

    g = torch.Generator().manual_seed(9)
    s = 2
    t = torch.rand(8, 6, 3, generator=g, dtype=torch.float64)
    lr = torch.rand(4, 3, 3, generator=g, dtype=torch.float64)
    render_grad = torch.randn(8, 6, 3, generator=g, dtype=torch.float64)
    render_grad[0, 0, 0] = float("nan")
    groups = [MapGroup("base_color", (0, 1)), MapGroup("metallic", (2,), 0.1)]
    texels = torch.rand(8, 6, generator=g) > 0.25
    channels = torch.tensor([True, False, True])
    # reference: autograd through the full-size losses
    x = t.clone().requires_grad_()
    ref_tv = _tv_reference(x, groups, repeats)
    (10.0 * pbr_consistency(x, lr, s, groups, 10.0)[0] + 0.5 * ref_tv).backward()
    want = torch.nan_to_num(x.grad + render_grad, nan=0.0) * (texels[..., None] & channels)
    want[0, 0, 0] = 0.0
    # fused: the consistency gradient at LR size, spread by the kernel
    pooled = avg_pool_map(t, s).requires_grad_()
    (10.0 * pooled_consistency(pooled, lr, groups, 10.0)[0]).backward()
    for contiguous in (True, False):
        grad = render_grad.clone()
        if not contiguous:  # the torch path (other devices) must give the same numbers
            grad = grad.permute(1, 0, 2).contiguous().permute(1, 0, 2)
        tv = accumulate_map_grad_(t, grad, groups, 0.5, pooled.grad, s, texels, channels, repeats)
        assert abs(tv - float(ref_tv.detach())) < 1e-12
        assert torch.allclose(grad, want, atol=1e-12)


@pytest.mark.parametrize("repeats", REPEATS)
@pytest.mark.parametrize("shape", [(1, 5, 3), (5, 1, 1), (1, 1, 2), (7, 9, 4), (16, 12, 3)])
def test_accumulate_map_grad_kernel_matches_torch_path_on_edges_float32(shape, repeats):
    """The fused kernel (contiguous CPU gradient) against the plain torch path (the same call
    with a non-contiguous gradient) on maps one texel wide or high and several channel counts,
    scale 1 for odd sizes."""
    h, w, c = shape
    s = 2 if h % 2 == 0 and w % 2 == 0 else 1
    g = torch.Generator().manual_seed(h * 100 + w * 10 + c)
    t = torch.rand(h, w, c, generator=g)
    t[0, 0, 0] = t[0, -1, 0]  # equal neighbours: sign 0
    render_grad = torch.randn(h, w, c, generator=g)
    render_grad.view(-1)[-1] = float("inf")
    pool_grad = torch.randn(h // s, w // s, c, generator=g)
    groups = [MapGroup("base_color", tuple(range(c)))]
    texels = torch.rand(h, w, generator=g) > 0.2
    channels = torch.ones(c, dtype=torch.bool)
    channels[-1] = c == 1
    fused = render_grad.clone()
    plain = render_grad.clone().permute(1, 0, 2).contiguous().permute(1, 0, 2)
    tv_f = accumulate_map_grad_(t, fused, groups, 0.5, pool_grad, s, texels, channels, repeats)
    tv_p = accumulate_map_grad_(t, plain, groups, 0.5, pool_grad, s, texels, channels, repeats)
    assert abs(tv_f - tv_p) <= 1e-6 * max(1.0, abs(tv_p))
    assert torch.isfinite(fused).all()
    assert torch.allclose(fused, plain, atol=1e-6)
