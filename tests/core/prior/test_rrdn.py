"""The TF.js -> torch conversion of @upscalerjs/esrgan-thick, proven on the package's own
sample input and upscaled outputs (assets/fixture.png, assets/samples/{s}x/result.png)."""

from __future__ import annotations

import numpy as np
import OpenImageIO as oiio
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core import runtime
from pbrsr_core.errors import InvalidOptions, PriorUnavailable, UnprocessableAsset
from pbrsr_core.prior import rrdn, tfjs
from pbrsr_core.prior.base import cpu_has_bf16_units, native_bf16
from pbrsr_core.prior.registry import clear_cache, load_prior

PKG = rrdn.package_dir()
pytestmark = pytest.mark.skipif(
    not (PKG / "package.json").is_file(), reason="npm package not installed (run scripts/setup)"
)


def _read_rgb(path) -> torch.Tensor:
    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    assert px is not None and px.ndim == 3, f"cannot read {path}"
    return torch.from_numpy(np.ascontiguousarray(px[..., :3])).permute(2, 0, 1)[None]


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a - b) ** 2).mean())
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """One intra-op thread: on this shared 2-core machine, 2 OpenMP threads competing with
    other processes run ~8x slower than one (measured: 15 s vs 2 s for a 64x64 x2 pass)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    d = tmp_path_factory.mktemp("pbrsr-cache")
    mp.setattr(runtime, "_current", runtime.current())
    runtime.configure(cache_dir=d)
    clear_cache()
    written = rrdn.install()
    assert len(written) == len(rrdn.SCALES)
    yield d
    clear_cache()
    mp.undo()


def test_depth_to_space_matches_tf_definition():
    s, c, h, w = 3, 2, 2, 4
    x = torch.randn(1, s * s * c, h, w)
    y = tfjs.depth_to_space(x, s)
    assert y.shape == (1, c, h * s, w * s)
    for ch in range(c):
        for i in range(s):
            for j in range(s):
                # output[c, h*s+i, w*s+j] = input[(i*s+j)*C + c, h, w]
                assert torch.equal(y[0, ch, i::s, j::s], x[0, (i * s + j) * c + ch])
    # torch's pixel_shuffle uses another channel order: not the same operation
    assert not torch.equal(y, F.pixel_shuffle(x, s))


def test_graph_is_what_the_converter_supports():
    import json

    model = json.loads((PKG / "models" / "x4" / "model.json").read_text())
    ops, kernels = tfjs.parse_graph(model)
    kinds = {op["op"] for op in ops}
    assert kinds == {"input", "conv", "relu", "concat", "add", "mul", "d2s"}
    assert len(kernels) == 154 and all(k == (3, 3) for k in kernels.values())
    assert [op["scale"] for op in ops if op["op"] == "d2s"] == [4]


# The network's output at a cut edge differs from the uncut image's by < 1e-6 beyond 14 LR
# px (measured), so a corner crop of the fixture reproduces the shipped output exactly except
# within MARGIN of the two cut sides; the image's own borders are kept. A quarter of the work.
CROP, MARGIN = 64, 16


def _fixture_crop(scale: int) -> tuple[torch.Tensor, torch.Tensor]:
    x = _read_rgb(PKG / "assets" / "fixture.png")  # (1, 3, 128, 128)
    ref = _read_rgb(PKG / "assets" / "samples" / f"{scale}x" / "result.png")
    assert ref.shape[-2:] == (128 * scale, 128 * scale)
    keep = (CROP - MARGIN) * scale
    return x[:, :, :CROP, :CROP], ref[:, :, :keep, :keep]


@pytest.mark.parametrize("scale", [2, 3, 4, 8])
def test_converted_model_reproduces_package_samples(cache, scale):
    x, ref = _fixture_crop(scale)
    prior = load_prior("rrdn-thick", "cpu")
    with torch.inference_mode():  # the network itself: upscale() also back-projects
        y = prior._run_padded(x, scale)
    assert y.shape[-2:] == (CROP * scale, CROP * scale)
    k = ref.shape[-1]
    psnr = _psnr(y[:, :, :k, :k], ref)
    assert psnr >= 40.0, f"x{scale}: {psnr:.2f} dB against the package's own output"
    # and it is not just bicubic: the network output is far closer than interpolation
    bic = F.interpolate(x, scale_factor=scale, mode="bicubic").clamp(0, 1)[:, :, :k, :k]
    assert psnr > _psnr(bic, ref) + 10.0


def test_torch_pixel_shuffle_order_would_fail(cache, monkeypatch):
    """The fixture test can fail: with torch's channel order the output is garbage."""
    x, ref = _fixture_crop(2)
    net = tfjs.load_converted(rrdn.weights_file(2))
    monkeypatch.setattr(tfjs, "depth_to_space", F.pixel_shuffle)
    with torch.inference_mode():
        wrong = net(x).clamp(0, 1)[:, :, : ref.shape[-2], : ref.shape[-1]]
    assert _psnr(wrong, ref) < 30.0


