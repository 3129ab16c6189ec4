"""Training texture priors (pbrsr_core/prior/train): the split, the symmetries of normal maps,
a tiny network trained on procedural textures (loss falls, a resumed run is exact), the
weights file, the texture prior that loads it, and `pbrsr priors train` end to end."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
import torch

import pbrsr_core.prior.train.data as data_mod
from pbrsr_core.errors import InvalidOptions, PriorUnavailable
from pbrsr_core.prior.backproject import back_project
from pbrsr_core.prior.int8 import Calibration, FakeInt8
from pbrsr_core.prior.registry import check_name, load_prior
from pbrsr_core.prior.srmd import SRMD
from pbrsr_core.prior.symmetry import dihedral
from pbrsr_core.prior.texture import TexturePrior
from pbrsr_core.prior.train.data import (
    CropSampler,
    degrade_pair,
    load_materials,
    read_manifest,
    split_materials,
    validation_crops,
)
from pbrsr_core.prior.train.graphics import (
    data_graphics_crop,
    graphics_crop,
    height_normals,
    normal_graphics_crop,
)
from pbrsr_core.prior.train.loop import (
    TrainConfig,
    Validator,
    build_network,
    interior_l1,
    train,
    upscale_net,
)
from pbrsr_core.prior.train.report import model_card
from pbrsr_core.prior.train.weights import load_network, save_network
from pbrsr_core.prior.waifu2x import UpConv7
from tests.clirun import run_cli

TINY = (4, 8)


def _height(size: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    h = np.zeros((size, size))
    for _ in range(6):
        fx, fy, ph = rng.uniform(1, 9), rng.uniform(1, 9), rng.uniform(0, 6.3)
        h += np.sin(2 * np.pi * (fx * x + fy * y) + ph) / (fx + fy)
    return (h - h.min()) / (np.ptp(h) + 1e-9)


def normals_from_height(h: np.ndarray, strength: float = 4.0) -> np.ndarray:
    """Encoded OpenGL normals (+X right, +Y up) of a square height field over the unit
    square, ``strength`` its height scale."""
    assert h.shape[0] == h.shape[1]
    return (height_normals(h, strength * h.shape[0]) * 0.5 + 0.5).astype(np.float32)


def _write(path: Path, pixels: np.ndarray) -> None:
    a = np.clip(np.round(pixels * 255), 0, 255).astype(np.uint8)
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], 1 if a.ndim == 2 else a.shape[2], oiio.UINT8)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(a)
    out.close()


def make_texture_folder(root: Path, n: int = 10, size: int = 128) -> Path:
    """A manifest and ``n`` procedural materials: basecolor everywhere, normal/roughness/
    metallic on every other one."""
    manifest = {}
    for i in range(n):
        name = f"mat{i:02d}"
        (root / name).mkdir(parents=True)
        h = _height(size, i)
        rng = np.random.default_rng(100 + i)
        tint = rng.uniform(0.2, 0.9, 3)
        files = {"basecolor": "basecolor.png"}
        _write(root / name / "basecolor.png", h[..., None] * tint + 0.05 * (1 - h[..., None]))
        if i % 2 == 0:
            files.update(normal="normal.png", roughness="roughness.png", metallic="metallic.png")
            _write(root / name / "normal.png", normals_from_height(h))
            _write(root / name / "roughness.png", 1 - 0.7 * h)
            _write(root / name / "metallic.png", (h > 0.6).astype(np.float32))
        manifest[name] = {"files": files, "maps": list(files)}
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return make_texture_folder(tmp_path_factory.mktemp("textures"))


@pytest.fixture(scope="module")
def materials(folder):
    manifest = read_manifest(folder)
    train_names, held = split_materials(manifest)
    return load_materials(folder, train_names, manifest), load_materials(folder, held, manifest)


def test_split_is_deterministic_by_material_and_keeps_quotas():
    manifest = {f"m{i}": {"files": {"basecolor": "b.jpg"}} for i in range(60)}
    for i in range(0, 60, 3):
        manifest[f"m{i}"]["files"]["normal"] = "n.jpg"
    a_train, a_held = split_materials(manifest)
    b_train, b_held = split_materials(dict(reversed(list(manifest.items()))))
    assert (a_train, a_held) == (b_train, b_held)
    assert not set(a_train) & set(a_held) and len(a_train) + len(a_held) == 60
    assert 12 <= len(a_held) <= 16  # basecolor quota 12, normal quota 4 (20 // 5)
    assert sum("normal" in manifest[m]["files"] for m in a_held) == 4


@pytest.mark.parametrize("op", range(8))
def test_dihedral_moves_normal_vectors_with_the_pixels(op):
    """Transforming a height field and deriving its normals equals transforming the normals."""
    h = _height(48, 3)
    n = torch.from_numpy(normals_from_height(h)).permute(2, 0, 1)[None].double()
    h_t = dihedral(torch.from_numpy(h)[None, None].expand(1, 3, -1, -1), op, "colour")
    expect = torch.from_numpy(normals_from_height(h_t[0, 0].numpy())).permute(2, 0, 1)[None]
    got = dihedral(n, op, "normal")
    assert torch.allclose(got.float(), expect, atol=1e-5)
    if op:  # a pixel move alone (the colour rule) is wrong for a normal map
        assert not torch.allclose(dihedral(n, op, "colour").float(), expect, atol=1e-3)


def test_sampler_batches_are_a_function_of_seed_and_step(materials):
    train_m, _ = materials
    s = CropSampler(train_m, ("colour", "data", "normal"), 2, 32, 6, seed=5)
    lr1, hr1, k1 = s.batch(7)
    lr2, hr2, k2 = s.batch(7)
    assert torch.equal(lr1, lr2) and torch.equal(hr1, hr2) and k1 == k2
    assert set(k1) == {"colour", "data", "normal"}
    assert lr1.shape == (6, 3, 16, 16) and hr1.shape == (6, 3, 32, 32)
    assert not torch.equal(s.batch(8)[1], hr1)
    normals = hr1[[i for i, k in enumerate(k1) if k == "normal"]] * 2 - 1
    assert (normals[:, 2] > 0).all()


def test_data_crops_are_one_scalar_map_each_as_the_prior_runs_them(materials):
    """The direct prior runs a data map channel by channel, each a greyscale image: a data
    crop is one scalar map in all three channels, in training and in validation, and the
    validation crops take each of a material's scalar maps at least once."""
    train_m, held_m = materials
    _, hr, kinds = CropSampler(train_m, ("data",), 2, 32, 6, seed=5).batch(3)
    assert set(kinds) == {"data"}
    assert torch.equal(hr[:, 0], hr[:, 1]) and torch.equal(hr[:, 0], hr[:, 2])
    crops = validation_crops(held_m + train_m, "data", 32)
    assert crops and all((c == c[..., :1]).all() for _, c in crops)
    mat = next(m for m in held_m + train_m if m.has("data"))
    mine = [c for n, c in crops if n.split("#")[0] == mat.name]
    assert len(mine) == 2  # roughness and metallic, one crop each
    binary = sorted(len(np.unique(c)) <= 2 for c in mine)  # the metallic map is a mask
    assert binary == [False, True]


