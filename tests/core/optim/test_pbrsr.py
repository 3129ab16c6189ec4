"""End-to-end PBR-SR optimisation on procedural scenes with the real renderer.

The "oracle" runs use ``reference_maps``: the pseudo-GT of each view is the render of known HR
ground-truth maps, so the optimiser must recover the HR albedo (better than bicubic)."""

from __future__ import annotations

import math
import time

import pytest
import torch
import torch.nn.functional as F

from pbrsr_core.asset.model import Material, TextureRef
from pbrsr_core.errors import Cancelled
from pbrsr_core.optim.losses import psnr
from pbrsr_core.optim.pbrsr import optimize_pbrsr
from pbrsr_core.optim.presets import get_preset
from pbrsr_core.prior.bicubic import BicubicPrior
from pbrsr_core.render import camera as cam
from pbrsr_core.render import shapes
from pbrsr_core.render.light import EnvLight

CPU = torch.device("cpu")


def _pattern(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """(h, w, 3) smooth-but-detailed colours in [0.1, 0.9]."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    ph = float(seed)
    return torch.stack(
        [
            0.5 + 0.4 * torch.sin(xx * 25 + ph),
            0.5 + 0.4 * torch.cos(yy * 19 + ph),
            0.5 + 0.3 * torch.sin((xx + yy) * 31 + ph),
        ],
        -1,
    )


def _down(t: torch.Tensor, s: int) -> torch.Tensor:
    return F.avg_pool2d(t.permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)


def _bicubic(t: torch.Tensor, s: int) -> torch.Tensor:
    up = F.interpolate(t.permute(2, 0, 1)[None], scale_factor=s, mode="bicubic")
    return up[0].permute(1, 2, 0).clamp(0, 1)


def _front_camera(res: int, fov: float = 30.0) -> cam.Camera:
    return cam.look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov, (res, res))


def _quad_scene():
    mesh = shapes.quad(1.0, n_sub=2)
    mats = [
        Material(index=0, base_color=TextureRef(image=0), metallic_factor=0.0, roughness_factor=0.9)
    ]
    return mesh, mats


def _optimize_base_color(mesh, mats, lr, init, **kw):
    """``optimize_pbrsr`` of one base-colour map (image 0) on the CPU, under a uniform white
    light unless ``light`` is given."""
    kw.setdefault("light", EnvLight.uniform(1.0))
    return optimize_pbrsr(mesh, mats, {0: lr}, {0: init}, {0: {"base_color"}}, device=CPU, **kw)


def _oracle_on_quad(gt, s, **kw):
    """The oracle run on the quad: the LR map is ``gt`` averaged down by ``s``, the init its
    bicubic upscaling, the pseudo-GT the render of ``gt``. -> (result, init)"""
    lr = _down(gt, s)
    init = _bicubic(lr, s)
    mesh, mats = _quad_scene()
    res = _optimize_base_color(
        mesh, mats, lr, init, scale=s, prior=None, reference_maps={0: gt}, **kw
    )
    return res, init


def _cfg(**kw):
    base = dict(
        iterations=60, lr=1e-2, batch_views=1, log_every=10, mask_unseen=True, lambda_pix=100.0
    )
    base.update(kw)
    return get_preset("fast").with_(**base)


def test_recovers_hr_albedo_better_than_bicubic():
    s, h = 4, 48
    gt = _pattern(h, h)
    t0 = time.perf_counter()
    res, init = _oracle_on_quad(
        gt, s, config=_cfg(iterations=40, lr=1.5e-2), cameras=[_front_camera(72)]
    )
    elapsed = time.perf_counter() - t0
    m = res.seen_masks[0]
    assert m.float().mean() > 0.9 and res.coverage[0] > 0.9
    before, after = psnr(init[m], gt[m]), psnr(res.maps[0][m], gt[m])
    assert after > before + 6.0, (before, after)
    out = res.maps[0]
    assert out.shape == init.shape and torch.isfinite(out).all()
    assert out.min() >= 0 and out.max() <= 1
    assert elapsed < 300  # ~5 s on an idle 2-core CPU; generous: the CI box is shared
    # bookkeeping the pipeline reports
    assert set(res.timings) == {"gbuffers", "pseudo_gt", "optimize"}
    assert res.history[-1]["it"] == 40 and all(
        math.isfinite(v) for e in res.history for v in e["losses"].values()
    )
    assert res.history[-1]["losses"]["pbr"] < res.history[0]["losses"]["pbr"] + 1e-6
    assert res.consistency_psnr["0:base_color"] > 30
    rep = res.report()
    assert rep["num_views"] == 1 and rep["config"]["iterations"] == 40


def test_same_seed_same_maps_in_both_sampling_modes():
    s = 2
    gt = _pattern(16, 24, seed=1)
    cams = [_front_camera(48), cam.look_at((0.6, 0.3, 1.9), fov_deg=30.0, resolution=(48, 48))]
    for mode in ("views", "pixels"):
        cfg = _cfg(iterations=8, sampling=mode, pixels_per_step=500)
        runs = [
            _oracle_on_quad(gt, s, light=EnvLight.uniform(0.8), config=cfg, cameras=cams, seed=3)
            for _ in range(2)
        ]
        assert torch.equal(runs[0][0].maps[0], runs[1][0].maps[0]), mode
        assert not torch.equal(runs[0][0].maps[0], runs[0][1])


def test_hard_cases_stay_finite_and_in_range():
    """Roughness 0/1, metallic 0/1, zero-length normals, a 1x1 and a non-square map."""
    s = 2
    mesh = shapes.quad(1.0, n_sub=1)
    mats = [
        Material(
            index=0,
            base_color=TextureRef(image=0),
            metallic_roughness=TextureRef(image=1),
            occlusion=TextureRef(image=1),
            normal=TextureRef(image=2),
        )
    ]
    lr_c = torch.rand(3, 5, 4)  # non-square, RGBA
    orm = torch.zeros(1, 1, 3)
    orm[..., 1] = 0.0  # roughness 0
    orm[..., 2] = 1.0  # metallic 1
    nrm = torch.full((3, 5, 3), 0.5)  # decodes to zero-length normals
    nrm[0, 0] = torch.tensor([1.0, 1.0, 0.0])  # z < 0 after decoding
    gt_orm = torch.zeros(2, 2, 3)
    gt_orm[..., 1] = torch.tensor([[0.0, 1.0], [1.0, 0.0]])
    gt_orm[..., 2] = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    lr_maps = {0: lr_c, 1: orm, 2: nrm}
    init = {0: _bicubic(lr_c, s), 1: _bicubic(orm, s), 2: _bicubic(nrm, s)}
    ref = {0: _bicubic(torch.rand(3, 5, 4), s), 1: gt_orm, 2: init[2].clone()}
    res = optimize_pbrsr(
        mesh,
        mats,
        lr_maps,
        init,
        {0: {"base_color"}, 1: {"metallic_roughness", "occlusion"}, 2: {"normal"}},
        scale=s,
        prior=None,
        light=EnvLight.procedural(),
        config=_cfg(iterations=6),
        device=CPU,
        cameras=[_front_camera(32)],
        reference_maps=ref,
    )
    for i, t in res.maps.items():
        assert torch.isfinite(t).all(), i
        assert t.min() >= 0 and t.max() <= 1, i
    n = res.maps[2] * 2 - 1
    assert torch.allclose(n.norm(dim=-1), torch.ones(n.shape[:2]), atol=1e-4)
    assert (n[..., 2] > 0).all()
    assert torch.equal(res.maps[0][..., 3], init[0][..., 3])  # alpha kept
    assert all(math.isfinite(v) for e in res.history for v in e["losses"].values())
    assert set(res.optimized[1]) == {"occlusion", "roughness", "metallic"}


def test_unseen_texels_keep_their_init():
    s = 2
    # a narrow view of the quad's centre: the border texels are never seen
    c = cam.look_at((0.0, 0.0, 1.0), fov_deg=20.0, resolution=(64, 64))
    res, init = _oracle_on_quad(_pattern(32, 32), s, config=_cfg(iterations=10), cameras=[c])
    seen = res.seen_masks[0]
    assert 0.05 < float(seen.float().mean()) < 0.9
    assert torch.equal(res.maps[0][~seen], init[~seen])
    assert not torch.equal(res.maps[0][seen], init[seen])
    assert res.coverage[0] < 0.9


class _CountingPrior(BicubicPrior):
    """The real bicubic prior, counting its calls."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def upscale(self, x, scale, **kw):
        self.calls += 1
        return super().upscale(x, scale, **kw)


def test_pseudo_gt_is_cached_on_disk_and_reused(tmp_path):
    from pbrsr_core.optim import pseudo_gt

    s = 2
    lr = _down(_pattern(16, 16), s)
    init = _bicubic(lr, s)
    mesh, mats = _quad_scene()
    cams = [_front_camera(32), cam.look_at((0.5, 0.0, 1.9), fov_deg=30.0, resolution=(32, 32))]
    kw = dict(scale=s, config=_cfg(iterations=3), cameras=cams, cache_dir=tmp_path)
    pseudo_gt.MEMORY_CACHE.clear()
    p1 = _CountingPrior()
    r1 = _optimize_base_color(mesh, mats, lr, init, prior=p1, **kw)
    assert p1.calls == 2 and len(list(tmp_path.glob("*.npy"))) == 2
    pseudo_gt.MEMORY_CACHE.clear()  # a retried job in a new process: only the disk cache
    p2 = _CountingPrior()
    r2 = _optimize_base_color(mesh, mats, lr, init, prior=p2, **kw)
    assert p2.calls == 0
    assert torch.equal(r1.maps[0], r2.maps[0])
    # other init maps: a different key, recomputed
    p3 = _CountingPrior()
    _optimize_base_color(mesh, mats, lr, init * 0.9, prior=p3, **kw)
    assert p3.calls == 2


def test_maps_with_rate_zero_keep_their_init_and_cost_no_prior_calls(tmp_path):
    """map_lr 0 (the CPU presets' emissive): the map is rendered as its init and never
    differentiated, the others still optimise; with nothing to optimise no pseudo-GT is made."""
    s = 2
    lr_c, lr_e = _down(_pattern(16, 16), s), _down(_pattern(16, 16, seed=3), s) * 0.5
    init = {0: _bicubic(lr_c, s), 1: _bicubic(lr_e, s)}
    mesh = shapes.quad(1.0, n_sub=2)
    mats = [
        Material(
            index=0,
            base_color=TextureRef(image=0),
            emissive=TextureRef(image=1),
            emissive_factor=(1.0, 1.0, 1.0),
            metallic_factor=0.0,
            roughness_factor=0.9,
        )
    ]
    kw = dict(
        scale=s,
        light=EnvLight.uniform(1.0),
        device=CPU,
        cameras=[_front_camera(32)],
        cache_dir=tmp_path,
    )
    lrs, roles = {0: lr_c, 1: lr_e}, {0: {"base_color"}, 1: {"emissive"}}
    frozen = _cfg(iterations=4, map_lr={"emissive": 0.0})
    prior = _CountingPrior()
    res = optimize_pbrsr(mesh, mats, lrs, init, roles, prior=prior, config=frozen, **kw)
    assert torch.equal(res.maps[1], init[1])
    assert not torch.equal(res.maps[0], init[0])
    assert res.optimized == {0: ["base_color"], 1: []} and prior.calls == 1
    nothing = frozen.with_(map_lr={"emissive": 0.0, "base_color": 0.0})
    prior = _CountingPrior()
    res = optimize_pbrsr(mesh, mats, lrs, init, roles, prior=prior, config=nothing, **kw)
    assert all(torch.equal(res.maps[i], init[i]) for i in (0, 1))
    assert prior.calls == 0 and res.history == []
    # no iterations: the init as it is; no view chosen or rasterised, no pseudo-GT
    prior, events = _CountingPrior(), []
    res = optimize_pbrsr(
        mesh,
        mats,
        lrs,
        init,
        roles,
        prior=prior,
        config=frozen.with_(iterations=0),
        progress=events.append,
        **{k: v for k, v in kw.items() if k != "cameras"},
    )
    assert torch.equal(res.maps[0], init[0]) and prior.calls == 0
    assert res.views == [] and res.timings == {} and events == []
    assert set(res.consistency_psnr) == {"0:base_color", "1:emissive"}
    assert res.report()["optimized_maps"] == {"0": [], "1": []}


def test_coverage_views_on_a_sphere_and_progress_cancel():
    s = 2
    mesh = shapes.uv_sphere(8, 16, radius=0.5)
    mats = [Material(index=0, base_color=TextureRef(image=0), metallic_factor=0.0)]
    lr = _down(_pattern(16, 32), s)
    init = _bicubic(lr, s)
    cfg = get_preset("fast").with_(
        n_candidates=12, max_views=6, max_render_res=64, iterations=4, log_every=1
    )
    events = []
    res = _optimize_base_color(
        mesh,
        mats,
        lr,
        init,
        scale=s,
        prior=BicubicPrior(),
        config=cfg,
        progress=events.append,
    )
    assert 2 <= len(res.views) <= 6
    assert res.coverage[0] > 0.9  # a few well-chosen views see (almost) the whole sphere
    assert res.render_res % s == 0 and res.render_res <= 64
    stages = [e.stage for e in events]
    assert {"gbuffers", "pseudo_gt", "optimize"} <= set(stages)
    opt = [e for e in events if e.stage == "optimize"]
    assert opt[-1].step == 4 and opt[-1].metrics and opt[-1].eta_s is not None

    def cancel(p):
        if p.stage == "optimize" and p.step >= 2:
            raise Cancelled("stop")

    with pytest.raises(Cancelled):
        _optimize_base_color(
            mesh, mats, lr, init, scale=s, prior=BicubicPrior(), config=cfg, progress=cancel
        )


def test_covered_box_in_lr_pixels_with_context():
    from pbrsr_core.optim.targets import covered_box

    assert covered_box(torch.zeros(0, dtype=torch.long), (16, 16), 4, context=16) is None
    pix = torch.tensor([5 * 16 + 7])  # row 5, column 7 of a 16 x 16 image
    assert covered_box(pix, (16, 16), 4, context=0) == (1, 2, 1, 2)
    assert covered_box(pix, (16, 16), 4, context=1) == (0, 3, 0, 3)
    assert covered_box(pix, (16, 16), 4, context=100) == (0, 4, 0, 4)
    corners = torch.tensor([0, 16 * 16 - 1])
    assert covered_box(corners, (16, 16), 1, context=0) == (0, 16, 0, 16)


class _ShapeRecordingPrior(_CountingPrior):
    def upscale(self, x, scale, **kw):
        self.shapes = [*getattr(self, "shapes", []), tuple(x.shape[2:])]
        return super().upscale(x, scale, **kw)


@pytest.mark.parametrize("lr_render", ["supersample", "raster"])
def test_prior_sees_only_the_covered_box_and_covered_pixels_keep_their_target(
    tmp_path, monkeypatch, lr_render
):
    """The pseudo-GT made from the box around the covered pixels equals the one made from the
    whole LR render at every covered pixel (bicubic prior: its support is 2 LR pixels, well
    inside the context), and the prior is run on fewer pixels."""
    import numpy as np

    from pbrsr_core.optim import pseudo_gt
    from pbrsr_core.optim import targets as target_mod
    from pbrsr_core.render.raster import coverage

    s = 2
    lr = _down(_pattern(32, 32), s)
    mesh, mats = _quad_scene()
    camera = cam.look_at((0.0, 0.0, 8.0), fov_deg=30.0, resolution=(128, 128))
    targets = {}
    assert target_mod.PRIOR_CONTEXT == 16
    for context in (16, 10**6):
        monkeypatch.setattr(target_mod, "PRIOR_CONTEXT", context)
        pseudo_gt.MEMORY_CACHE.clear()
        prior = _ShapeRecordingPrior()
        cache = tmp_path / f"c{context}"
        _optimize_base_color(
            mesh,
            mats,
            lr,
            _bicubic(lr, s),
            prior=prior,
            scale=s,
            cameras=[camera],
            config=_cfg(iterations=1, lr_render=lr_render, target="detail"),
            cache_dir=cache,
        )
        (f,) = cache.glob("*.npy")
        targets[context] = np.load(f).reshape(-1, 3)
        (shape,) = prior.shapes
        if context == 16:
            assert shape[0] < 64 and shape[1] < 64  # a crop of the 64 x 64 LR render
        else:
            assert shape == (64, 64)
    tri, _, _ = coverage(mesh, camera)
    covered = (tri >= 0).numpy()
    assert 0.02 < covered.mean() < 0.5
    cropped, full = targets[16], targets[10**6]
    np.testing.assert_array_equal(cropped[covered], full[covered])
