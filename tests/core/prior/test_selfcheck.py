"""The prior self-check: a prior that loses to bicubic on a map of the asset one scale down
does not initialise that map; one that wins does; the pipeline reports each map's decision
and follows it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset import load_asset, make_demo_asset
from pbrsr_core.asset.procedural import make_quad_asset
from pbrsr_core.degrade import degrade_image
from pbrsr_core.optim import presets
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.selfcheck import MIN_SIDE, check_factor, prior_self_check


class BlurringPrior(Prior):
    """A real, poor prior: nearest-neighbour upscaling followed by a wide box blur."""

    name = "blurring"
    scales = (2, 4)
    back_project = False  # its output as it is: back-projection would sharpen it

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        up = F.interpolate(x, scale_factor=scale, mode="nearest")
        return F.avg_pool2d(up, 2 * scale + 1, stride=1, padding=scale, count_include_pad=False)


class OraclePrior(Prior):
    """A perfect prior for one image: returns the HR map the self-check's crop was degraded
    from."""

    name = "oracle"
    scales = (4,)
    back_project = False

    def __init__(self, hr: np.ndarray):
        super().__init__()
        self.hr = torch.from_numpy(hr[..., :3]).permute(2, 0, 1)[None]

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        h, w = x.shape[-2] * scale, x.shape[-1] * scale
        return self.hr[..., :h, :w].clone()


class SelectivePrior(BlurringPrior):
    """Perfect on the self-check of one LR map (it knows which HR crop that check degraded),
    the blurring prior on every other input."""

    name = "selective"
    scales = (4,)  # knows the x4 check's crop: no x2 to check a small map at (check_factor)

    def __init__(self, lr_map: np.ndarray, scale: int = 4, kernel: str = "gaussian"):
        super().__init__()
        small = degrade_image(lr_map[..., :3], scale, kernel=kernel)
        self.small = torch.from_numpy(small).permute(2, 0, 1)
        self.hr = torch.from_numpy(np.ascontiguousarray(lr_map[..., :3])).permute(2, 0, 1)

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        if x.shape[1:] == self.small.shape and torch.allclose(x[0], self.small, atol=1e-6):
            return self.hr[None].clone()
        return super()._forward(x, scale)


def _made_by(report: dict, name: str) -> list[str]:
    """What the report says each channel entry of the map ``name`` was made from."""
    (img,) = [img for img in report["images"] if img["name"] == name]
    return img["made_by"]


def _texture(size: int = 96, seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    base = g.random((size // 8, size // 8, 3)).astype(np.float32)
    t = torch.from_numpy(base).permute(2, 0, 1)[None]
    img = F.interpolate(t, size=(size, size), mode="bicubic", align_corners=False)
    return img[0].permute(1, 2, 0).clamp(0, 1).numpy()


def test_blurring_prior_is_rejected_and_a_perfect_one_accepted():
    tex = _texture()
    bad = prior_self_check(BlurringPrior(), tex, 4)
    assert bad is not None and not bad["use_prior"] and bad["prior_db"] < bad["bicubic_db"]
    assert bad["texels"] == 96 * 96
    assert bad["margins"][0] == pytest.approx(bad["prior_db"] - bad["bicubic_db"], abs=1.1e-3)
    assert bad["scale"] == 2  # 96 texels at x4: checked at x2 (check_factor)
    good = prior_self_check(OraclePrior(tex), tex, 4)
    assert good["use_prior"] and good["prior_db"] == 100.0
    assert good["margins"][0] > 0 and bad["margins"][0] < 0
    assert prior_self_check(BlurringPrior(), tex[:8, :8], 4) is None  # too small to check


def test_a_small_map_is_checked_at_a_smaller_factor():
    """One scale down the crop keeps MIN_SIDE texels a side where the priors allow: a 128²
    map at x8 is checked at x4 (16² would decide on too little), a 256² one at x8."""
    assert MIN_SIDE == 32
    assert [check_factor(n, 8) for n in (512, 256, 255, 128, 64, 40)] == [8, 8, 4, 4, 2, 2]
    assert [check_factor(n, 4) for n in (512, 128, 127, 96)] == [4, 4, 2, 2]
    assert check_factor(96, 4, [OraclePrior(np.zeros((8, 8, 3), np.float32))]) == 4  # x4 only
    assert check_factor(16, 2) == 2 and check_factor(24, 3) == 3

    class Blurring8(BlurringPrior):
        scales = (2, 4, 8)

    tex = _texture(128)
    small = prior_self_check(Blurring8(), tex, 8)
    assert small is not None and small["scale"] == 4 and small["texels"] == 128 * 128
    # what the report says is what was compared: the same check asked at x4 directly
    assert prior_self_check(Blurring8(), tex, 4) == small
    assert prior_self_check(Blurring8(), _texture(256), 8)["scale"] == 8
    assert prior_self_check(Blurring8(), tex[:31, :31], 8) is None  # under 4 * 8 texels


class HalfOraclePrior(OraclePrior):
    """Perfect on the left half of the check's crop, far off (inverted) on the right half."""

    name = "half-oracle"

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        out = super()._forward(x, scale)
        half = out.shape[-1] // 2
        out[..., half:] = 1.0 - out[..., half:]
        return out