def test_install_is_idempotent_and_loading_reads_only_safetensors(cache, set_runtime):
    assert rrdn.is_installed()
    assert rrdn.install() == []  # second run: nothing to do
    # loading must not touch the npm package
    set_runtime(npm_dir=cache / "no-such-dir")
    clear_cache()
    prior = load_prior("rrdn-thick", "cpu")
    assert prior.num_parameters() > 1_000_000
    with pytest.raises(UnprocessableAsset):
        prior.upscale(torch.rand(1, 3, 8, 8), 5)
    clear_cache()


def test_not_installed_names_the_command(tmp_path, set_runtime):
    set_runtime(cache_dir=tmp_path / "empty")
    clear_cache()
    with pytest.raises(PriorUnavailable, match="pbrsr priors install rrdn-thick"):
        load_prior("rrdn-thick", "cpu")
    set_runtime(npm_dir=tmp_path / "nothing")
    with pytest.raises(PriorUnavailable, match="scripts/setup"):
        rrdn.install()
    clear_cache()


def test_tiled_matches_untiled_within_1e3(cache):
    g = torch.Generator().manual_seed(1)
    # a smooth random image with some edges, 56x56, 4 tiles of 40 sharing 24 px at x2
    base = torch.rand(1, 3, 9, 9, generator=g)
    x = F.interpolate(base, size=(56, 56), mode="bicubic").clamp(0, 1)
    x[:, :, 25:31, :] = 0.9
    prior = load_prior("rrdn-thick", "cpu")
    prior.precision = "fp32"  # the tiling arithmetic itself, without bfloat16 rounding
    try:
        calls = []
        whole = prior.upscale(x, 2, tile_size=128)
        tiled = prior.upscale(
            x, 2, tile_size=40, tile_overlap=24, progress=lambda d, t: calls.append((d, t))
        )
    finally:
        prior.precision = None
    assert calls == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert float((whole - tiled).abs().max()) < 1e-3


def test_bfloat16_stays_close_to_float32(cache, set_runtime):
    x, _ = _fixture_crop(4)
    prior = load_prior("rrdn-thick", "cpu")
    set_runtime(prior_precision="fp32")
    assert prior.precision_in_use() != "bf16" and prior.describe()["precision"] == "fp32"
    full = prior.upscale(x, 4, tile_size=512)
    set_runtime(prior_precision="bf16")
    assert prior.precision_in_use() == "bf16"
    half = prior.upscale(x, 4, tile_size=512)
    assert half.dtype == torch.float32 and torch.isfinite(half).all()
    assert 45.0 <= _psnr(half, full) < 100.0  # bfloat16 really ran, and stayed close
    set_runtime(prior_precision="auto")
    assert (prior.precision_in_use() == "bf16") == native_bf16(torch.device("cpu"))
    set_runtime(prior_precision="bf16")
    assert load_prior("bicubic", "cpu").precision_in_use() == "fp32"  # interpolation: never
    prior.precision = "half"
    with pytest.raises(InvalidOptions, match="'half' is not one of auto, fp32, bf16"):
        prior.upscale(x, 4)
    prior.precision = None


def test_auto_precision_follows_the_cpus_bf16_units_not_onednns_emulation(
    cache, monkeypatch, set_runtime
):
    assert not cpu_has_bf16_units({})
    assert not cpu_has_bf16_units({"avx512_f": True, "avx512_bw": True, "avx512_vnni": True})
    assert cpu_has_bf16_units({"avx512_f": True, "avx512_bf16": True})
    assert cpu_has_bf16_units({"amx_tile": True, "amx_bf16": True})
    prior = load_prior("rrdn-thick", "cpu")
    set_runtime(prior_precision="auto")
    # an AVX512 CPU without BF16 (oneDNN emulates bfloat16 there, 3.7x slower): float32
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx512_f": True})
    assert prior.precision_in_use() != "bf16" and prior.describe()["precision"] == "fp32"
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx512_bf16": True})
    assert prior.precision_in_use() == "bf16" and prior.describe()["precision"] == "bf16"