def test_jpeg_stage_compresses_half_the_lr_crops_and_stays_deterministic(materials):
    train_m, _ = materials
    kinds = ("colour", "data", "normal")
    clean = CropSampler(train_m, kinds, 2, 32, 8, seed=5)
    jpeg = CropSampler(train_m, kinds, 2, 32, 8, seed=5, jpeg=(30, 60))
    _, hr_c, k_c = clean.batch(3)
    lr_j, hr_j, k_j = jpeg.batch(3)
    assert k_j == k_c and torch.equal(hr_j[0], hr_c[0])  # the first crop is drawn alike
    assert torch.equal(jpeg.batch(3)[0], lr_j)  # a function of (seed, step): resume is exact
    n_jpeg = 0
    for step in range(4, 16):
        for lr, hr, kind in zip(*jpeg.batch(step), strict=True):
            if not torch.equal(lr, degrade_pair(hr[None], 2, kind)[0]):
                n_jpeg += 1
                assert torch.equal(lr, torch.round(lr * 255) / 255)  # 8-bit, as decoded
    assert 24 <= n_jpeg <= 72, n_jpeg  # of 96
    every = CropSampler(train_m, kinds, 2, 32, 8, seed=5, jpeg=(30, 60), jpeg_share=1.0)
    for lr, hr, kind in zip(*every.batch(4), strict=True):
        assert not torch.equal(lr, degrade_pair(hr[None], 2, kind)[0])


def test_lr_kernels_are_drawn_per_crop_and_validation_takes_them_in_turn(materials):
    """With one kernel the batches are the protocol's run's (no extra draw); with several,
    each LR crop is its HR crop downsampled by one of them (normal maps renormalised), more
    than one appears, and the batch is still a function of (seed, step). The validator's crop
    i is made by kernel i modulo their number."""
    from pbrsr_core.prior.train.loop import Validator

    train_m, held_m = materials
    kinds = ("colour", "data", "normal")
    plain = CropSampler(train_m, kinds, 2, 32, 8, seed=5)
    one = CropSampler(train_m, kinds, 2, 32, 8, seed=5, kernels=("gaussian",))
    assert all(torch.equal(a, b) for a, b in zip(plain.batch(3), one.batch(3)[:2], strict=False))
    ks = ("gaussian", "area", "lanczos")
    mixed = CropSampler(train_m, kinds, 2, 32, 8, seed=5, kernels=ks)
    lr_m, _, _ = mixed.batch(3)
    assert torch.equal(mixed.batch(3)[0], lr_m)
    used = []
    for step in range(4):
        for lr, hr, kind in zip(*mixed.batch(step), strict=True):
            hit = [k for k in ks if torch.allclose(lr, degrade_pair(hr[None], 2, kind, k)[0])]
            assert len(hit) == 1, (kind, hit)
            used += hit
    assert len(set(used)) == 3, used
    area = degrade_pair(lr_m[:1], 2, "colour", "area")[0]
    assert torch.allclose(area, lr_m[0].reshape(3, 8, 2, 8, 2).mean(dim=(2, 4)), atol=1e-6)
    val = Validator(held_m, ("colour",), 2, 32, kernels=("gaussian", "area"))
    lr_v, hr_v = val.sets["colour"]
    for i in range(len(hr_v)):
        k = ("gaussian", "area")[i % 2]
        assert torch.allclose(lr_v[i], degrade_pair(hr_v[i : i + 1], 2, "colour", k)[0])
    with pytest.raises(InvalidOptions, match="unknown LR kernel"):
        TrainConfig(kernels=("nearest",)).check()


@pytest.mark.parametrize("draw", [graphics_crop, data_graphics_crop, normal_graphics_crop])
def test_a_drawing_is_a_crop_drawn_from_its_generator(draw):
    a = draw(np.random.default_rng(3), 64)
    assert a.shape == (64, 64, 3) and a.dtype == np.uint8
    assert np.array_equal(a, draw(np.random.default_rng(3), 64))
    assert not np.array_equal(a, draw(np.random.default_rng(4), 64))