def test_the_check_goes_one_scale_down_by_the_runs_lr_model():
    """A prior that knows the map's crop made by the area kernel one scale down is perfect on
    the check that makes it so, within ``lr_model("area")``, and blurs the protocol's crop."""
    from pbrsr_core.degrade import lr_model

    tex = _texture(128, seed=4)
    knows_area = SelectivePrior(tex, kernel="area")
    with lr_model("area"):
        assert prior_self_check(knows_area, tex, 4)["use_prior"]
    assert not prior_self_check(knows_area, tex, 4)["use_prior"]


def test_the_check_compares_only_covered_texels():
    """An atlas's uncovered texels are never seen: they do not decide the check."""
    tex = _texture()
    left = np.zeros((96, 96), dtype=bool)
    left[:, :48] = True
    prior = HalfOraclePrior(tex)
    whole = prior_self_check(prior, tex, 4)
    assert not whole["use_prior"] and whole["texels"] == 96 * 96
    on_left = prior_self_check(prior, tex, 4, covered=left)
    assert on_left["use_prior"] and on_left["prior_db"] == 100.0 and on_left["texels"] == 96 * 48
    assert not prior_self_check(prior, tex, 4, covered=~left)["use_prior"]
    few = np.zeros((96, 96), dtype=bool)
    few[:4, :4] = True  # fewer than (4 * scale)^2 covered texels: the whole crop decides
    assert prior_self_check(prior, tex, 4, covered=few)["texels"] == 96 * 96
    with pytest.raises(ValueError, match="coverage mask"):
        prior_self_check(prior, tex, 4, covered=left[:48])


