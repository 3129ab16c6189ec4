"""``pbrsr priors finetune --from spandrel:<file>``: any SR model spandrel recognises trains on
texture crops as the project's own networks do, resumes exactly, and comes out as a texture
prior (and a file spandrel itself loads again). The models are small ones the tests build
(a Real-ESRGAN Compact network and a SwinIR), random weights."""

from __future__ import annotations

import pytest
import torch
from safetensors.torch import save_file

from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior.registry import clear_cache, load_prior
from pbrsr_core.prior.spandrel_prior import SpandrelNet, import_spandrel
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.loop import TrainConfig, train
from pbrsr_core.prior.train.weights import load_network, read_metadata, save_network
from tests.clirun import run_cli
from tests.core.prior.test_spandrel import _compact_state
from tests.core.prior.test_train import (
    assert_resume_is_exact,
    folder,  # noqa: F401  (fixture)
    make_texture_folder,
    materials,  # noqa: F401  (fixture)
)


def _compact_file(tmp_path, scale: int = 2):
    path = tmp_path / f"compact-x{scale}.safetensors"
    save_file(_compact_state(num_feat=8, num_conv=2, scale=scale), str(path))
    return path


def _swinir_file(tmp_path):
    import_spandrel()
    from spandrel.architectures.SwinIR import SwinIR

    torch.manual_seed(0)
    net = SwinIR(img_size=16, embed_dim=12, depths=[1], num_heads=[2], window_size=4,
                 mlp_ratio=2.0, upscale=2, upsampler="pixelshuffledirect")  # fmt: skip
    path = tmp_path / "swinir-x2.safetensors"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path))
    return path


def _config(path, **kw) -> TrainConfig:
    base = dict(kinds=("colour",), arch="spandrel", widths=(), init=f"spandrel:{path}", scale=4,
                stride=2, steps=40, batch_size=4, patch=48, val_patch=64, lr=2e-3, val_every=20,
                ckpt_every=20)  # fmt: skip
    return TrainConfig(**{**base, **kw})


def test_a_spandrel_model_learns_resumes_exactly_and_runs_as_a_texture_prior(
    materials,  # noqa: F811
    tmp_path,
    one_thread,
):
    start = _compact_file(tmp_path)
    cfg = _config(start)
    best, hist = train(cfg, *materials, tmp_path / "a", name="ft", resume=False)
    assert hist.loss[-1] < 0.7 * hist.loss[0], hist.loss
    meta = read_metadata(best)
    assert (meta["arch"], meta["architecture"], meta["stride"]) == ("spandrel", "Compact", "2")
    net = load_network(best)
    assert isinstance(net, SpandrelNet) and net.stride == 2
    before = SpandrelNet.from_file(start).weights()
    assert any(not torch.equal(v, before[k]) for k, v in net.weights().items())  # it trained

    assert_resume_is_exact(cfg, materials, tmp_path / "a", tmp_path / "b", "ft", hist, 20)

    # the run's folder is a texture prior (x4: two passes of the x2 network) ...
    prior = TexturePrior(tmp_path / "a")
    x = torch.rand(1, 3, 20, 24)
    up = prior.for_kind("colour").upscale(x, 4)
    assert up.shape == (1, 3, 80, 96) and torch.isfinite(up).all()
    # ... and its weights file a model spandrel loads as it is: the same x2 upscale
    clear_cache()
    again = load_prior(f"spandrel:{best}", "cpu").upscale(x, 2)
    assert torch.allclose(prior.for_kind("colour").upscale(x, 2), again, atol=1e-5)
    clear_cache()


@pytest.mark.filterwarnings("ignore:torch.meshgrid")
def test_a_transformer_pads_to_its_window_trains_and_round_trips(tmp_path):
    net = SpandrelNet.from_file(_swinir_file(tmp_path))
    assert (net.architecture, net.stride) == ("SwinIR", 2)
    x = torch.rand(2, 3, 17, 23, requires_grad=True)
    y = net.train()(x)
    assert y.shape == (2, 3, 34, 46)
    y.mean().backward()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)
    path = tmp_path / "saved.safetensors"
    save_network(net, path, _config(path), {})
    back = load_network(path)
    assert isinstance(back, SpandrelNet) and back.architecture == "SwinIR"
    with torch.no_grad():
        assert torch.allclose(back(x), net.eval()(x), atol=1e-6)


def test_a_spandrel_start_trains_as_its_file_has_it(tmp_path):
    x2 = _compact_file(tmp_path)
    with pytest.raises(InvalidOptions, match=r"x2 Compact model: train it with --stride 2"):
        _config(x2, stride=4).check()
    with pytest.raises(InvalidOptions, match="no --widths"):
        _config(x2, widths=(8, 8)).check()
    with pytest.raises(InvalidOptions, match="--from spandrel:<file>"):
        TrainConfig(arch="spandrel", widths=()).check()
    junk = tmp_path / "junk.safetensors"
    save_file({"w": torch.zeros(3)}, str(junk))
    with pytest.raises(InvalidOptions, match="not a model architecture spandrel recognises"):
        _config(junk).check()
    # a file whose tensors are not the architecture its metadata names is refused on load
    path = tmp_path / "net.safetensors"
    save_network(SpandrelNet.from_file(x2), path, _config(x2), {"architecture": "SwinIR"})
    with pytest.raises(PriorUnavailable, match="the file says x2 SwinIR"):
        load_network(path)


def test_cli_finetunes_a_spandrel_model_and_names_it_in_the_card(tmp_path, capfd):
    textures = make_texture_folder(tmp_path / "tex", n=10, size=128)
    out = tmp_path / "out"
    start = _compact_file(tmp_path, scale=4)
    args = ["priors", "finetune", "--from", f"spandrel:{start}", "-o", str(out), "--textures",
            str(textures), "--kinds", "colour", "--scale", "4", "--patch", "48", "--batch", "2",
            "--steps", "2", "-q"]  # fmt: skip
    code, err = run_cli(args, capfd)
    assert code == InvalidOptions.exit_code and "--stride 4" in err  # an x4 model
    if not torch.cuda.is_available():
        code, err = run_cli([*args, "--stride", "4", "--device", "cuda"], capfd)
        assert code == InvalidOptions.exit_code and "CUDA is not available" in err
    code, err = run_cli([*args, "--stride", "4"], capfd)
    assert code == 0, err
    (file,) = out.glob("*/*.safetensors")
    assert read_metadata(file)["architecture"] == "Compact"
    assert "Compact trained on PBR maps" in (out / "MODEL_CARD.md").read_text()
    up = TexturePrior(out).for_kind("colour").upscale(torch.rand(1, 3, 12, 12), 4)
    assert up.shape == (1, 3, 48, 48) and torch.isfinite(up).all()