def test_graphics_crops_are_flat_coloured_drawings():
    crops = [graphics_crop(np.random.default_rng(s), 64) for s in range(20)]
    # flat colours with antialiased edges: most texels repeat a neighbour, and edges exist
    flat = np.mean([np.mean(np.all(c[:, 1:] == c[:, :-1], axis=2)) for c in crops])
    assert flat > 0.6, flat
    assert all(len(np.unique(c.reshape(-1, 3), axis=0)) > 1 for c in crops)


def test_data_graphics_crops_are_grey_regions_half_of_them_masks():
    crops = [data_graphics_crop(np.random.default_rng(s), 64) for s in range(40)]
    assert all((c[..., 0] == c[..., 1]).all() and (c[..., 0] == c[..., 2]).all() for c in crops)
    # a mask's texels are 0 or 255 but on its antialiased edges
    masks = [c for c in crops if np.mean((c[..., 0] == 0) | (c[..., 0] == 255)) > 0.9]
    assert 10 <= len(masks) <= 30, len(masks)
    flat = np.mean([np.mean(c[:, 1:, 0] == c[:, :-1, 0]) for c in crops])
    assert flat > 0.6, flat


def test_height_normals_lean_away_from_the_rise_in_the_opengl_frame():
    ramp = np.tile(np.arange(8.0), (8, 1))  # rises to the right, 1 a texel
    for down in (1, 2):
        n = height_normals(ramp, 0.5, down=down)
        assert n.shape == (8 // down, 8 // down, 3)
        np.testing.assert_allclose(n, np.broadcast_to([-0.5, 0, 1] / np.sqrt(1.25), n.shape))
    # rows run down the image: a height rising down the image rises towards -Y
    n = height_normals(ramp.T.copy(), 2.0)
    np.testing.assert_allclose(n, np.broadcast_to([0, 2, 1] / np.sqrt(5.0), n.shape))
    bump = np.exp(-((np.arange(32.0)[:, None] - 16) ** 2 + (np.arange(32.0) - 16) ** 2) / 20)
    n = height_normals(bump, 8.0)
    assert n[16, 20, 0] > 0.1 and n[16, 12, 0] < -0.1  # right side leans right
    assert n[12, 16, 1] > 0.1 and n[20, 16, 1] < -0.1  # the side above leans up
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-12)


def test_normal_graphics_crops_are_normal_maps_of_flat_ground_and_bevelled_shapes():
    flat, tilted = [], []
    for seed in range(20):
        n = normal_graphics_crop(np.random.default_rng(seed), 64).astype(np.float64) / 127.5 - 1
        length = np.linalg.norm(n, axis=-1)
        assert np.all(np.abs(length - 1) < 0.02) and np.all(n[..., 2] > 0)
        angle = np.degrees(np.arccos(np.clip(n[..., 2] / length, -1, 1)))
        flat.append(np.mean(angle < 1.0))
        tilted.append(np.mean(angle > 10.0))
    assert np.mean(flat) > 0.3, flat  # flat ground between the shapes
    assert sum(t > 0.01 for t in tilted) >= 15, tilted  # bevels that lean the normal


def test_graphics_share_replaces_crops_of_every_kind_and_stays_deterministic(
    materials, monkeypatch
):
    train_m, _ = materials
    kinds = ("colour", "data", "normal")
    plain = CropSampler(train_m, kinds, 2, 32, 6, seed=5)
    every = CropSampler(train_m, kinds, 2, 32, 6, seed=5, graphics=1.0)
    off = CropSampler(train_m, kinds, 2, 32, 6, seed=5, graphics=0.0)
    assert torch.equal(off.batch(2)[1], plain.batch(2)[1])  # no share: the batches as before
    lr, hr, k = every.batch(2)
    assert torch.equal(every.batch(2)[1], hr)  # a function of (seed, step): resume is exact

    def flat(crop: torch.Tensor) -> float:  # texels repeating their left neighbour
        texels = (crop * 255).round().byte().permute(1, 2, 0).numpy()
        return float(np.mean(np.all(texels[:, 1:] == texels[:, :-1], axis=2)))

    # drawings are flat colours; the materials' colour crops are not
    assert all(
        flat(h) < 0.2 for h, kind in zip(*plain.batch(2)[1:], strict=True) if kind == "colour"
    )
    for i, kind in enumerate(k):
        assert kind == "normal" or flat(hr[i]) > 0.5  # drawn in flat colours or levels
        assert torch.equal(lr[i], degrade_pair(hr[i][None], 2, kind)[0])
    drawn = {"colour": 0, "data": 0, "normal": 0}

    def counted(kind, draw):
        def fn(rng, p):
            drawn[kind] += 1
            return draw(rng, p)

        return fn

    monkeypatch.setattr(data_mod, "graphics_crop", counted("colour", graphics_crop))
    monkeypatch.setattr(data_mod, "normal_graphics_crop", counted("normal", normal_graphics_crop))
    monkeypatch.setattr(data_mod, "data_graphics_crop", counted("data", data_graphics_crop))
    every.batch(3)
    assert drawn == {"colour": 2, "data": 2, "normal": 2}  # every crop of 6
    drawn.update(colour=0, data=0, normal=0)
    half = CropSampler(train_m, ("colour", "normal"), 2, 32, 8, seed=5, graphics=0.5)
    for step in range(8):
        half.batch(step)
    assert 8 <= drawn["colour"] <= 24 and 8 <= drawn["normal"] <= 24, drawn  # of 32 each
    with pytest.raises(InvalidOptions, match="graphics share"):
        TrainConfig(kinds=("colour",), graphics=1.5).check()
    TrainConfig(kinds=("normal",), graphics=0.5).check()
    TrainConfig(kinds=("data",), graphics=0.5).check()


