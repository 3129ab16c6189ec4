"""The PBR-SR losses against references: skimage SSIM, hand-computed values, gradcheck."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from pbrsr_core.optim.losses import (
    MapGroup,
    avg_pool_map,
    consistency_psnr,
    pbr_consistency,
    pooled_consistency,
    robust_pixel_loss,
    robust_pixel_terms,
    sample_weights,
    ssim_target,
    upsample_weights,
)
from pbrsr_core.optim.ssim import ssim_per_channel, window_size_for
from pbrsr_core.optim.whole_map import tv_loss


def _sk_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a,
        b,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )


@pytest.mark.parametrize("shape", [(32, 40, 3), (11, 11, 1), (17, 64, 2)])
def test_ssim_matches_skimage(shape):
    rng = np.random.default_rng(1)
    a = rng.random(shape)
    b = np.clip(a + 0.2 * rng.standard_normal(shape), 0, 1)
    ours = ssim_per_channel(
        torch.from_numpy(a).permute(2, 0, 1)[None], torch.from_numpy(b).permute(2, 0, 1)[None]
    )
    assert ours.dtype == torch.float64
    assert float(ours.mean()) == pytest.approx(_sk_ssim(a, b), abs=1e-10)


def test_ssim_identical_is_one_and_small_images_are_finite():
    x = torch.rand(1, 3, 20, 20, dtype=torch.float64)
    assert torch.allclose(ssim_per_channel(x, x), torch.ones(1, 3, dtype=torch.float64))
    assert (
        window_size_for(4, 9) == 3 and window_size_for(1, 1) == 1 and window_size_for(64, 64) == 11
    )
    # 1x1: SSIM = luminance term (2xy + c1)(c2) / ((x^2 + y^2 + c1)(c2)).
    a = torch.tensor([[[[0.3]]]], dtype=torch.float64)
    b = torch.tensor([[[[0.5]]]], dtype=torch.float64)
    c1 = 0.01**2
    want = (2 * 0.3 * 0.5 + c1) / (0.3**2 + 0.5**2 + c1)
    assert float(ssim_per_channel(a, b)) == pytest.approx(want, rel=1e-12)
    z = torch.zeros(1, 1, 5, 3)
    assert torch.isfinite(ssim_per_channel(z, z)).all()


def test_robust_loss_hand_computed():
    # One view, 1x2 pixels, 1 channel. W = (1, 0.5); errors (pred - target) = (1, 2).
    pred = torch.tensor([[[[1.0], [2.0]]]], dtype=torch.float64)
    target = torch.zeros_like(pred)
    w = torch.tensor([[[1.0, 0.5]]], dtype=torch.float64)
    l_pix, reg = robust_pixel_loss(pred, target, w)
    # (1*1 + 0.25*4) / (1 + 0.25) = 1.6 ; R = mean((1-1)^2, (1-0.25)^2) = 0.28125
    assert float(l_pix) == pytest.approx(1.6)
    assert float(reg) == pytest.approx(0.28125)
    # With the second pixel not covered only the first counts in L_pix, R is unchanged.
    l_pix, reg = robust_pixel_loss(pred, target, w, torch.tensor([[[True, False]]]))
    assert float(l_pix) == pytest.approx(1.0) and float(reg) == pytest.approx(0.28125)


def test_robust_loss_two_views_mean_and_reg_sum():
    # Colour error sums channels; L_pix averages views, R sums them.
    pred = torch.zeros(2, 1, 1, 2, dtype=torch.float64)
    target = torch.tensor([[[[1.0, 1.0]]], [[[3.0, 0.0]]]], dtype=torch.float64)
    w = torch.tensor([[[0.5]], [[1.0]]], dtype=torch.float64)
    l_pix, reg = robust_pixel_loss(pred, target, w)
    assert float(l_pix) == pytest.approx((2.0 + 9.0) / 2)
    assert float(reg) == pytest.approx((1 - 0.25) ** 2 + 0.0)


def test_robust_loss_is_normalised_per_view():
    g = torch.Generator().manual_seed(0)
    pred = torch.rand(3, 8, 6, 3, generator=g, dtype=torch.float64)
    target = torch.rand(3, 8, 6, 3, generator=g, dtype=torch.float64)
    w = torch.rand(3, 8, 6, generator=g, dtype=torch.float64) * 0.9 + 0.05
    mask = torch.rand(3, 8, 6, generator=g) > 0.3
    base, _ = robust_pixel_loss(pred, target, w, mask)
    scaled = w * torch.tensor([0.1, 0.7, 1.0], dtype=torch.float64).view(3, 1, 1)
    again, _ = robust_pixel_loss(pred, target, scaled, mask)
    assert float(again) == pytest.approx(float(base), rel=1e-12)


def test_robust_loss_view_without_coverage_is_ignored_and_finite():
    pred = torch.ones(2, 2, 2, 3)
    target = torch.zeros(2, 2, 2, 3)
    w = torch.zeros(2, 2, 2, requires_grad=True)
    mask = torch.zeros(2, 2, 2, dtype=torch.bool)
    mask[0] = True
    l_pix, reg = robust_pixel_loss(pred, target, w, mask)  # W = 0 everywhere: 0 / eps
    (l_pix + reg).backward()
    assert torch.isfinite(l_pix) and torch.isfinite(w.grad).all()
    l_none, _ = robust_pixel_loss(
        pred, target, torch.ones(2, 2, 2), torch.zeros(2, 2, 2, dtype=bool)
    )
    assert float(l_none) == 0.0


def test_sample_weights_equals_upsampling():
    g = torch.Generator().manual_seed(3)
    w = torch.rand(2, 4, 5, generator=g, dtype=torch.float64)
    h, wd = 12, 20
    up = upsample_weights(w, (h, wd))
    view = torch.tensor([0, 1, 1, 0, 1])
    px = torch.tensor([0, 19, 7, 11, 3])
    py = torch.tensor([0, 11, 5, 2, 9])
    xy = torch.stack([(2 * px + 1) / wd - 1, (2 * py + 1) / h - 1], -1).double()
    got = sample_weights(w, view, xy)
    assert torch.allclose(got, up[view, py, px], atol=1e-12)


def test_consistency_zero_when_pool_matches_and_hand_value():
    g = torch.Generator().manual_seed(0)
    lr = torch.rand(6, 5, 3, generator=g, dtype=torch.float64)
    hr = lr.repeat_interleave(4, 0).repeat_interleave(4, 1)
    groups = [MapGroup("roughness", (1,)), MapGroup("metallic", (2,), 0.1)]
    total, terms = pbr_consistency(hr, lr, 4, groups, lambda_ssim=10.0)
    assert float(total) == pytest.approx(0.0, abs=1e-12)
    assert consistency_psnr(hr, lr, 4, groups[0]) == 100.0
    # Constant offset 0.1 on the metallic channel of a 2x2 LR map (window 1 -> SSIM luminance).
    lr = torch.full((2, 2, 3), 0.5, dtype=torch.float64)
    hr = torch.full((4, 4, 3), 0.5, dtype=torch.float64)
    hr[..., 2] = 0.6
    total, terms = pbr_consistency(hr, lr, 2, groups, lambda_ssim=10.0)
    c1 = 0.01**2
    s = (2 * 0.6 * 0.5 + c1) / (0.36 + 0.25 + c1)
    assert float(terms["metallic"]) == pytest.approx(0.1 + 10 * (1 - s))
    assert float(total) == pytest.approx(0.1 * (0.1 + 10 * (1 - s)))


def test_consistency_with_a_kept_ssim_target_is_the_same_loss():
    """The optimiser keeps the LR map's SSIM moments across steps: same value, same gradient."""
    g = torch.Generator().manual_seed(4)
    lr = torch.rand(20, 17, 3, generator=g, dtype=torch.float64)
    groups = [MapGroup("base_color", (0, 1, 2))]
    target = ssim_target(lr)
    for _ in range(2):  # reused
        pooled = torch.rand(20, 17, 3, generator=g, dtype=torch.float64)
        a, b = pooled.clone().requires_grad_(), pooled.clone().requires_grad_()
        la = pooled_consistency(a, lr, groups, 10.0, target)[0]
        lb = pooled_consistency(b, lr, groups, 10.0)[0]
        la.backward()
        lb.backward()
        assert float(la.detach()) == pytest.approx(float(lb.detach()), abs=1e-14)
        assert torch.allclose(a.grad, b.grad, atol=1e-14)


