"""Optimiser pieces that need no renderer: map groups, projection, island dilation, presets,
the pseudo-GT cache, view-selection geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pbrsr_core.errors import InvalidOptions
from pbrsr_core.optim import pseudo_gt
from pbrsr_core.optim.groups import map_groups
from pbrsr_core.optim.presets import MAP_NAMES, PRESETS, get_preset
from pbrsr_core.optim.schedule import channel_lr
from pbrsr_core.optim.views import fibonacci_directions, texel_density_resolution
from pbrsr_core.optim.whole_map import dilate_islands, project_


def test_map_groups_follow_gltf_packing():
    cfg = get_preset("paper")
    g = {x.name: x for x in map_groups({"metallic_roughness", "occlusion"}, 3, cfg)}
    assert g["occlusion"].channels == (0,) and g["roughness"].channels == (1,)
    assert g["metallic"].channels == (2,) and g["metallic"].weight == pytest.approx(0.1)
    assert g["roughness"].weight == 1.0
    mr_only = map_groups({"metallic_roughness"}, 3, cfg)
    assert [x.name for x in mr_only] == ["roughness", "metallic"]  # R unused: not optimised
    bc = map_groups({"base_color"}, 4, cfg)
    assert bc[0].channels == (0, 1, 2)  # alpha is kept, not optimised
    assert map_groups({"base_color"}, 1, cfg)[0].channels == (0,)


def test_channel_lr_per_map():
    cfg = get_preset("paper").with_(lr=1e-3, map_lr={"metallic": 0.5, "occlusion": 0.0})
    orm = channel_lr(map_groups({"metallic_roughness", "occlusion"}, 4, cfg), 4, cfg)
    assert orm.tolist() == pytest.approx([0.0, 1e-3, 5e-4, 0.0])  # occlusion frozen, A unowned
    assert get_preset("paper").map_lr == {}  # the paper: one learning rate
    assert get_preset("balanced").map_lr == {"normal": 0.3, "emissive": 0.0}
    assert get_preset("paper").prior_maps == ("base_color", "emissive")  # paper 3.1
    assert set(get_preset("balanced").prior_maps) == set(MAP_NAMES)  # each self-checked
    with pytest.raises(InvalidOptions, match="prior_maps"):
        cfg.with_(prior_maps=("albedo",))  # glTF's name is base_color
    with pytest.raises(InvalidOptions, match="map_lr keys"):
        cfg.with_(map_lr={"albedo": 1.0})
    with pytest.raises(InvalidOptions, match="map_lr factors"):
        cfg.with_(map_lr={"normal": -1.0})


def test_project_ranges_and_normals():
    t = torch.tensor([[[1.5, -0.2, 0.5], [0.5, 0.5, 0.5]], [[0.5, 0.5, 0.0], [float("nan"), 1, 1]]])
    n = t.clone()
    project_(n, is_normal=True)
    assert torch.isfinite(n).all() and (n >= 0).all() and (n <= 1).all()
    dec = n * 2 - 1
    assert torch.allclose(dec.norm(dim=-1), torch.ones(2, 2), atol=1e-5)
    assert (dec[..., 2] > 0).all()
    assert torch.allclose(dec[0, 1], torch.tensor([0.0, 0.0, 1.0]))  # zero-length -> +z
    c = t.clone()
    project_(c, is_normal=False)
    assert (c >= 0).all() and (c <= 1).all() and float(c[0, 0, 0]) == 1.0


def test_dilate_islands_fills_rings_and_keeps_covered():
    m = np.zeros((7, 7), dtype=bool)
    m[3, 3] = True
    img = np.zeros((7, 7, 2), dtype=np.float32)
    img[3, 3] = (0.25, 0.75)
    out = dilate_islands(img, m, 1)
    assert out.dtype == np.float32
    assert np.allclose(out[2:5, 2:5], (0.25, 0.75))  # first ring filled
    assert np.allclose(out[0], 0.0) and np.allclose(out[:, 6], 0.0)  # beyond 1 px: untouched
    # two islands: a texel between them takes the mean of both
    m = np.zeros((1, 3), dtype=bool)
    m[0, 0] = m[0, 2] = True
    t = torch.tensor([[[0.0], [9.0], [1.0]]])
    got = dilate_islands(t, m, 4)
    assert torch.allclose(got, torch.tensor([[[0.0], [0.5], [1.0]]]))
    with pytest.raises(ValueError):
        dilate_islands(np.zeros((2, 2, 1)), np.zeros((3, 2), bool), 1)


def test_presets_paper_numbers_exact():
    p = get_preset("paper")
    assert (p.n_elev, p.n_azim, p.distance, p.fov_deg) == (15, 50, 3.25, 10.0)
    assert (p.iterations, p.batch_views, p.lr, p.render_res) == (2000, 4, 1e-4, 1024)
    assert (p.lambda_pix, p.lambda_reg, p.lambda_ssim, p.lambda_pbr, p.lambda_tv) == (
        100.0,
        0.5,
        10.0,
        10.0,
        0.5,
    )
    assert (p.w_metallic, p.w_other, p.weight_map_res, p.eval_views) == (0.1, 1.0, 64, 240)
    assert p.view_mode == "orbit" and p.sampling == "views" and p.weight_map_lr == 1e-4
    assert set(PRESETS) == {"fast", "balanced", "quality", "paper"}
    for name in ("fast", "balanced", "quality"):  # CPU presets: the paper's losses, a weaker
        q = get_preset(name)  # pixel term (the pseudo-GT of a small prior, presets.py)
        assert (q.lambda_pix, q.lambda_pbr, q.lambda_tv, q.lambda_ssim) == (1, 10, 0.5, 10)
        assert q.lambda_reg == 0.5 and q.project_lr == ("colour", "data")
    assert p.project_lr == ()  # the paper exports the optimised maps as they are
    with pytest.raises(InvalidOptions):
        get_preset("nope")
    with pytest.raises(InvalidOptions):
        p.with_(iterations=-1)
    with pytest.raises(InvalidOptions, match="blend_margin and blend_network_db"):
        p.with_(blend_network_db=-0.1)
    with pytest.raises(InvalidOptions, match="blend_pick_db"):
        p.with_(blend_pick_db=-0.1)
    assert p.with_(blend_pick_db=None).blend_pick_db is None
    with pytest.raises(InvalidOptions, match="blend_channel_db"):
        p.with_(blend_channel_db=-0.1)
    channel_rule = [n for n, q in PRESETS.items() if q.blend_channel_db == 0.1]
    assert channel_rule == ["fast", "balanced", "quality"]
    assert p.blend_channel_db is None  # the paper blends nothing


def test_pseudo_gt_cache_roundtrip(tmp_path):
    img = torch.rand(5, 4, 3)
    q = pseudo_gt.quantize(img)
    assert q.dtype == np.uint16
    back = pseudo_gt.dequantize(q, torch.device("cpu"))
    assert float((back - img).abs().max()) <= 0.5 / 65535 + 1e-7
    k1 = pseudo_gt.content_hash({"a": torch.ones(3)}, 4, "prior")
    assert k1 == pseudo_gt.content_hash({"a": torch.ones(3)}, 4, "prior")
    assert k1 != pseudo_gt.content_hash({"a": torch.ones(3) * 2}, 4, "prior")
    pseudo_gt.store_cached(k1, q, tmp_path)
    pseudo_gt.MEMORY_CACHE.clear()
    got = pseudo_gt.load_cached(k1, tmp_path)  # from disk
    assert got is not None and np.array_equal(got, q)
    (tmp_path / f"{k1}.npy").write_bytes(b"garbage")
    pseudo_gt.MEMORY_CACHE.clear()
    assert pseudo_gt.load_cached(k1, tmp_path) is None  # corrupt: recompute


def test_fibonacci_and_texel_density_rule():
    d = fibonacci_directions(50)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert abs(d.mean(axis=0)).max() < 0.05  # evenly spread
    # probe at 128 px sees 4 HR texels per pixel -> 512 px for one texel per pixel
    assert (
        texel_density_resolution(
            [4.0, 4.0], 128, texel_footprint=1.0, scale=4, min_res=64, max_res=1024
        )
        == 512
    )
    assert (
        texel_density_resolution(
            [100.0], 128, texel_footprint=1.0, scale=4, min_res=64, max_res=1000
        )
        == 1000
    )
    r = texel_density_resolution(
        [0.01], 128, texel_footprint=1.0, scale=3, min_res=64, max_res=1024
    )
    assert r % 3 == 0 and r >= 63
    assert (
        texel_density_resolution([], 128, texel_footprint=1.0, scale=4, min_res=64, max_res=256)
        == 256
    )
    assert math.isfinite(r)


def test_pad_update_keeps_the_inputs_padding_and_pads_the_change():
    from pbrsr_core.optim.whole_map import pad_update

    rng = np.random.default_rng(3)
    init = rng.random((12, 12, 3), dtype=np.float32) * 0.5 + 0.25
    m = np.zeros((12, 12), bool)
    m[4:8, 4:8] = True  # one island
    # nothing optimised: the padding the asset had (here: random texels) is kept exactly
    np.testing.assert_array_equal(pad_update(init.copy(), init, m, 2), init)
    result = init.copy()
    result[m] += 0.1  # the optimiser raised every island texel by 0.1
    out = pad_update(result, init, m, 2)
    np.testing.assert_array_equal(out[m], result[m])
    ring = np.zeros_like(m)
    ring[2:10, 2:10] = True
    ring &= ~m
    np.testing.assert_allclose(out[ring], init[ring] + 0.1, atol=1e-6)  # the change, padded
    beyond = ~(m | ring)
    np.testing.assert_array_equal(out[beyond], init[beyond])
    # clipped to [0, 1]; normal maps renormalised where padded
    assert pad_update(np.ones_like(init), init * 0 + 0.99, m, 2).max() <= 1.0
    n = np.zeros((12, 12, 3), np.float32)
    n[..., 2] = 1.0
    n_init = n * 0.5 + 0.5  # flat encoded normals
    n_res = n_init.copy()
    n_res[m, 0] = 0.8  # tilted inside the island
    n_res[m] = (n_res[m] * 2 - 1) / np.linalg.norm(
        n_res[m] * 2 - 1, axis=-1, keepdims=True
    ) / 2 + 0.5
    padded = pad_update(n_res, n_init, m, 2, normal=True)
    dec = padded[ring] * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(dec, axis=-1), 1.0, atol=1e-5)
    assert (dec[:, 2] > 0).all() and (dec[:, 0] > 0.1).all()  # tilted like the island