def test_bad_jpeg_range_is_refused():
    with pytest.raises(InvalidOptions, match="JPEG qualities"):
        TrainConfig(jpeg=(90, 70)).check()
    with pytest.raises(InvalidOptions, match="JPEG qualities"):
        TrainConfig(jpeg=(0, 70)).check()
    with pytest.raises(InvalidOptions, match="JPEG share"):
        TrainConfig(jpeg=(70, 90), jpeg_share=0.0).check()


@pytest.mark.parametrize("loss", ["l1", "l1-backprojected"])
def test_loss_compares_the_output_as_it_is_or_backprojected(materials, tmp_path, one_thread, loss):
    """The first step's loss is the L1 of the start weights' output on the first batch, taken
    back-projected onto the LR crop for ``l1-backprojected``; the model card names it."""
    train_m, val_m = materials
    cfg = TrainConfig(kinds=("colour",), steps=1, batch_size=2, patch=32, val_patch=64,
                      widths=TINY, init="random", loss=loss, scale=2)  # fmt: skip
    seen: list[float] = []
    train(cfg, train_m, val_m, tmp_path / "run" / "tiny-colour", name="tiny-colour", resume=False,
          progress=lambda step, total, info: seen.append(info["loss"]))  # fmt: skip
    net = build_network(cfg)
    sampler = CropSampler(train_m, cfg.kinds, cfg.scale, cfg.patch, cfg.batch_size, cfg.seed)
    lr, hr, _ = sampler.batch(0)
    with torch.no_grad():
        up = upscale_net(net, lr, cfg.scale)
        raw = float(interior_l1(up, hr, 4 * cfg.scale))
        projected = float(interior_l1(back_project(up, lr, cfg.scale), hr, 4 * cfg.scale))
    assert raw != pytest.approx(projected, rel=1e-3)
    assert seen[0] == pytest.approx(projected if loss == "l1-backprojected" else raw, rel=1e-5)
    card = model_card([tmp_path / "run"], {}, "")
    assert ("back-projected onto the LR crop" in card) == (loss == "l1-backprojected")


def test_unknown_loss_is_refused():
    with pytest.raises(InvalidOptions, match="unknown loss 'l2'"):
        TrainConfig(loss="l2").check()
    with pytest.raises(InvalidOptions, match="distilling run"):
        TrainConfig(loss="l1-backprojected", distill=True).check()


class _Stop(Exception):
    pass


def assert_resume_is_exact(cfg, materials, done, out, name, hist, stop) -> None:
    """A run of ``cfg`` into ``out`` stopped after step ``stop`` and resumed ends with the
    weights and history of the unbroken run in ``done`` (``hist``)."""
    train_m, val_m = materials

    def stop_there(step, total, info):
        if step == stop:
            raise _Stop

    with pytest.raises(_Stop):
        train(cfg, train_m, val_m, out, name=name, progress=stop_there)
    _, hist_b = train(cfg, train_m, val_m, out, name=name)
    a = torch.load(done / "checkpoint.pt", weights_only=False)
    b = torch.load(out / "checkpoint.pt", weights_only=False)
    for key in ("net", "ema"):
        for k, t in a[key].items():
            assert torch.equal(t, b[key][k]), (key, k)
    assert hist_b.loss == hist.loss and hist_b.val_psnr == hist.val_psnr


def test_tiny_network_learns_and_resumes_exactly(materials, tmp_path, one_thread):
    train_m, val_m = materials
    cfg = TrainConfig(
        kinds=("colour",),
        steps=60,
        batch_size=4,
        patch=32,
        val_patch=64,
        lr=2e-3,
        widths=TINY,
        init="random",
        val_every=30,
        ckpt_every=30,
    )
    weights, hist = train(cfg, train_m, val_m, tmp_path / "a", name="tiny", resume=False)
    assert hist.loss[-1] < 0.6 * hist.loss[0], hist.loss
    assert weights.is_file() and hist.best_step in (30, 60)

    assert_resume_is_exact(cfg, materials, tmp_path / "a", tmp_path / "b", "tiny", hist, 30)
    other = TrainConfig(**{**cfg.__dict__, "lr": 1e-3})
    with pytest.raises(InvalidOptions, match="other settings"):
        train(other, train_m, val_m, tmp_path / "b", name="tiny")


def test_srmd_trained_through_int8_rounding_learns_validates_in_int8_and_resumes_exactly(
    materials, tmp_path, one_thread
):
    train_m, val_m = materials
    cfg = TrainConfig(
        kinds=("colour",),
        scale=4,
        stride=4,
        steps=40,
        batch_size=4,
        patch=48,
        val_patch=64,
        lr=2e-3,
        arch="srmd",
        widths=(8,) * 3,
        init="random",
        int8=True,
        val_every=20,
        ckpt_every=20,
    )
    _, hist = train(cfg, train_m, val_m, tmp_path / "a", name="q", resume=False)
    assert hist.loss[-1] < 0.7 * hist.loss[0], hist.loss
    state = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=False)
    calibration = Calibration.from_json(state["int8"], 3)
    ema = load_network(tmp_path / "a" / "q.safetensors")
    assert isinstance(ema, SRMD)
    # validation scored the network through the int8 rounding, not in float32
    plain = TrainConfig(**{**cfg.__dict__, "int8": False})
    validator = Validator(val_m, ("colour",), 4, 64)
    ema_state = {k: v.float() for k, v in state["ema"].items()}
    ema.load_state_dict(ema_state)
    assert validator(FakeInt8(ema, calibration))["colour"] == hist.val_psnr["colour"][-1]
    assert validator(ema)["colour"] != hist.val_psnr["colour"][-1]
    assert_resume_is_exact(cfg, materials, tmp_path / "a", tmp_path / "b", "q", hist, 20)
    with pytest.raises(InvalidOptions, match="other settings"):
        train(plain, train_m, val_m, tmp_path / "b", name="q")
    with pytest.raises(InvalidOptions, match="--int8 trains an SRMD network"):
        TrainConfig(kinds=("colour",), int8=True).check()