def test_pipeline_reports_the_check_and_uses_bicubic_when_the_prior_loses(tmp_path, monkeypatch):
    import pbrsr_core.pipeline as pipeline

    real = pipeline.load_prior
    monkeypatch.setattr(
        pipeline, "load_prior", lambda n, d: BlurringPrior() if n == "blurring" else real(n, d)
    )
    asset = make_demo_asset(tmp_path / "demo.glb", size=64)
    out = tmp_path / "out"
    # the prior's own check (the data channels' blend is tested in test_guided.py)
    fast = presets.FAST.with_(blend_data=False)
    monkeypatch.setitem(presets.PRESETS, "fast", fast)
    # the CPU presets leave normal maps unchecked (the prior initialises them)
    report = upscale_asset(asset, tmp_path / "cpu", UpscaleOptions(preset="fast", prior="blurring"))
    (normal,) = [c for c in report["prior_check"] if "normal" in c["image"]]
    assert normal["use_prior"] and normal["note"] == "normal maps are not checked"
    assert report["prior_used"] == "blurring" and report["prior_init"] == [normal["image"]]
    every_kind = fast.with_(check_prior=("colour", "data", "normal"))
    monkeypatch.setitem(presets.PRESETS, "fast", every_kind)
    report = upscale_asset(asset, out, UpscaleOptions(preset="fast", prior="blurring"))
    keys = {"image", "index", "priors", "prior_db", "bicubic_db", "candidates", "texels"}
    keys |= {"use_prior", "channels", "margins", "gains", "flat", "spread", "scale"}
    assert all(set(c) == keys and not c["use_prior"] for c in report["prior_check"])
    check = next(c for c in report["prior_check"] if c["image"] == "bricks_albedo")
    assert check["channels"] == [False]
    assert report["prior_used"] == "bicubic" and report["prior_init"] == []
    assert "prior_check" in report["timings"]
    assert json.loads((out / "report.json").read_text())["prior_check"] == report["prior_check"]
    # the paper preset never checks: it always uses its prior
    out2 = tmp_path / "out2"
    tiny_paper = presets.PAPER.with_(iterations=1, n_elev=1, n_azim=2, render_res=32)
    monkeypatch.setitem(presets.PRESETS, "paper", tiny_paper)
    report = upscale_asset(asset, out2, UpscaleOptions(preset="paper", prior="blurring"))
    assert report["prior_check"] is None and report["prior_used"] == "blurring"
    assert report["prior_init"] == ["bricks_albedo"]


def test_each_colour_map_is_checked_on_its_own(tmp_path, monkeypatch):
    """Albedo and emissive of one material: the prior wins the check on the albedo only, so
    it initialises the albedo, bicubic the emissive, and the pseudo-GT still uses it."""
    import pbrsr_core.pipeline as pipeline

    albedo, emissive = _texture(64, seed=1), _texture(64, seed=2)
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": albedo, "emissive": emissive})
    lr_albedo = load_asset(asset).images[0].pixels  # as stored: 8-bit rounded
    prior = SelectivePrior(np.asarray(lr_albedo, np.float32))
    real = pipeline.load_prior
    monkeypatch.setattr(
        pipeline, "load_prior", lambda n, d: prior if n == "selective" else real(n, d)
    )
    both = presets.FAST.with_(
        iterations=2, prior_maps=("base_color", "emissive"), max_prior_scale=None
    )
    monkeypatch.setitem(presets.PRESETS, "fast", both)
    report = upscale_asset(asset, tmp_path / "a", UpscaleOptions(preset="fast", prior="selective"))
    decided = {c["image"]: c["use_prior"] for c in report["prior_check"]}
    assert decided == {"base_color.png": True, "emissive.png": False}
    assert report["prior_init"] == ["base_color.png"] and report["prior_used"] == "selective"
    # a preset that leaves the emissive map out of prior_maps does not check it
    monkeypatch.setitem(presets.PRESETS, "fast", both.with_(prior_maps=("base_color",)))
    report = upscale_asset(asset, tmp_path / "b", UpscaleOptions(preset="fast", prior="selective"))
    assert [c["image"] for c in report["prior_check"]] == ["base_color.png"]
    assert report["prior_init"] == ["base_color.png"]


def test_a_map_too_small_to_check_is_initialised_by_the_prior(tmp_path, monkeypatch):
    import pbrsr_core.pipeline as pipeline

    real = pipeline.load_prior
    monkeypatch.setattr(
        pipeline, "load_prior", lambda n, d: BlurringPrior() if n == "blurring" else real(n, d)
    )
    monkeypatch.setitem(presets.PRESETS, "fast", presets.FAST.with_(iterations=1))
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": _texture(8)})
    report = upscale_asset(asset, tmp_path / "o", UpscaleOptions(preset="fast", prior="blurring"))
    (check,) = report["prior_check"]
    assert check["use_prior"] and "prior_db" not in check and "16 texels" in check["note"]
    assert report["prior_init"] == ["base_color.png"] and report["prior_used"] == "blurring"