def test_avg_pool_and_shape_errors():
    hr = torch.arange(16.0).view(4, 4, 1)
    assert avg_pool_map(hr, 2)[..., 0].tolist() == [[2.5, 4.5], [10.5, 12.5]]
    with pytest.raises(ValueError):
        avg_pool_map(torch.zeros(5, 4, 1), 2)
    with pytest.raises(ValueError):
        pbr_consistency(torch.zeros(4, 4, 1), torch.zeros(3, 2, 1), 2, [MapGroup("a", (0,))], 1)


def test_tv_zero_on_constants_and_hand_value():
    groups = [MapGroup("base_color", (0, 1, 2))]
    assert float(tv_loss(torch.full((7, 3, 4), 0.3), groups)) == 0.0
    assert float(tv_loss(torch.rand(1, 1, 3), groups)) == 0.0  # 1x1: no differences
    t = torch.zeros(2, 3, 1, dtype=torch.float64)
    t[:, 1] = 1.0  # columns 0 1 0: |dx| = 1, 1 on both rows; |dy| = 0
    assert float(tv_loss(t, [MapGroup("r", (0,))])) == pytest.approx(1.0)
    t = torch.tensor([[[0.0], [0.2]], [[0.6], [1.0]]], dtype=torch.float64)
    # dx: |0.2|, |0.4| -> 0.3 ; dy: |0.6|, |0.8| -> 0.7
    assert float(tv_loss(t, [MapGroup("r", (0,))])) == pytest.approx(1.0)