def test_weights_file_round_trip_and_texture_prior(tmp_path):
    cfg = TrainConfig(kinds=("colour",), widths=TINY, init="random")
    nets = {}
    for kind in ("colour", "normal"):
        torch.manual_seed(len(nets))
        nets[kind] = UpConv7(TINY)
        cfg.kinds = (kind,)
        save_network(nets[kind], tmp_path / f"t-{kind}.safetensors", cfg, {"step": "1"})
    back = load_network(tmp_path / "t-colour.safetensors")
    assert back.widths == TINY
    x = torch.rand(1, 3, 20, 20)
    assert torch.equal(back(x), nets["colour"].eval()(x))
    prior = TexturePrior(tmp_path)
    assert prior.for_kind("normal") is not prior and prior.for_kind("colour") is prior
    assert prior.for_kind("data").name == "waifu2x-photo"  # no data weights: the fallback
    with torch.no_grad():
        a = prior.for_kind("colour")._forward(x, 2)
        b = prior.for_kind("normal")._forward(x, 2)
    assert a.shape == (1, 3, 40, 40) and not torch.equal(a, b)
    up = prior.upscale(x, 4)
    assert up.shape == (1, 3, 80, 80) and torch.isfinite(up).all()
    check_name(f"texture:{tmp_path}")
    with pytest.raises(PriorUnavailable):
        TexturePrior(tmp_path / "missing")
    (tmp_path / "junk.safetensors").write_bytes(b"not a file")
    with pytest.raises(PriorUnavailable):
        TexturePrior(tmp_path)


def test_shipped_prior_loads_and_upscales_each_kind(capfd):
    """pbr-upconv7 ships a network per kind (MODEL_CARD.md); colour and data maps have
    waifu2x-photo as a second candidate for the self-check; the renders go through the colour
    network."""
    prior = load_prior("pbr-upconv7")
    assert prior.scales == (2, 4, 8)
    assert set(prior.nets) == {"colour", "data", "normal"} and prior.kind == "colour"
    for kind in ("colour", "data", "normal"):
        own, photo = prior.candidates(kind, 4)
        assert own is prior.for_kind(kind) and photo.name == "waifu2x-photo"
        assert own.name == ("pbr-upconv7" if kind == "colour" else f"pbr-upconv7[{kind}]")
    x = torch.rand(1, 3, 24, 24)
    for kind in ("colour", "data", "normal"):
        for s in (2, 4):
            y = prior.for_kind(kind).upscale(x, s)
            assert y.shape == (1, 3, 24 * s, 24 * s) and torch.isfinite(y).all()
    code, err = run_cli(["priors", "install", "pbr-upconv7"], capfd)
    assert code == 0, err


def test_shipped_fast_prior_runs_narrow_later_passes_behind_pbr_upconv7(capfd):
    """pbr-upconv7-fast: pbr-upconv7's networks make the first x2 pass, a narrow residual
    network every later one for colour and normal maps; data maps run pbr-upconv7's network in
    every pass (MODEL_CARD.md in its folder)."""
    base, fast = load_prior("pbr-upconv7"), load_prior("pbr-upconv7-fast")
    assert fast.scales == (2, 4, 8) and set(fast.later) == {"colour", "normal"}
    x = torch.rand(1, 3, 20, 20)
    with torch.no_grad():
        data = base.nets["data"][2]
        twice = data(data(x).clamp(0, 1)).clamp(0, 1)
        assert torch.equal(fast.for_kind("data")._forward(x, 4), twice)
        for kind in ("colour", "normal"):
            first, later = fast.nets[kind][2], fast.later[kind]
            assert later.residual and sum(p.numel() for p in later.parameters()) < 200_000
            for a, b in zip(first.parameters(), base.nets[kind][2].parameters(), strict=True):
                assert torch.equal(a, b)
            one = first(x).clamp(0, 1)
            assert torch.equal(fast.for_kind(kind)._forward(x, 2), one)
            assert torch.equal(fast.for_kind(kind)._forward(x, 4), later(one).clamp(0, 1))
    assert fast.num_parameters() < 1.3 * base.num_parameters()
    code, err = run_cli(["priors", "install", "pbr-upconv7-fast"], capfd)
    assert code == 0, err