class FirstChannelOracle(BlurringPrior):
    """Perfect on the first channel of the one image it was given, upscaled from one scale
    down (which reaches it as a greyscale image, as a data map's channels do), the blurring
    prior on everything else."""

    name = "first-channel"

    def __init__(self, hr: np.ndarray):
        super().__init__()
        self.full = np.ascontiguousarray(hr[..., :3])
        self.hr = torch.from_numpy(self.full[..., 0].copy())

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        out = super()._forward(x, scale)
        small = torch.from_numpy(np.clip(degrade_image(self.full, scale)[..., 0], 0, 1))
        for i, img in enumerate(x):
            if img.shape[-2:] == small.shape and torch.allclose(
                img, small.expand_as(img), atol=1e-6
            ):
                out[i] = self.hr
        return out


def test_data_map_channels_are_decided_one_by_one():
    from pbrsr_core.prior.selfcheck import merge_channels

    orm = _texture(96, seed=3)
    check = prior_self_check(FirstChannelOracle(orm), orm, 4, "data")
    assert check["channels"] == [True, False, False] and check["use_prior"]
    # a colour map is decided as a whole (here the blurred channels outweigh the exact one)
    colour = prior_self_check(FirstChannelOracle(orm), orm, 4, "colour")
    assert len(colour["channels"]) == 1
    a, b = np.zeros((4, 4, 3), np.float32), np.ones((4, 4, 3), np.float32)
    merged = merge_channels(a, b, [True, False, True])
    assert merged[..., 0].max() == 0 and merged[..., 1].min() == 1 and merged[..., 2].max() == 0
    assert merge_channels(a, b, [False]) is b


def test_presets_name_the_maps_and_orm_channels_the_prior_may_initialise():
    from types import SimpleNamespace

    from pbrsr_core.initial_maps import prior_channels

    def img(roles, channels=3):
        return SimpleNamespace(roles=set(roles), pixels=np.zeros((4, 4, channels), np.float32))

    paper = presets.PAPER
    cpu = presets.BALANCED.with_(prior_maps=("base_color", "normal", "occlusion", "roughness"))
    # occlusion R and roughness G from the prior, metallic B from bicubic
    assert prior_channels(img({"occlusion", "metallic_roughness"}), cpu) == [True, True, False]
    assert prior_channels(img({"metallic_roughness"}), cpu) == [False, True, False]
    assert prior_channels(img({"occlusion"}, 1), cpu) == [True]
    assert prior_channels(img({"normal"}), cpu) == [True]
    assert prior_channels(img({"emissive"}), cpu) == [False]
    # the paper: albedo and emissive only
    assert prior_channels(img({"normal"}), paper) == [False]
    assert prior_channels(img({"emissive"}), paper) == [True]
    assert prior_channels(img({"occlusion", "metallic_roughness"}), paper) == [False] * 3
    # the CPU presets: every map (each then self-checked)
    orm = img({"occlusion", "metallic_roughness"})
    assert prior_channels(orm, presets.BALANCED) == [True] * 3
    assert prior_channels(img({"emissive"}), presets.FAST) == [True]
    # KHR_materials_* data maps: the channels their extensions read (alpha is never the prior's)
    assert prior_channels(img({"clearcoat"}), presets.BALANCED) == [True, False, False]
    both = img({"clearcoat", "clearcoat_roughness"})
    assert prior_channels(both, presets.BALANCED) == [True, True, False]
    assert prior_channels(img({"thickness", "transmission"}), presets.BALANCED) == [True] * 2 + [
        False
    ]
    assert prior_channels(img({"specular"}, 4), presets.BALANCED) == [False] * 3
    assert prior_channels(img({"anisotropy"}), presets.BALANCED) == [True] * 3
    assert prior_channels(img({"clearcoat"}, 1), presets.BALANCED) == [True]
    assert prior_channels(img({"sheen_roughness"}, 2), presets.BALANCED) == [False]
    assert prior_channels(img({"clearcoat"}), paper) == [False] * 3
    assert prior_channels(img({"sheen_color"}), presets.BALANCED) == [True]
    # an image a core map shares with a KHR map: the channels of both
    shared = img({"occlusion", "clearcoat_roughness"})
    assert prior_channels(shared, presets.BALANCED) == [True, True, False]
    assert prior_channels(shared, cpu) == [True, True, False]
    assert (
        prior_channels(img({"occlusion", "specular"}, 4), presets.BALANCED) == [True] + [False] * 2
    )
    assert prior_channels(shared, paper) == [False] * 3


