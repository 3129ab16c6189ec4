"""Later-pass networks (``pbrsr priors train --first``): a residual UpConv7 starts as bicubic,
a network trained behind a frozen first pass learns (the first pass stays as it was, a resumed
run is exact), its output folder is a texture set that runs first then later passes, and a set
whose later network was trained behind another first network is refused."""

from __future__ import annotations

import json

import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.loop import TrainConfig, train
from pbrsr_core.prior.train.weights import file_sha256, load_network, new_network, save_network
from pbrsr_core.prior.waifu2x import UpConv7
from tests.clirun import run_cli
from tests.core.prior.test_train import TINY, assert_resume_is_exact, make_texture_folder


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_texture_folder(tmp_path_factory.mktemp("textures"), n=10, size=128)


@pytest.fixture(scope="module")
def materials(folder):
    from pbrsr_core.prior.train.data import load_materials, read_manifest, split_materials

    manifest = read_manifest(folder)
    train_names, held = split_materials(manifest)
    return load_materials(folder, train_names, manifest), load_materials(folder, held, manifest)


def _first(path, kind="colour", seed=0):
    torch.manual_seed(seed)
    net = UpConv7(TINY)
    save_network(net, path, TrainConfig(kinds=(kind,), widths=TINY, init="random"), {})
    return net.eval()


def _later_config(first_file, **changes) -> TrainConfig:
    """A tiny residual colour network behind ``first_file``, at x4 on 48² crops."""
    base = dict(kinds=("colour",), scale=4, batch_size=4, patch=48, val_patch=64, widths=TINY)
    return TrainConfig(init="random", residual=True, first=str(first_file), **base, **changes)


def test_residual_network_starts_as_bicubic_and_round_trips(tmp_path):
    x = torch.rand(2, 3, 13, 17, dtype=torch.float64)
    net = new_network("upconv7", TINY, 2, residual=True).double()
    expect = F.interpolate(x, scale_factor=2, mode="bicubic", align_corners=False)
    assert torch.equal(net(x), expect)
    with torch.no_grad():  # a trained residual network: bicubic plus what it learned
        for p in net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    plain = UpConv7(TINY).double()
    plain.load_state_dict(net.state_dict())
    assert torch.allclose(net(x), plain(x) + expect, atol=1e-12)
    cfg = TrainConfig(widths=TINY, residual=True, init="random")
    save_network(net.float(), tmp_path / "r.safetensors", cfg, {})
    back = load_network(tmp_path / "r.safetensors")
    assert back.residual and torch.equal(back(x.float()), net.eval()(x.float()))
    with pytest.raises(InvalidOptions, match="residual"):
        TrainConfig(arch="compact", widths=(8, 8), residual=True).check()


def test_later_pass_trains_behind_a_frozen_first_pass_and_resumes_exactly(
    materials, tmp_path, one_thread
):
    train_m, val_m = materials
    first_file = tmp_path / "first.safetensors"
    first = _first(first_file)
    before = first_file.read_bytes()
    cfg = _later_config(first_file, steps=40, lr=2e-3, val_every=20, ckpt_every=20)
    best, hist = train(cfg, train_m, val_m, tmp_path / "a", name="later")
    assert hist.loss[-1] < hist.loss[0], hist.loss
    assert first_file.read_bytes() == before  # the first pass is frozen
    copy = tmp_path / "a" / "later-first.safetensors"
    assert copy.read_bytes() == before
    later = load_network(best)
    assert later.residual and later.stride == 2

    prior = TexturePrior(tmp_path / "a")
    assert set(prior.later) == {"colour"} and prior.scales == (2, 4, 8)
    assert prior.num_parameters() == sum(p.numel() for n in (first, later) for p in n.parameters())
    x = torch.rand(1, 3, 10, 12)
    with torch.no_grad():
        one = first(x).clamp(0, 1)
        two = later(one).clamp(0, 1)
        assert torch.equal(prior._forward(x, 2), one)
        assert torch.equal(prior._forward(x, 4), two)
        assert torch.equal(prior._forward(x, 8), later(two).clamp(0, 1))
    up = prior.upscale(x, 4)
    assert up.shape == (1, 3, 40, 48) and torch.isfinite(up).all()

    assert_resume_is_exact(cfg, materials, tmp_path / "a", tmp_path / "b", "later", hist, 20)