def test_shipped_srmd_prior_makes_colour_and_normal_x4_in_one_srmd_pass(capfd):
    """pbr-srmd, the default prior: pbr-upconv7's x2 colour and normal networks, SRMD networks
    (float16 on disk, under 4 MiB) that make colour and normal maps x4 in one pass, and an x2
    data network of its own, pbr-upconv7's fine-tuned (MODEL_CARD.md in its folder); x8 colour
    is the SRMD network then the x2 one, x8 normal maps are three x2 passes (the set's
    ``x4_only``)."""
    from pbrsr_core.options import DEFAULT_PRIOR
    from pbrsr_core.prior.srmd import SRMD
    from pbrsr_core.prior.texture import WEIGHTS_ROOT, shipped_files

    assert DEFAULT_PRIOR == "pbr-srmd"
    base, prior = load_prior("pbr-upconv7"), load_prior("pbr-srmd")
    assert prior.scales == (2, 4, 8) and not prior.later
    assert all(f.stat().st_size < 4 * 2**20 for f in shipped_files("pbr-srmd"))
    x = torch.rand(1, 3, 20, 20)
    with torch.no_grad():
        for kind in ("colour", "normal"):
            srmd, up2 = prior.nets[kind][4], prior.nets[kind][2]
            assert isinstance(srmd, SRMD) and srmd.stride == 4
            run = prior.for_kind(kind)._forward
            assert torch.equal(run(x, 4), srmd(x).clamp(0, 1))
            assert torch.equal(run(x, 2), base.for_kind(kind)._forward(x, 2))
            if kind == "colour":
                assert torch.equal(run(x, 8), up2(srmd(x).clamp(0, 1)).clamp(0, 1))
            else:
                assert torch.equal(run(x, 8), base.for_kind(kind)._forward(x, 8))
        assert torch.equal(prior._forward(x, 4), prior.for_kind("colour")._forward(x, 4))
        assert set(prior.nets["data"]) == {2}
        assert prior.for_kind("normal").scales == (2, 4, 8)
        assert prior.describe()["x4_only"] == ["normal"]
        # one SRMD pass runs in tiles of up to 1024² on the CPU, the x2 networks' passes 512²
        one_pass = (prior.one_pass_bytes_per_pixel, 1024)
        assert prior.tile_limits(4) == prior.for_kind("colour").tile_limits(4) == one_pass
        assert prior.for_kind("normal").tile_limits(4) == one_pass
        assert prior.for_kind("colour").tile_limits(8)[1] == 512
        assert prior.for_kind("normal").tile_limits(8)[1] == 512
        assert prior.for_kind("data").tile_limits(4) == (prior.bytes_per_pixel, 512)
        assert prior.for_kind("colour").tile_limits(2) == (prior.bytes_per_pixel, 512)
        data, base_data = prior.nets["data"][2], base.nets["data"][2]
        assert type(data) is type(base_data) and data.widths == base_data.widths
        assert not torch.equal(data(x), base_data(x))
        alone = load_prior(f"texture:{WEIGHTS_ROOT / 'pbr-srmd' / 'pbr-srmd-data.safetensors'}")
        assert torch.equal(
            prior.for_kind("data")._forward(x, 4), alone.for_kind("data")._forward(x, 4)
        )
    code, err = run_cli(["priors", "install", "pbr-srmd"], capfd)
    assert code == 0, err


def test_pbr_srmd_offers_its_colour_x2_passes_as_a_candidate_at_x4_only():
    """At x4 (and only there, and not under a cap of x2) the self-check of a colour map also
    weighs pbr-srmd's x2 colour network run twice: pbr-upconv7's x4, by a name of its own
    that a check's pick resolves to."""
    from pbrsr_core.prior.selfcheck import chosen, offered

    base, prior = load_prior("pbr-upconv7"), load_prior("pbr-srmd")
    names = [c.name for c in prior.candidates("colour", 4)]
    assert names == ["pbr-srmd", "waifu2x-photo", "pbr-srmd[colour/x2]"]
    for kind, scale in (("colour", 2), ("colour", 8), ("data", 4), ("normal", 4)):
        assert len(prior.candidates(kind, scale)) == 2
    assert len(offered(prior, "colour", 4, max_prior_scale=2)) == 2
    assert len(offered(prior, "colour", 4, max_prior_scale=4)) == 3
    passes = prior.x2_passes("colour")
    assert passes is prior.candidates("colour", 4)[2]  # one view, made once
    assert passes.scales == (2, 4, 8) and passes.one_pass_scales == (2,)
    assert passes.tile_limits(4) == (prior.bytes_per_pixel, 512)
    assert not passes.int8_ready()
    assert passes.num_parameters() == base.for_kind("colour").num_parameters()
    x = torch.rand(1, 3, 20, 20)
    with torch.no_grad():
        for s in (2, 4, 8):
            assert torch.equal(passes._forward(x, s), base.for_kind("colour")._forward(x, s))
        assert not torch.equal(passes._forward(x, 4), prior.for_kind("colour")._forward(x, 4))
    check = {"priors": ["pbr-srmd[colour/x2]"]}
    assert chosen(prior, "colour", check, 1, 4) == [passes]
    assert chosen(prior, "colour", check, 1, 8) == [prior.for_kind("colour")]  # not offered
    assert chosen(prior, "colour", check, 1, 4, max_prior_scale=2) == [prior.for_kind("colour")]


