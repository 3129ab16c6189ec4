"""The Prior interface, tiling and the registry, checked with the bicubic prior (exact
references) and a tiny local-receptive-field network."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.errors import InvalidOptions, UnprocessableAsset
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.registry import check_name, clear_cache
from pbrsr_core.prior.tiling import (
    axis_windows,
    count_tiles,
    default_tile_size,
    run_tiled,
    tile_layout,
    tile_starts,
)


@pytest.mark.parametrize(
    "length,tile,overlap", [(10, 16, 4), (100, 32, 8), (257, 64, 16), (1024, 512, 32)]
)
def test_tiles_cover_and_windows_partition_unity(length, tile, overlap):
    size, starts = tile_layout(length, tile, overlap)
    assert size <= tile and starts == tile_starts(length, tile, overlap)
    assert starts[0] == 0 and starts[-1] + size == length
    for a, b in zip(starts, starts[1:], strict=False):
        assert b - a <= size - overlap and b > a
    for scale in (1, 3):
        total = torch.zeros(length * scale)
        for w, s in zip(
            axis_windows(length, starts, size, overlap, scale, torch.device("cpu")),
            starts,
            strict=True,
        ):
            assert w.min() >= 0
            total[s * scale : s * scale + w.numel()] += w
        assert torch.allclose(total, torch.ones_like(total), atol=1e-6)


def test_tile_arguments_are_checked():
    with pytest.raises(ValueError):
        tile_starts(10, 8, 8)
    assert count_tiles(100, 10, 32, 8) == 4
    assert tile_layout(1024, 512, 32) == (363, [0, 330, 661])  # 3 fitted tiles, not 3 x 512
    assert 64 <= default_tile_size(torch.device("cpu"), 4096.0) <= 512
    # memory does not bind at one byte a pixel: the CPU cap does (512 unless the prior says)
    assert default_tile_size(torch.device("cpu"), 1.0) == 512
    assert default_tile_size(torch.device("cpu"), 1.0, cpu_max=1024) == 1024


class LocalNet(Prior):
    """A fixed 5x5 conv (receptive radius 2) then nearest x2: tiles with a dead zone >= 2 px
    must reproduce the untiled output exactly."""

    name = "local"
    scales = (2,)
    default_overlap = 8
    pad_multiple = 4
    back_project = False  # the padding test compares with the plain convolution

    def __init__(self):
        super().__init__()
        self.weight = torch.rand(3, 3, 5, 5) / 75
        self.seen_shapes = []

    def _forward(self, x, scale):
        self.seen_shapes.append(tuple(x.shape))
        assert x.shape[2] % 4 == 0 and x.shape[3] % 4 == 0
        y = F.conv2d(x, self.weight, padding=2)
        return F.interpolate(y, scale_factor=scale, mode="nearest")


def test_tiled_equals_untiled_for_local_network():
    net = LocalNet()
    x = torch.rand(2, 3, 40, 52)
    whole = net.upscale(x, 2, tile_size=64)
    net.seen_shapes.clear()
    tiled = net.upscale(x, 2, tile_size=16, tile_overlap=8)
    assert whole.shape == (2, 3, 80, 104)
    assert float((whole - tiled).abs().max()) < 1e-6
    assert len(net.seen_shapes) == 2 * count_tiles(40, 52, 16, 8)
    assert all(s[2:] == net.seen_shapes[0][2:] for s in net.seen_shapes)


def test_padding_inside_for_any_size():
    net = LocalNet()
    x = torch.rand(1, 3, 7, 13)
    y = net.upscale(x, 2, tile_size=64)
    assert y.shape == (1, 3, 14, 26)
    assert net.seen_shapes[-1][2:] == (8, 16)
    # away from the padded border the result equals the unpadded convolution
    ref = F.interpolate(F.conv2d(x, net.weight, padding=2), scale_factor=2).clamp(0, 1)
    assert torch.allclose(y[:, :, :8, :18], ref[:, :, :8, :18], atol=1e-6)


def test_bicubic_prior_matches_torch_and_clamps():
    prior = load_prior("bicubic", "cpu")
    x = torch.rand(3, 3, 17, 23)
    for s in prior.scales:
        y = prior.upscale(x, s)
        ref = F.interpolate(x, scale_factor=s, mode="bicubic").clamp(0, 1)
        assert y.shape == (3, 3, 17 * s, 23 * s)
        assert torch.allclose(y, ref, atol=1e-6)
    # tiled bicubic is exact: the dead zone covers the 2-pixel footprint
    big = torch.rand(1, 3, 70, 90)
    tiled = prior.upscale(big, 4, tile_size=24)
    assert torch.allclose(
        tiled, F.interpolate(big, scale_factor=4, mode="bicubic").clamp(0, 1), atol=1e-5
    )


def test_output_is_clean_ordinary_tensor():
    prior = load_prior("bicubic", "cpu")
    x = torch.rand(1, 3, 8, 8)
    x[0, 0, 2, 2] = float("nan")
    x[0, 1, 3, 3] = 5.0
    y = prior.upscale(x, 2)
    assert torch.isfinite(y).all() and y.min() >= 0 and y.max() <= 1
    assert not y.is_inference()
    p = torch.rand(1, 3, 16, 16, requires_grad=True)
    (p * y).sum().backward()  # usable as a loss target
    assert torch.allclose(p.grad, y)


def test_progress_counts_tiles_and_can_cancel():
    from pbrsr_core.errors import Cancelled

    prior = load_prior("bicubic", "cpu")
    seen = []
    prior.upscale(
        torch.rand(2, 3, 40, 40),
        2,
        tile_size=24,
        tile_overlap=8,
        progress=lambda d, t: seen.append((d, t)),
    )
    assert seen == [(i, 8) for i in range(1, 9)]

    def cancel(done, total):
        raise Cancelled("stop")

    with pytest.raises(Cancelled):
        prior.upscale(torch.rand(1, 3, 40, 40), 2, tile_size=24, progress=cancel)


def test_bad_inputs_and_scales():
    prior = load_prior("bicubic", "cpu")
    with pytest.raises(ValueError):
        prior.upscale(torch.rand(3, 8, 8), 2)
    with pytest.raises(ValueError):
        prior.upscale(torch.rand(1, 4, 8, 8), 2)
    with pytest.raises(TypeError):
        prior.upscale([[0.0]], 2)
    with pytest.raises(UnprocessableAsset, match="x5"):
        prior.upscale(torch.rand(1, 3, 8, 8), 5)


def test_registry_names_and_cache():
    clear_cache()
    a = load_prior("bicubic", "cpu")
    assert load_prior("bicubic", torch.device("cpu")) is a
    with pytest.raises(InvalidOptions, match="unknown prior"):
        load_prior("esrgan-huge", "cpu")
    with pytest.raises(InvalidOptions):
        check_name("spandrel:")
    check_name("spandrel:/x/y.pth")
    check_name("diffusion:/models/sd-x4")


def test_run_tiled_single_tile_passthrough():
    x = torch.rand(1, 3, 10, 10)
    out = run_tiled(lambda t: t.repeat_interleave(2, 2).repeat_interleave(2, 3), x, 2, 32, 8)
    assert out.shape == (1, 3, 20, 20)