class Offering(Prior):
    """A prior that offers two others for every map kind, as a texture set offers its own
    network and its fallback; called directly, it runs the first."""

    name = "offering"
    scales = (4,)
    back_project = False

    def __init__(self, first: Prior, second: Prior):
        super().__init__()
        self.first, self.second = first, second

    def candidates(self, kind: str, scale: int) -> list[Prior]:
        return [self.first, self.second]

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        return self.first._forward(x, scale)


class NearestSelective(SelectivePrior):
    """Perfect on the self-check of one LR map, nearest-neighbour upscaling elsewhere."""

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        if x.shape[1:] == self.small.shape and torch.allclose(x[0], self.small, atol=1e-6):
            return self.hr[None].clone()
        return F.interpolate(x, scale_factor=scale, mode="nearest")


def test_the_check_keeps_the_candidate_that_reconstructs_the_map_best():
    tex = _texture()
    for order in ((BlurringPrior(), OraclePrior(tex)), (OraclePrior(tex), BlurringPrior())):
        check = prior_self_check(Offering(*order), tex, 4)
        assert check["priors"] == ["oracle"] and check["prior_db"] == 100.0 and check["use_prior"]
        assert set(check["candidates"]) == {"oracle", "blurring"}
        assert check["candidates"]["blurring"] < check["bicubic_db"]
    # neither candidate beats bicubic: the better one is named, and the map stays bicubic
    lost = prior_self_check(Offering(BlurringPrior(), BlurringPrior()), tex, 4)
    assert not lost["use_prior"] and lost["priors"] == ["blurring"]
    # a data map: each channel's own best candidate, used where it beats bicubic
    orm = _texture(96, seed=3)
    check = prior_self_check(Offering(BlurringPrior(), FirstChannelOracle(orm)), orm, 4, "data")
    assert check["priors"][0] == "first-channel" and check["channels"] == [True, False, False]


def test_direct_and_the_presets_upscale_each_map_with_the_candidate_the_check_chose(
    tmp_path, monkeypatch
):
    import pbrsr_core.pipeline as pipeline

    albedo = _texture(64, seed=4)
    asset = make_quad_asset(tmp_path / "q.gltf", {"base_color": albedo})
    lr = np.asarray(load_asset(asset).images[0].pixels, np.float32)
    sharp = NearestSelective(lr)
    priors = {
        "offering": Offering(BlurringPrior(), sharp),
        "selective": sharp,
        "blurring": BlurringPrior(),
        "blurs": Offering(BlurringPrior(), BlurringPrior()),
    }
    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: priors.get(n) or real(n, d))

    runs = iter(range(100))

    def albedo_out(prior: str, **kw) -> tuple[np.ndarray, dict]:
        out = tmp_path / f"run{next(runs)}"
        report = upscale_asset(asset, out, UpscaleOptions(prior=prior, **kw))
        return load_asset(next(out.glob("*.gltf"))).images[0].pixels, report

    picked, report = albedo_out("offering", method="direct")
    assert _made_by(report, "base_color.png") == ["selective"]
    assert np.array_equal(picked, albedo_out("selective", method="direct")[0])
    assert not np.array_equal(picked, albedo_out("blurring", method="direct")[0])
    # where no candidate beats bicubic one scale down, direct keeps bicubic's upscale
    kept, report = albedo_out("blurs", method="direct")
    assert _made_by(report, "base_color.png") == ["bicubic"]
    assert np.array_equal(kept, albedo_out("blurs", method="bicubic")[0])
    # a single-candidate prior upscales every map in direct, checked for its gain alone
    report = albedo_out("selective", method="direct")[1]
    (check,) = report["prior_check"]
    assert "only candidate" in check["note"] and check["gains"] == [1.0]  # perfect: no gain
    assert _made_by(report, "base_color.png") == ["selective"]
    monkeypatch.setitem(presets.PRESETS, "fast", presets.FAST.with_(max_prior_scale=None))
    picked, report = albedo_out("offering", preset="fast")
    (check,) = report["prior_check"]
    assert check["priors"] == ["selective"] and check["use_prior"]
    assert np.array_equal(picked, albedo_out("selective", preset="fast")[0])