def test_cli_trains_reports_and_the_result_is_a_prior(tmp_path, capfd):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=256)
    out = tmp_path / "out"
    code, err = run_cli(
        [
            "priors",
            "train",
            "-o",
            str(out),
            "--textures",
            str(folder),
            "--kinds",
            "colour,normal",
            "--steps",
            "4",
            "--batch",
            "2",
            "--patch",
            "32",
            "--widths",
            "4,8",
            "--jpeg",
            "80-95",
            "--kernels",
            "gaussian,lanczos",
            "-q",
        ],
        capfd,
    )
    assert code == 0, err
    files = sorted(p.name for p in out.glob("*/*.safetensors"))
    assert files == ["pbr-upconv7-colour.safetensors", "pbr-upconv7-normal.safetensors"]
    report = json.loads((out / "report.json").read_text())
    assert set(report) == {"colour", "normal"}
    assert set(report["normal"]["4"]) == {"bicubic", "waifu2x-photo", "out"}
    assert "angle" in report["normal"]["4"]["out"]
    card = (out / "MODEL_CARD.md").read_text()
    assert "CC0" in card and "priors train" in card and (out / "report.png").is_file()
    assert "JPEG stage" in card and "50% of the LR crops at quality 80-95" in card
    assert "pbr-upconv7-colour.safetensors: gaussian, lanczos" in card
    prior = TexturePrior(out)  # the training output folder is a prior as it is written
    assert set(prior.nets) == {"colour", "normal"}
    assert prior.for_kind("normal").upscale(torch.rand(1, 3, 16, 16), 4).shape[-1] == 64
    check_name(f"texture:{out}")
    cmp = tmp_path / "cmp"
    args = ["priors", "report", str(out), "-o", str(cmp), "--textures", str(folder)]
    code, err = run_cli([*args, "--scales", "4"], capfd)
    assert code == 0, err
    again = json.loads((cmp / "report.json").read_text())
    assert set(again["colour"]) == {"crops", "materials", "4"}
    assert again["colour"]["4"]["out"] == report["colour"]["4"]["out"] | {
        "seconds": again["colour"]["4"]["out"]["seconds"]
    }
    area_args = ["priors", "report", str(out), "-o", str(tmp_path / "a"), "--textures", str(folder)]
    code, err = run_cli([*area_args, "--scales", "4", "--kernel", "area"], capfd)
    assert code == 0, err
    assert "LR crops made by the area kernel" in (tmp_path / "a" / "report.md").read_text()
    area = json.loads((tmp_path / "a" / "report.json").read_text())["colour"]["4"]
    assert area["bicubic"]["psnr"] != again["colour"]["4"]["bicubic"]["psnr"]
    flat = tmp_path / "set"  # a texture set's folder, its files side by side, as shipped
    flat.mkdir()
    for f in out.glob("*/*.safetensors"):
        shutil.copy(f, flat / f.name)
    code, err = run_cli(["priors", "report", str(flat), "-o", str(tmp_path / "s"), "--textures",
                         str(folder), "--scales", "4"], capfd)  # fmt: skip
    assert code == 0, err
    as_set = json.loads((tmp_path / "s" / "report.json").read_text())["colour"]["4"]["set"]
    assert as_set["psnr"] == again["colour"]["4"]["out"]["psnr"]
    code, err = run_cli([*args, "--scales", "3"], capfd)
    assert code == InvalidOptions.exit_code and "among 2, 4, 8" in err
    code, err = run_cli([*args, "--kernel", "box"], capfd)
    assert code == InvalidOptions.exit_code and "unknown LR kernel(s) box" in err
    code, err = run_cli(["priors", "report", str(folder), "-o", str(cmp)], capfd)
    assert code == InvalidOptions.exit_code and "no trained networks" in err


@pytest.mark.parametrize(
    ("extra", "says"),
    [
        (["--kinds", "colour,gloss"], "gloss"),
        (["--patch", "33"], "multiple"),
        (["--patch", "16"], "larger than 16 px"),
        (["--widths", "4,x"], "widths"),
        (["--jpeg", "high"], "--jpeg"),
        (["--jpeg", "95-70"], "JPEG qualities"),
        (["--jpeg-share", "1"], "--jpeg-share needs --jpeg"),
        (["--graphics", "2"], "graphics share"),
        (["--kernels", "area,box"], "unknown LR kernel(s) box"),
        (["--kernels", ","], "(none given)"),
    ],
)
def test_cli_refuses_bad_training_input(tmp_path, capfd, extra, says):
    folder = make_texture_folder(tmp_path / "tex", n=10, size=64)
    out = tmp_path / "o"
    code, err = run_cli(
        ["priors", "train", "-o", str(out), "--textures", str(folder), "-q", *extra], capfd
    )
    assert code == InvalidOptions.exit_code and says in err, err
    assert not out.exists()


def test_cli_refuses_a_missing_texture_folder(tmp_path, capfd):
    out = tmp_path / "o"
    code, err = run_cli(
        ["priors", "train", "-o", str(out), "--textures", str(tmp_path / "no")], capfd
    )
    assert code == InvalidOptions.exit_code and "not found" in err, err
    assert not out.exists()


def test_stride_four_network_runs_x4_in_one_pass_and_mixes_with_x2(tmp_path):
    from pbrsr_core.prior.texture import passes

    assert passes({2}, 8) == [2, 2, 2] and passes({2, 4}, 8) == [4, 2] and passes({4}, 2) is None
    net4 = UpConv7(TINY, stride=4)
    assert net4(torch.rand(1, 3, 10, 12)).shape == (1, 3, 40, 48)
    cfg = TrainConfig(kinds=("colour",), widths=TINY, init="random", stride=4, scale=4)
    save_network(net4, tmp_path / "c4.safetensors", cfg, {})
    only4 = TexturePrior(tmp_path)
    assert only4.scales == (4,)
    save_network(UpConv7(TINY), tmp_path / "c2.safetensors", TrainConfig(widths=TINY), {})
    both = TexturePrior(tmp_path)
    assert both.scales == (2, 4, 8)
    x = torch.rand(1, 3, 8, 8)
    with torch.no_grad():
        expect = both.nets["colour"][2](both.nets["colour"][4](x).clamp(0, 1)).clamp(0, 1)
        assert torch.equal(both._forward(x, 8), expect)
        # a kind whose x4 network makes x4 only runs x8 as three x2 passes
        x4_only = TexturePrior(tmp_path, x4_only=frozenset({"colour"}))
        assert x4_only.scales == (2, 4, 8)
        assert torch.equal(x4_only._forward(x, 4), both._forward(x, 4))
        net2 = both.nets["colour"][2]
        expect = net2(net2(net2(x).clamp(0, 1)).clamp(0, 1)).clamp(0, 1)
        assert torch.equal(x4_only._forward(x, 8), expect)
    with pytest.raises(InvalidOptions, match="stride 4"):
        TrainConfig(stride=4, scale=2).check()