def test_losses_gradcheck_float64():
    g = torch.Generator().manual_seed(5)
    hr = (torch.rand(4, 4, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    lr = torch.rand(2, 2, 3, generator=g, dtype=torch.float64)
    groups = [MapGroup("albedo", (0, 1)), MapGroup("metallic", (2,), 0.1)]
    assert torch.autograd.gradcheck(
        lambda t: pbr_consistency(t, lr, 2, groups, 10.0)[0], (hr,), fast_mode=True
    )
    big = (torch.rand(12, 13, 2, generator=g, dtype=torch.float64)).requires_grad_()
    lr_big = torch.rand(12, 13, 2, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda t: pbr_consistency(t, lr_big, 1, [MapGroup("x", (0, 1))], 10.0)[0], (big,)
    )
    # TV away from kinks (|differences| > 0).
    tv_in = torch.linspace(0, 1, 5 * 4 * 1, dtype=torch.float64).view(5, 4, 1) ** 2
    tv_in = tv_in.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t: tv_loss(t, [MapGroup("r", (0,))]), (tv_in,), fast_mode=True
    )
    pred = torch.rand(2, 5, 4, 3, generator=g, dtype=torch.float64).requires_grad_()
    target = torch.rand(2, 5, 4, 3, generator=g, dtype=torch.float64)
    w64 = (torch.rand(2, 3, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    mask = torch.rand(2, 5, 4, generator=g) > 0.2

    def robust(p, w):
        l_pix, reg = robust_pixel_loss(p, target, upsample_weights(w, (5, 4)), mask)
        return 100 * l_pix + 0.5 * reg

    assert torch.autograd.gradcheck(robust, (pred, w64), fast_mode=True)


def test_robust_terms_rejects_bad_shapes():
    with pytest.raises(ValueError):
        robust_pixel_terms(torch.zeros(3), torch.zeros(2), torch.zeros(3, dtype=torch.long), 1)