class ChannelOracle(BlurringPrior):
    """Perfect on channel ``c`` of the check's crop of one map (it knows the HR crop that
    check degraded; a data map reaches a prior channel by channel, each a greyscale image),
    the blurring prior on the check's other channels; off the check, ``c / 4`` everywhere, so
    its output shows which prior made which channel."""

    scales = (4,)  # knows the x4 check's crop, as SelectivePrior

    def __init__(self, lr_map: np.ndarray, c: int, scale: int = 4):
        super().__init__()
        self.name, self.c = f"channel-{c}", c
        self.small = torch.from_numpy(degrade_image(lr_map[..., :3], scale)).permute(2, 0, 1)
        self.hr = torch.from_numpy(np.ascontiguousarray(lr_map[..., :3])).permute(2, 0, 1)

    def _forward(self, x: torch.Tensor, scale: int) -> torch.Tensor:
        out = super()._forward(x, scale)
        for i, img in enumerate(x):
            if img.shape != self.small.shape:  # off the check
                out[i] = self.c / 4
            elif torch.allclose(img, self.small[self.c].expand_as(img), atol=1e-6):
                out[i] = self.hr[self.c]
        return out


def _pbrsr_and_direct(asset, offering, tmp_path, monkeypatch):
    """(method, (report, the output's only image inside an 8-texel border)) for PBR-SR's fast
    preset at the full scale and for direct, each run with ``offering`` as its prior."""
    import pbrsr_core.pipeline as pipeline

    real = pipeline.load_prior
    monkeypatch.setattr(pipeline, "load_prior", lambda n, d: offering if n == "o" else real(n, d))
    monkeypatch.setitem(presets.PRESETS, "fast", presets.FAST.with_(max_prior_scale=None))
    for method in ("pbrsr", "direct"):
        out = tmp_path / method
        report = upscale_asset(asset, out, UpscaleOptions(prior="o", preset="fast", method=method))
        yield method, (report, load_asset(next(out.glob("*.gltf"))).images[0].pixels[8:-8, 8:-8])


def test_each_channel_of_a_packed_map_comes_from_the_candidate_that_won_it(tmp_path, monkeypatch):
    """Roughness (G) and metallic (B) in one image: the check gives G to one candidate and B
    to the other, and the init (PBR-SR's and direct's) takes each channel from its own; R,
    which no material reads, runs no prior: bicubic's."""
    mr = _texture(64, seed=5)
    asset = make_quad_asset(tmp_path / "q.gltf", {"metallic_roughness": mr})
    lr = np.asarray(load_asset(asset).images[0].pixels, np.float32)
    offering = Offering(ChannelOracle(lr, 2), ChannelOracle(lr, 1))
    check = prior_self_check(offering, lr, 4, "data")
    assert check["priors"][1:] == ["channel-1", "channel-2"]
    assert check["channels"][1:] == [True, True]
    for method, (report, inner) in _pbrsr_and_direct(asset, offering, tmp_path, monkeypatch):
        assert np.allclose(inner[..., 1], 0.25, atol=1 / 255)  # channel-1's off-check output
        assert np.allclose(inner[..., 2], 0.5, atol=1 / 255)  # channel-2's
        assert not np.allclose(inner[..., 0], 0.25, atol=0.05)  # no prior's
        assert not np.allclose(inner[..., 0], 0.5, atol=0.05)
        made_by = _made_by(report, "metallic_roughness.png")
        if method == "pbrsr":
            (c,) = report["prior_check"]
            assert c["channels"] == [False, True, True]
            assert made_by[0] == "bicubic" and "channel-1" in made_by[1]
            assert "channel-2" in made_by[2]
        else:
            assert made_by == ["bicubic", "channel-1", "channel-2"]
            (c,) = report["prior_check"]  # what direct decided on, as the presets report it
            assert c["image"] == "metallic_roughness.png" and c["margins"] == check["margins"]
            assert c["priors"] == check["priors"] and c["channels"] == check["channels"]