def test_start_weights_of_another_stride_give_the_convolutions(tmp_path):
    x2 = UpConv7(TINY)
    save_network(x2, tmp_path / "x2.safetensors", TrainConfig(widths=TINY), {})
    cfg = TrainConfig(widths=TINY, stride=4, scale=4, init=str(tmp_path / "x2.safetensors"))
    net = build_network(cfg)
    for a, b in zip(net.mods[:-1], x2.mods[:-1], strict=True):
        assert torch.equal(a.weight, b.weight) and torch.equal(a.bias, b.bias)
    assert net.mods[-1].weight.shape != x2.mods[-1].weight.shape
    with pytest.raises(InvalidOptions, match="widths"):
        build_network(TrainConfig(widths=(4, 4), init=str(tmp_path / "x2.safetensors")))


def test_start_weights_resolve_per_kind(tmp_path):
    from pbrsr_core.prior.train.weights import resolve_start

    for kind, stride in (("colour", 2), ("colour", 4), ("normal", 2)):
        cfg = TrainConfig(kinds=(kind,), widths=TINY, stride=stride, scale=4)
        save_network(
            UpConv7(TINY, stride=stride), tmp_path / f"{kind}{stride}.safetensors", cfg, {}
        )
    src = f"texture:{tmp_path}"
    assert resolve_start(src, "colour", 4).endswith("colour4.safetensors")
    assert resolve_start(src, "colour", 2).endswith("colour2.safetensors")
    assert resolve_start(src, "normal", 4).endswith("normal2.safetensors")  # the other stride
    assert resolve_start("waifu2x-photo", "data", 2) == "waifu2x-photo"
    with pytest.raises(PriorUnavailable, match="no weights for data"):
        resolve_start(src, "data", 2)
    with pytest.raises(PriorUnavailable, match="cannot start from"):
        resolve_start("rrdn-thick", "colour", 2)


def test_report_scores_each_crop_and_each_data_map_type(materials):
    """Pooled PSNR lets the crops furthest from their ground truth decide; the report also
    gives the mean of each crop's PSNR, and for data maps that mean per map type, each
    recomputed here crop by crop."""
    from pbrsr_core.prior.train.report import _table, score_prior

    train_m, held_m = materials
    crops = validation_crops(held_m + train_m, "data", 32)
    types = {n.rpartition(":")[2] for n, _ in crops}
    assert types == {"roughness", "metallic"}
    scores = score_prior(load_prior("bicubic"), "data", crops, 2)
    own = []
    for _, c in crops:
        hr = torch.from_numpy(c).permute(2, 0, 1)[None].float() / 255
        up = load_prior("bicubic").upscale(degrade_pair(hr, 2, "data"), 2)
        own.append(-10 * np.log10(float(((up - hr)[..., 2:-2, 2:-2] ** 2).mean())))
    assert scores["crop_psnr"] == pytest.approx(np.mean(own), abs=1e-4)
    assert scores["crop_psnr"] >= scores["psnr"]  # the mean of logs against the log of a mean
    by_map = scores["by_map"]
    assert sum(e["crops"] for e in by_map.values()) == len(crops) and set(by_map) == types
    for m, e in by_map.items():
        mine = [v for (n, _), v in zip(crops, own, strict=True) if n.endswith(f":{m}")]
        assert e["crop_psnr"] == pytest.approx(np.mean(mine), abs=1e-4)
    md = _table({"data": {"crops": len(crops), "materials": 2, "2": {"bicubic": scores}}})
    assert "| prior | x2 PSNR | x2 crop mean | x2 s |" in md
    head = f"| prior | roughness ({by_map['roughness']['crops']}) x2 | metallic ("
    row = next(line for line in md.splitlines() if line.startswith(head))
    assert row.endswith(f"({by_map['metallic']['crops']}) x2 |")


def test_report_leaves_out_the_scales_a_set_cannot_run(tmp_path):
    """A set of x4 networks only has no x2 (nor x8) entry; its x4 is scored."""
    from pbrsr_core.prior.train.report import write_report

    folder = make_texture_folder(tmp_path / "tex", n=10, size=256)
    manifest = read_manifest(folder)
    held = load_materials(folder, split_materials(manifest)[1], manifest)

    cfg = TrainConfig(kinds=("colour",), widths=TINY, init="random", stride=4, scale=4)
    (tmp_path / "s4" / "c").mkdir(parents=True)
    save_network(UpConv7(TINY, stride=4), tmp_path / "s4" / "c" / "c.safetensors", cfg, {})
    md = write_report(tmp_path / "rep", held, (2, 4), folders=[tmp_path / "s4"])
    report = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert "s4" not in report["colour"]["2"] and "s4" in report["colour"]["4"]
    assert set(report["colour"]["2"]) == {"bicubic", "waifu2x-photo"}
    row = next(line for line in md.read_text().splitlines() if line.startswith("| s4 "))
    assert row.split("|")[2].strip() == "-"
    assert "stride x4" in (tmp_path / "rep" / "MODEL_CARD.md").read_text()


def test_set_without_colour_network_runs_renders_through_the_fallback(tmp_path):
    """A set of a normal network only: normal maps go through it; colour maps and images of
    no stated kind (the optimiser's renders) through waifu2x-photo."""
    cfg = TrainConfig(kinds=("normal",), widths=TINY, init="random")
    save_network(UpConv7(TINY), tmp_path / "n.safetensors", cfg, {})
    prior = TexturePrior(tmp_path)
    photo = load_prior("waifu2x-photo")
    assert prior.for_kind("colour") is prior.for_kind("data")
    assert prior.for_kind("colour").name == photo.name and prior.scales == photo.scales
    x = torch.rand(1, 3, 12, 12)
    assert torch.allclose(prior.upscale(x, 2), photo.upscale(x, 2), atol=1e-6)
    own = prior.for_kind("normal").upscale(x, 2)
    assert own.shape == (1, 3, 24, 24) and not torch.allclose(own, photo.upscale(x, 2))
    assert prior.num_parameters() == photo.num_parameters()
