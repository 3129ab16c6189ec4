"""Int8 SRMD networks (pbrsr_core/prior/int8.py): against float32 on procedural images, the
float model of their rounding that training goes through, the calibration as a weights file
stores it, the precision a texture prior takes on which CPU,
the shipped pbr-srmd networks in int8 against float32, and ``pbrsr priors calibrate`` on a
procedural texture folder."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior import int8, srmd
from pbrsr_core.prior.base import cpu_has_int8_units, native_int8
from pbrsr_core.prior.registry import load_prior
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.loop import TrainConfig
from pbrsr_core.prior.train.weights import (
    load_network,
    read_metadata,
    save_network,
    update_metadata,
)
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder

needs_engine = pytest.mark.skipif(int8.engine() is None, reason="torch has no x86 int8 engine")
needs_int8_units = pytest.mark.skipif(
    not native_int8(torch.device("cpu")),
    reason="this CPU sums int8 products in 16 bits (no VNNI or AMX), where the kernels may "
    "saturate: pbrsr runs no int8 network on it",
)


def _images(n: int, size: int, seed: int = 0) -> torch.Tensor:
    """Smooth colour fields with hard-edged blocks over them, in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    smooth = F.interpolate(torch.rand(n, 3, 4, 4, generator=g), size=(size, size), mode="bilinear")
    blocks = (torch.rand(n, 1, size // 4, size // 4, generator=g) > 0.5).float()
    return (0.7 * smooth + 0.3 * F.interpolate(blocks, size=(size, size))).clamp(0, 1)


def _net(feat: int = 16, convs: int = 4) -> srmd.SRMD:
    torch.manual_seed(0)
    return srmd.SRMD(feat, convs, 4).eval()


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return 10 * math.log10(1.0 / max(float((a - b).pow(2).mean()), 1e-20))


def _relative_error(y: torch.Tensor, ref: torch.Tensor) -> float:
    return float((y - ref).pow(2).mean().sqrt() / ref.std())


@needs_int8_units
def test_int8_network_follows_float32_and_needs_its_calibration():
    net = _net()
    calibration = int8.calibrate(net, _images(8, 32))
    assert len(calibration.scales) == net.convs and set(calibration.zero_points) == {0}  # ReLU
    q = int8.Int8SRMD(net, calibration)
    from torch.ao.nn.intrinsic.quantized import ConvReLU2d

    assert len(q.body) == net.convs - 1 and all(isinstance(m, ConvReLU2d) for m in q.body)
    x = _images(2, 24, seed=1)
    with torch.no_grad():
        ref, y = net(x), q(x)
    assert y.shape == ref.shape == (2, 3, 96, 96) and torch.isfinite(y).all()
    assert 0 < _relative_error(y, ref) < 0.005
    # ranges 30x too wide leave few levels, 10x too narrow clip: the calibration counts
    for factor, least in ((30.0, 0.02), (0.1, 0.3)):
        scales = tuple(factor * s for s in calibration.scales)
        bad = int8.Calibration(scales, calibration.zero_points)
        with torch.no_grad():
            assert _relative_error(int8.Int8SRMD(net, bad)(x), ref) > least


@needs_int8_units
def test_training_through_the_rounding_computes_what_int8_does_and_passes_gradients():
    net = _net()
    calibration = int8.calibrate(net, _images(8, 32))
    x = _images(2, 24, seed=1)
    fake = int8.FakeInt8(net, calibration)
    with torch.no_grad():
        ref, q = net(x), int8.Int8SRMD(net, calibration)(x)
    y = fake(x)
    assert _relative_error(y.detach(), q) < 0.1 * _relative_error(q, ref)  # the same rounding
    y.square().mean().backward()
    for conv in net.body[1:]:  # straight through the rounding, to the float weights
        assert conv.weight.grad is not None and torch.isfinite(conv.weight.grad).all()
        assert float(conv.weight.grad.abs().sum()) > 0


def test_calibration_round_trips_and_refuses_what_does_not_fit():
    c = int8.Calibration((0.01, 0.02, 0.03), (0, 0, 3), "pbrsr priors calibrate X")
    assert int8.Calibration.from_json(c.to_json(), 3) == c
    for text, convs, message in (
        ("{", 3, "not readable"),
        ('{"scales": [0.1]}', 1, "not readable"),
        (c.to_json(), 4, "3 scales for 4 convolutions"),
        ('{"scales": [0.1, -1], "zero_points": [0, 0]}', 2, "not positive"),
        ('{"scales": [0.1, NaN], "zero_points": [0, 0]}', 2, "not positive"),
        ('{"scales": [0.1, 0.1], "zero_points": [0, 300]}', 2, "outside 0-255"),
        ('{"scales": [0.1, 0.1], "zero_points": [0]}', 2, "2 scales but 1 zero points"),
    ):
        with pytest.raises(PriorUnavailable, match=message):
            int8.Calibration.from_json(text, convs)


def test_int8_units_are_vnni_or_amx():
    assert not cpu_has_int8_units({})
    assert not cpu_has_int8_units({"avx2": True, "avx512_f": True, "avx512_bf16": True})
    for flag in ("avx512_vnni", "avx_vnni", "amx_int8"):
        assert cpu_has_int8_units({flag: True})


def _set(tmp_path, calibrated: bool):
    folder = tmp_path / "set"
    folder.mkdir(parents=True)
    file = folder / "net-colour.safetensors"
    config = TrainConfig(kinds=("colour",), scale=4, stride=4, arch="srmd", widths=(16,) * 4)
    save_network(_net(), file, config, {"name": "net"})
    if calibrated:
        net = load_network(file)
        assert isinstance(net, srmd.SRMD)
        update_metadata(file, {int8.METADATA_KEY: int8.calibrate(net, _images(8, 32)).to_json()})
    return folder, file


@needs_engine
def test_a_texture_prior_takes_int8_where_asked_and_the_cpu_sums_in_32_bits(
    tmp_path, monkeypatch, set_runtime
):
    folder, file = _set(tmp_path, calibrated=True)
    before = load_network(file).state_dict()
    prior = TexturePrior(folder)
    assert prior.int8_ready() and prior.for_kind("colour").int8_ready()
    assert not prior.for_kind("data").int8_ready()  # the fallback, waifu2x-photo
    for name, tensor in load_network(file).state_dict().items():
        assert torch.equal(tensor, before[name])  # the calibration changed no weight
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx512_vnni": True})
    set_runtime(prior_precision="int8")
    assert prior.precision_in_use() == "int8" and prior.describe()["precision"] == "int8"
    for choice in ("auto", "fp32"):  # never automatic: the output would depend on the CPU
        set_runtime(prior_precision=choice)
        assert prior.precision_in_use() == "fp32"
    set_runtime(prior_precision="int8")
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"avx2": True, "avx512_f": True})
    assert prior.precision_in_use() == "fp32"  # 8-bit activations could saturate there
    monkeypatch.setattr(torch.cpu, "get_capabilities", lambda: {"amx_int8": True})
    assert prior.precision_in_use() == "int8"
    prior.device = torch.device("cuda")  # the int8 kernels are the CPU's
    assert prior.precision_in_use() == "fp32"
    plain, _ = _set(tmp_path / "plain", calibrated=False)
    assert TexturePrior(plain).precision_in_use() == "fp32"