def test_a_flat_channel_keeps_bicubic_even_where_a_network_wins_the_check(tmp_path, monkeypatch):
    """Metallic (B) that is one value plus 8-bit noise: a candidate perfect on it one scale
    down still leaves it to bicubic (nothing to sharpen); roughness (G) keeps its
    candidate. PBR-SR's blend and direct alike."""
    from pbrsr_core.prior.selfcheck import FLAT_STD

    mr = _texture(64, seed=5)
    noise = np.random.default_rng(0).normal(0.0, 0.4 / 255, mr.shape[:2])
    mr[..., 2] = (0.3 + noise).astype(np.float32)
    asset = make_quad_asset(tmp_path / "q.gltf", {"metallic_roughness": mr})
    lr = np.asarray(load_asset(asset).images[0].pixels, np.float32)
    assert lr[..., 2].std() < FLAT_STD < lr[..., 1].std()
    offering = Offering(ChannelOracle(lr, 2), ChannelOracle(lr, 1))
    check = prior_self_check(offering, lr, 4, "data")
    assert check["priors"][1:] == ["channel-1", "channel-2"] and check["margins"][2] > 10
    assert check["flat"] == [False, False, True]
    assert check["channels"][1:] == [True, False]
    for method, (report, inner) in _pbrsr_and_direct(asset, offering, tmp_path, monkeypatch):
        assert np.allclose(inner[..., 1], 0.25, atol=1 / 255)  # channel-1's off-check output
        assert np.allclose(inner[..., 2], 0.3, atol=4 / 255)  # bicubic's, not channel-2's 0.5
        if method == "pbrsr":
            (c,) = report["prior_check"]
            assert c["channels"] == [False, True, False] and "blend" in c
            assert c["blend"]["margins"][2] is None  # not blended
        made_by = _made_by(report, "metallic_roughness.png")
        assert made_by[0] == "bicubic" and "channel-1" in made_by[1]
        assert made_by[2] == "bicubic (flat)"


def test_one_texel_far_from_the_rest_is_a_feature_not_flatness():
    """Metallic at 0.3 but for one texel of a 128² map: 0.3 + 0.4 (an LED, a sparse mask) is
    under a level RMS, yet no noise puts a texel that far off, so it is checked; 0.3 + 12
    levels, within the peak, stays flat. A deviation just past the peak is not flat."""
    from pbrsr_core.prior import load_prior
    from pbrsr_core.prior.selfcheck import FLAT_PEAK, FLAT_STD

    prior = load_prior("bicubic", "cpu")
    lr = _texture(128, seed=2)
    for offset, flat in ((0.4, False), (12 / 255, True), (FLAT_PEAK + 2 / 255, False)):
        lr[..., 2] = 0.3
        lr[64, 64, 2] = 0.3 + offset
        assert lr[..., 2].std() < FLAT_STD
        check = prior_self_check(prior, lr, 4, "data")
        assert check["flat"] == [False, False, flat]
        metallic = check["spread"][2]  # as the report gives it, in 8-bit levels
        assert metallic["peak"] == pytest.approx(offset * 255, abs=0.1)
        assert metallic["rms"][0] < metallic["floor"][0] == 1.0


