"""The SPAN-shaped network (pbrsr_core/prior/span.py): bicubic at its start weights, its
attention block as the paper writes it, trained and fine-tuned through the CLI, stored and run
as a texture prior."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.errors import InvalidOptions
from pbrsr_core.prior.bicubic import bicubic_upscale
from pbrsr_core.prior.span import Block, Span
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.weights import load_network, new_network, read_metadata
from tests.clirun import run_cli
from tests.core.prior.test_train import make_texture_folder


@pytest.mark.parametrize("stride", [2, 4])
def test_start_weights_are_bicubic_exactly(stride):
    torch.manual_seed(0)
    net = Span(8, 2, stride).eval()
    x = torch.rand(2, 3, 13, 10)
    with torch.no_grad():
        y = net(x)
    assert y.shape == (2, 3, 13 * stride, 10 * stride)
    torch.testing.assert_close(y, bicubic_upscale(x, stride), rtol=0, atol=0)


def test_parameters_follow_the_shape():
    def conv(cin: int, cout: int, k: int = 3) -> int:
        return cin * cout * k * k + cout

    f, b, s = 48, 6, 4
    want = conv(3, f) + b * 3 * conv(f, f) + conv(4 * f, f, 1) + conv(f, f) + conv(f, 3 * s * s)
    assert sum(p.numel() for p in Span(f, b, s).parameters()) == want  # 426,288: SPAN's size
    with pytest.raises(ValueError, match="stride"):
        Span(8, 2, 3)
    with pytest.raises(ValueError, match="positive"):
        Span(8, 0, 4)


def test_block_is_the_parameter_free_attention_of_the_paper():
    torch.manual_seed(1)
    block = Block(4).eval()
    x = torch.randn(1, 4, 9, 7)
    c1 = F.conv2d(x, block.c1.weight, block.c1.bias, padding=1)
    c2 = F.conv2d(F.silu(c1), block.c2.weight, block.c2.bias, padding=1)
    y = F.conv2d(F.leaky_relu(c2, 0.1), block.c3.weight, block.c3.bias, padding=1)
    with torch.no_grad():
        out, inner = block(x)
    torch.testing.assert_close(inner, c1)
    torch.testing.assert_close(out, (y + x) * (torch.sigmoid(y) - 0.5))
    # the attention is odd in y about 0: sigmoid(y) - 1/2 has the sign of y, |.| < 1/2
    att = torch.sigmoid(y) - 0.5
    assert torch.equal(torch.sign(att), torch.sign(y)) and att.abs().max() < 0.5


def test_a_trained_network_is_not_bicubic_and_stays_translation_equivariant_inside():
    """After a step of training the network moves off bicubic; its convolutions stay local,
    so shifting the input by whole pixels shifts the output away from the borders."""
    torch.manual_seed(2)
    net = Span(8, 2, 2)
    opt = torch.optim.Adam(net.parameters(), 1e-2)
    x, hr = torch.rand(2, 3, 16, 16), torch.rand(2, 3, 32, 32)
    for _ in range(3):
        opt.zero_grad()
        (net(x) - hr).abs().mean().backward()
        opt.step()
    net.eval()
    big = torch.rand(1, 3, 48, 48)
    with torch.no_grad():
        a, b = net(big), net(big[..., 3:, 5:])
        assert (a - bicubic_upscale(big, 2)).abs().max() > 1e-3
    # the receptive field: 1 + 3 * blocks + 2 convolutions of radius 1 -> 9 LR px; 12 to spare
    torch.testing.assert_close(b[..., 24:-24, 24:-24], a[..., 30:-24, 34:-24], rtol=1e-4,
                               atol=1e-5)  # fmt: skip


def test_cli_trains_a_span_set_that_runs_x4_in_one_pass(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    args = ["priors", "train", "-o", str(out), "--textures", str(folder), "--kinds", "colour"]
    args += ["--arch", "span", "--widths", "8,8", "--stride", "4", "--scale", "4"]
    code, err = run_cli([*args, "--steps", "3", "--batch", "2", "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    meta = read_metadata(file)
    assert (meta["arch"], meta["feat"], meta["blocks"], meta["stride"]) == ("span", "8", "2", "4")
    net = load_network(file)
    assert isinstance(net, Span) and net.widths == (8, 8)
    prior = TexturePrior(out)
    assert prior.for_kind("colour").scales == (4,)
    up = prior.upscale(torch.rand(1, 3, 12, 12), 4)
    assert up.shape == (1, 3, 48, 48) and torch.isfinite(up).all()
    assert prior.num_parameters() == sum(p.numel() for p in net.parameters())
    card = (out / "MODEL_CARD.md").read_text()
    assert "(SPAN trained on PBR maps)" in card and "random start weights" in card
    assert "UpConv7 photo model" not in card

    # fine-tuned at stride 2 from it: the body carries over, the head is new
    out2 = tmp_path / "out2"
    tune = ["priors", "finetune", "--from", str(file), "-o", str(out2), "--textures", str(folder)]
    tune += ["--kinds", "colour", "--stride", "2", "--scale", "2", "--steps", "1", "--batch", "2"]
    code, err = run_cli([*tune, "--patch", "48", "-q"], capfd)
    assert code == 0, err
    (file2,) = out2.glob("*/*.safetensors")
    net2 = load_network(file2)
    assert net2.stride == 2 and net2.head.weight.shape[0] == 12 and net2.widths == (8, 8)

    code, err = run_cli([*args[:8], "--arch", "span", "--widths", "8,4", "-q"], capfd)
    assert code == InvalidOptions.exit_code and "equal widths" in err
    code, err = run_cli([*args[:8], "--arch", "span", "--residual", "-q"], capfd)
    assert code == InvalidOptions.exit_code and "residual is an upconv7 option" in err


def test_new_network_builds_span_from_widths():
    net = new_network("span", (16, 16, 16), 4)
    assert isinstance(net, Span) and (net.feat, net.blocks, net.stride) == (16, 3, 4)