def test_an_unreadable_calibration_names_its_file(tmp_path):
    folder, file = _set(tmp_path, calibrated=False)
    file.chmod(0o640)
    update_metadata(file, {int8.METADATA_KEY: '{"scales": [1.0], "zero_points": [0]}'})
    assert file.stat().st_mode & 0o777 == 0o640  # rewritten with its permissions
    with pytest.raises(PriorUnavailable, match="net-colour.safetensors.*1 scales for 4"):
        TexturePrior(folder)


@pytest.mark.parametrize("kind", ["colour", "normal"])
def test_shipped_srmd_networks_in_int8_stay_close_to_float32(kind, set_runtime):
    prior = load_prior("pbr-srmd", "cpu").for_kind(kind)
    assert prior.int8_ready()
    x = _images(1, 48, seed=3)
    set_runtime(prior_precision="fp32")
    ref = prior.upscale(x, 4)
    set_runtime(prior_precision="int8")
    y = prior.upscale(x, 4)
    if not native_int8(torch.device("cpu")):  # no VNNI or AMX: int8 asked for, float32 run
        assert prior.precision_in_use() == "fp32" and torch.equal(y, ref)
        return
    assert prior.precision_in_use() == "int8"
    assert torch.isfinite(y).all() and 40.0 < _psnr(y, ref) < 90.0  # int8 ran, and stayed close


@needs_engine
def test_cli_calibrates_a_trained_srmd_set(tmp_path, capfd):
    textures = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "train", "-o", str(out), "--textures", str(textures), "--kinds", "colour"]
    args += ["--arch", "srmd", "--widths", "8,8,8", "--stride", "4", "--scale", "4", "-q"]
    code, err = run_cli([*args, "--steps", "3", "--batch", "2", "--patch", "48"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    trained = int8.Calibration.from_json(read_metadata(file)[int8.METADATA_KEY], 3)
    assert "priors train" in trained.source  # a trained SRMD set is calibrated at the end
    cal = ["priors", "calibrate", str(out), "--textures", str(textures)]
    code, err = run_cli([*cal, "--crops", "12", "--patch", "64"], capfd)
    assert code == 0, err
    stored = int8.Calibration.from_json(read_metadata(file)[int8.METADATA_KEY], 3)
    assert "priors calibrate" in stored.source
    assert TexturePrior(out).int8_ready()
    code, err = run_cli([*cal, "--crops", "0"], capfd)
    assert code == InvalidOptions.exit_code and "--crops must be positive" in err
    upconv = tmp_path / "upconv"
    args = ["priors", "train", "-o", str(upconv), "--textures", str(textures), "--kinds", "colour"]
    code, err = run_cli([*args, "--widths", "4,4,4,4,4,4", "--steps", "1", "-q"], capfd)
    assert code == 0, err
    code, err = run_cli(["priors", "calibrate", str(upconv), "--textures", str(textures)], capfd)
    assert code == InvalidOptions.exit_code and "holds no SRMD network" in err
    # fine-tuned through the int8 rounding: from the SRMD set, not from the UpConv7 one
    tune = ["priors", "finetune", "--textures", str(textures), "--kinds", "colour", "--int8"]
    tune += ["--stride", "4", "--scale", "4", "--steps", "2", "--batch", "2", "--patch", "48"]
    code, err = run_cli([*tune, "--from", f"texture:{out}", "-o", str(tmp_path / "q"), "-q"], capfd)
    assert code == 0, err
    (ckpt,) = (tmp_path / "q").glob("*/checkpoint.pt")
    assert torch.load(ckpt, weights_only=False)["int8"] is not None
    code, err = run_cli([*tune, "--from", f"texture:{upconv}", "-o", str(tmp_path / "u")], capfd)
    assert code == InvalidOptions.exit_code and "--int8 trains an SRMD network" in err