def test_a_jpeg_maps_noise_raises_the_flat_floor(tmp_path):
    """A metallic that varies by 1.5 levels is not flat; stored as a JPEG whose deblocking
    takes out 1.2 levels of noise, variation of that size is the file's: flat. The pipeline's
    checks see the stored map less the deblocked one; a map that was not deblocked none."""
    from pbrsr_core.initial_maps import self_checks
    from pbrsr_core.prior import load_prior
    from pbrsr_core.progress import StageTimer

    rng = np.random.default_rng(3)
    mr = _texture(64, seed=5)
    mr[..., 2] = 0.3 + rng.normal(0.0, 1.5 / 255, mr.shape[:2])
    asset = load_asset(make_quad_asset(tmp_path / "q.gltf", {"metallic_roughness": mr}))
    stored = asset.images[0].pixels
    jpeg_noise = np.zeros_like(stored)
    jpeg_noise[..., 2] = rng.normal(0.0, 1.2 / 255, stored.shape[:2])
    deblocked = stored - jpeg_noise
    prior = load_prior("bicubic", "cpu")
    assert prior_self_check(prior, deblocked, 4, "data")["flat"] == [False, False, False]
    check = prior_self_check(prior, deblocked, 4, "data", stored=stored)
    assert check["flat"] == [False, False, True]

    def checks(lr_pixels):
        found = self_checks(asset, asset.images, prior, lr_pixels, 4, ("data",), None,
                            StageTimer(), None)  # fmt: skip
        return found[0]["flat"]

    assert checks({0: deblocked}) == [False, False, True]
    assert checks({0: stored}) == [False, False, False]  # not deblocked: the 8-bit floor


def test_a_jpeg_maps_check_can_model_its_file_one_scale_down(tmp_path):
    """With ``storage`` (``check_storage``) the crop one scale down goes through the map's own
    file's compression (its tables and chroma sampling), and its deblocking where the run
    deblocked the map, before the candidates see it; a map stored losslessly, or a check
    without it, sees the protocol's crop."""
    from pbrsr_core.asset import make_test_asset
    from pbrsr_core.asset.jpeg import stored_as
    from pbrsr_core.degrade import degrade_asset
    from pbrsr_core.initial_maps import self_checks
    from pbrsr_core.prior import load_prior
    from pbrsr_core.progress import StageTimer

    src = make_test_asset(tmp_path / "t.glb", size=512)  # its RGBA colour map stays PNG
    asset = load_asset(degrade_asset(src, tmp_path / "lr.glb", 2, image_format="jpeg:80:420")[0])
    prior = load_prior("bicubic", "cpu")
    images = [im for im in asset.images if im.roles and im.channels >= 3]
    assert any(im.jpeg is not None for im in images) and any(im.jpeg is None for im in images)
    deblocked = {im.index: (im.pixels if im.jpeg is None else im.pixels * 0.5) for im in images}
    modelled = 0
    for lr_pixels in (deblocked, {im.index: im.pixels for im in images}):
        for storage in (False, True):
            kept: dict = {}
            self_checks(asset, images, prior, lr_pixels, 4, ("data", "colour"), None,
                        StageTimer(), None, kept, storage)  # fmt: skip
            for im in images:
                if im.index not in kept:  # colour maps keep nothing
                    continue
                small = degrade_image(kept[im.index]["crop"], 4)
                if storage and im.jpeg is not None:
                    as_read = lr_pixels[im.index] is im.pixels
                    plain = small
                    small = stored_as(small, im.jpeg, deblocked=not as_read)
                    assert np.abs(small - plain).max() > 1 / 255
                    modelled += 1
                np.testing.assert_array_equal(kept[im.index]["small"], small)
    assert modelled >= 2  # a JPEG data map, deblocked and as read