def test_distilled_later_pass_learns_the_first_networks_second_pass(
    materials, tmp_path, one_thread
):
    """--distill: the target is the first network run again on its own output, so the later
    network moves towards that two-pass output, whatever the HR crop holds."""
    train_m, val_m = materials
    first_file = tmp_path / "first.safetensors"
    first = _first(first_file)
    cfg = _later_config(first_file, steps=60, lr=3e-3, val_every=60, ckpt_every=60)
    nets, hists = {}, {}
    for distill in (True, False):
        out = tmp_path / str(distill)
        config = TrainConfig(**{**cfg.__dict__, "distill": distill})
        _, hists[distill] = train(config, train_m, val_m, out, name="n")
        nets[distill] = new_network("upconv7", TINY, 2, residual=True)
        nets[distill].load_state_dict(torch.load(out / "checkpoint.pt", weights_only=False)["net"])
    start = new_network("upconv7", TINY, 2, residual=True)  # bicubic exactly
    x = torch.stack([torch.from_numpy(m.maps["basecolor"][:32, :32]) for m in val_m[:4]])
    x = x.permute(0, 3, 1, 2).float() / 255
    with torch.no_grad():
        mid = first(x).clamp(0, 1)
        target = first(mid).clamp(0, 1)
        gap = {k: float((n.eval()(mid) - target).abs().mean()) for k, n in nets.items()}
        before = float((start(mid) - target).abs().mean())
    assert gap[True] < 0.7 * before and gap[True] < 0.7 * gap[False], (before, gap)
    # validated as what it learns: agreement with the teacher's second pass, against a bicubic
    # second pass (which the HR-trained run's validation does not measure)
    h = hists[True]
    assert h.val_psnr["colour"][-1] > h.val_bicubic["colour"] + 1.0, h
    assert h.val_bicubic["colour"] != hists[False].val_bicubic["colour"]
    with pytest.raises(InvalidOptions, match="distilling needs a network to learn from"):
        TrainConfig(widths=TINY, distill=True, init="random").check()


def test_later_pass_start_weights_resolve_to_a_sets_later_network(tmp_path):
    from pbrsr_core.prior.train.weights import resolve_start

    first_file = tmp_path / "first.safetensors"
    _first(first_file)
    cfg = TrainConfig(kinds=("colour",), scale=4, widths=TINY, init="random", first=str(first_file))
    meta = {"first_sha256": file_sha256(first_file)}
    save_network(new_network("upconv7", TINY, 2), tmp_path / "later.safetensors", cfg, meta)
    src = f"texture:{tmp_path}"
    assert resolve_start(src, "colour", 2, later=True).endswith("later.safetensors")
    assert resolve_start(src, "colour", 2).endswith("first.safetensors")


def test_sets_with_unmatched_later_networks_are_refused(tmp_path):
    first_file = tmp_path / "set" / "first.safetensors"
    first_file.parent.mkdir()
    _first(first_file)
    cfg = TrainConfig(kinds=("colour",), scale=4, widths=TINY, init="random", first=str(first_file))
    later = new_network("upconv7", TINY, 2, residual=True)
    save_network(
        later,
        tmp_path / "set" / "later.safetensors",
        cfg,
        {"first_sha256": file_sha256(first_file)},
    )
    assert set(TexturePrior(tmp_path / "set").later) == {"colour"}
    # the later network alone
    with pytest.raises(PriorUnavailable, match="no first-pass network for colour"):
        TexturePrior(tmp_path / "set" / "later.safetensors")
    # beside another first network than the one it was trained behind
    _first(first_file, seed=1)
    with pytest.raises(PriorUnavailable, match="another first-pass network"):
        TexturePrior(tmp_path / "set")
    with pytest.raises(InvalidOptions, match="scale 4 with stride 2"):
        TrainConfig(widths=TINY, scale=2, first=str(first_file)).check()
    with pytest.raises(InvalidOptions, match="first-pass network"):
        TrainConfig(widths=TINY, scale=4, first=str(tmp_path / "none.safetensors")).check()


def test_cli_trains_a_later_pass_behind_a_set(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=256)
    base = tmp_path / "base"
    (base / "b-colour").mkdir(parents=True)
    first = _first(base / "b-colour" / "b-colour.safetensors")
    out = tmp_path / "out"
    args = ["priors", "train", "-o", str(out), "--textures", str(folder), "--kinds", "colour"]
    args += ["--widths", "4,4", "--patch", "48", "--batch", "2", "--steps", "4", "-q"]
    code, err = run_cli([*args, "--first", f"texture:{base}", "--residual", "--scale", "4"], capfd)
    assert code == 0, err
    names = sorted(p.name for p in out.glob("*/*.safetensors"))
    assert names == ["pbr-upconv7-colour-first.safetensors", "pbr-upconv7-colour.safetensors"]
    prior = TexturePrior(out)
    assert torch.equal(prior.nets["colour"][2].mods[0].weight, first.mods[0].weight)
    assert prior.later["colour"].widths == (4, 4) and prior.later["colour"].residual
    report = json.loads((out / "report.json").read_text())
    assert "out" in report["colour"]["4"] and "out" in report["colour"]["8"]
    card = (out / "MODEL_CARD.md").read_text()
    row = next(line for line in card.splitlines() if "| pbr-upconv7-colour.safetensors" in line)
    assert "later, behind b-colour.safetensors (residual" in row and "| 4,4 |" in row
    assert "--first" in card and "makes every x2 pass after the first" in card
    code, err = run_cli([*args, "--first", f"texture:{base}", "-o", str(tmp_path / "o2")], capfd)
    assert code == InvalidOptions.exit_code and "scale 4 with stride 2" in err, err
    assert not (tmp_path / "o2").exists()
