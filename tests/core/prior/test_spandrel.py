"""spandrel:<path> loads a real weights file the test builds itself (a small Real-ESRGAN
Compact network, random weights) and runs it like an independent reference does."""

from __future__ import annotations

import sys

import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import save_file

from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.backproject import back_project
from pbrsr_core.prior.registry import clear_cache


def _compact_state(num_feat=8, num_conv=2, scale=2, seed=0) -> dict[str, torch.Tensor]:
    """A SRVGGNetCompact state dict: conv, PReLU, (conv, PReLU) x num_conv, conv to 3*s*s."""
    g = torch.Generator().manual_seed(seed)
    sd, i = {}, 0

    def conv(cin, cout):
        nonlocal i
        sd[f"body.{i}.weight"] = torch.randn(cout, cin, 3, 3, generator=g) * 0.2
        sd[f"body.{i}.bias"] = torch.randn(cout, generator=g) * 0.05
        i += 1

    def prelu(n):
        nonlocal i
        sd[f"body.{i}.weight"] = torch.rand(n, generator=g) * 0.3
        i += 1

    conv(3, num_feat)
    prelu(num_feat)
    for _ in range(num_conv):
        conv(num_feat, num_feat)
        prelu(num_feat)
    conv(num_feat, 3 * scale * scale)
    return sd


def _reference(sd: dict[str, torch.Tensor], x: torch.Tensor, scale: int) -> torch.Tensor:
    """Independent Compact forward: the body, pixel shuffle, plus nearest-upsampled input."""
    n = len({k.split(".")[1] for k in sd})
    y = x
    for i in range(n):
        w = sd[f"body.{i}.weight"]
        y = F.conv2d(y, w, sd[f"body.{i}.bias"], padding=1) if w.ndim == 4 else F.prelu(y, w)
    y = F.pixel_shuffle(y, scale)
    return (y + F.interpolate(x, scale_factor=scale, mode="nearest")).clamp(0, 1)


@pytest.mark.parametrize("ext", ["safetensors", "pth"])
def test_spandrel_loads_and_matches_reference(tmp_path, ext):
    sd = _compact_state()
    path = tmp_path / f"tiny.{ext}"
    if ext == "safetensors":
        save_file(sd, str(path))
    else:
        torch.save(sd, path)
    clear_cache()
    prior = load_prior(f"spandrel:{path}", "cpu")
    assert prior.scales == (2,)
    assert prior.num_parameters() == sum(v.numel() for v in sd.values())
    assert load_prior(f"spandrel:{path}", "cpu") is prior  # cached per process
    x = torch.rand(2, 3, 19, 23)
    y = prior.upscale(x, 2)
    assert y.shape == (2, 3, 38, 46)
    # the network's output, back-projected onto the input as every network prior's is
    assert torch.allclose(y, back_project(_reference(sd, x, 2), x, 2), atol=1e-5)
    # tiled run (receptive radius 4 px < the blend's dead zone): same result
    big = torch.rand(1, 3, 70, 50)
    tiled = prior.upscale(big, 2, tile_size=32, tile_overlap=16)
    assert torch.allclose(tiled, back_project(_reference(sd, big, 2), big, 2), atol=1e-5)
    clear_cache()


def test_no_torchvision_standin_leaks():
    from pbrsr_core.prior.spandrel_prior import import_spandrel

    import_spandrel()
    mod = sys.modules.get("torchvision.transforms.functional")
    # either the real torchvision or nothing at all: never the stand-in
    assert mod is None or getattr(mod, "__file__", None) is not None


def test_standin_raises_prior_unavailable_when_called():
    from pbrsr_core.prior.spandrel_prior import _standin_modules

    fn = _standin_modules()["torchvision.transforms.functional"]
    with pytest.raises(PriorUnavailable, match="needs torchvision"):
        fn.rotate(torch.zeros(1))
    assert fn.InterpolationMode.BILINEAR.value == "bilinear"


def test_bad_files_are_refused(tmp_path):
    with pytest.raises(InvalidOptions, match="does not exist"):
        load_prior(f"spandrel:{tmp_path / 'missing.pth'}", "cpu")
    junk = tmp_path / "junk.safetensors"
    save_file({"foo.weight": torch.zeros(3)}, str(junk))
    with pytest.raises(InvalidOptions, match="spandrel recognises"):
        load_prior(f"spandrel:{junk}", "cpu")
    one = tmp_path / "restore.safetensors"
    save_file(_compact_state(scale=1), str(one))
    with pytest.raises(InvalidOptions, match="super-resolution|x2 or more"):
        load_prior(f"spandrel:{one}", "cpu")
