"""Numerical hard cases end to end: asset files -> load -> renderer (forward and backward) ->
PBR-SR optimiser (real pseudo-GT from the bicubic prior) -> pipeline bundle. No NaN/Inf in any
render, loss or gradient; output maps finite and in range (colours/scalars in [0, 1], decoded
normals unit with z > 0)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pbrsr_core.asset import load_asset, make_quad_asset, make_test_asset, write_image
from pbrsr_core.maps import kind_of
from pbrsr_core.optim.pbrsr import optimize_pbrsr
from pbrsr_core.optim.presets import get_preset
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset
from pbrsr_core.prior.bicubic import BicubicPrior
from pbrsr_core.prior.direct import bicubic_map, normal_length
from pbrsr_core.render import camera as cam
from pbrsr_core.render import raster, shade
from pbrsr_core.render.light import EnvLight
from pbrsr_core.scene import asset_textures, make_scene

CPU = torch.device("cpu")


# ----------------------------------------------------------------------------- scenes
def _const(h: int, w: int, rgb) -> np.ndarray:
    return np.broadcast_to(np.asarray(rgb, np.float32), (h, w, len(rgb))).copy()


def _checker(h: int, w: int, lo: float, hi: float, c: int = 3) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    v = np.where(((yy // 2) + (xx // 2)) % 2 == 0, lo, hi).astype(np.float32)
    return np.repeat(v[..., None], c, axis=2)


def _hostile_normals(h: int, w: int) -> np.ndarray:
    """Encoded normal map with zero vectors, unnormalised vectors and negative z."""
    n = _const(h, w, (0.5, 0.5, 1.0))
    n[0::3] = (0.5, 0.5, 0.5)  # zero vector
    n[1::3] = (1.0, 1.0, 1.0)  # (1, 1, 1): unnormalised
    n[2::3, ::2] = (0.5, 0.5, 0.0)  # (0, 0, -1): pointing into the surface
    n[2::3, 1::2] = (0.0, 1.0, 0.2)  # negative z, off-axis
    return n


def _sun_light(sun: float = 1e5) -> EnvLight:
    env = torch.full((32, 64, 3), 0.2, dtype=torch.float64)
    env[6:8, 20:22] = sun  # a tiny, very bright sun
    return EnvLight(env, name="sun")


def _front_cameras(res: int) -> list[cam.Camera]:
    # the quad faces +z; views around the front hemisphere, one grazing
    eyes = [(0, 0, 3.0), (1.5, 0.8, 2.4), (-2.0, -0.5, 2.0), (2.95, 0.0, 0.35)]
    return [cam.look_at(e, (0, 0, 0), (0, 1, 0), 30.0, (res, res)) for e in eyes]


def _extreme_maps(h: int, w: int) -> dict[str, np.ndarray]:
    orm = _const(h, w, (1.0, 0.0, 1.0))  # roughness exactly 0, metallic exactly 1
    orm[:, w // 2 :] = (0.0, 1.0, 0.0)  # occlusion 0, roughness exactly 1, metallic 0
    return {
        "base_color": _checker(h, w, 0.0, 1.0, 4),  # albedo (and alpha) exactly 0 and 1
        "metallic_roughness": orm,
        "occlusion": orm,
        "normal": _hostile_normals(h, w),
        "emissive": _checker(h, w, 1.0, 0.0),
    }


def _edit_gltf(path: Path, fn) -> None:
    doc = json.loads(path.read_text())
    fn(doc)
    path.write_text(json.dumps(doc))


def _edit_uvs_and_drop_tangents(path: Path, fn) -> None:
    """Rewrite TEXCOORD_0 of the quad's only primitive with ``fn(uv) -> uv``; drop TANGENT so
    the loader generates tangents from the edited UVs."""
    doc = json.loads(path.read_text())
    prim = doc["meshes"][0]["primitives"][0]
    acc = doc["accessors"][prim["attributes"]["TEXCOORD_0"]]
    bv = doc["bufferViews"][acc["bufferView"]]
    binp = path.parent / doc["buffers"][bv["buffer"]]["uri"]
    data = bytearray(binp.read_bytes())
    off = bv.get("byteOffset", 0) + acc.get("byteOffset", 0)
    uv = np.frombuffer(bytes(data[off : off + 8 * acc["count"]]), "<f4").reshape(-1, 2).copy()
    tri_acc = doc["accessors"][prim["indices"]]
    tbv = doc["bufferViews"][tri_acc["bufferView"]]
    toff = tbv.get("byteOffset", 0) + tri_acc.get("byteOffset", 0)
    dt = {5123: "<u2", 5125: "<u4"}[tri_acc["componentType"]]
    nbytes = np.dtype(dt).itemsize * tri_acc["count"]
    tri = np.frombuffer(bytes(data[toff : toff + nbytes]), dt).reshape(-1, 3)
    uv = fn(uv, tri).astype("<f4")
    data[off : off + uv.nbytes] = uv.tobytes()
    binp.write_bytes(bytes(data))
    del prim["attributes"]["TANGENT"]
    path.write_text(json.dumps(doc))


def _mirror_half(uv: np.ndarray, tri: np.ndarray) -> np.ndarray:
    out = uv.copy()
    right = out[:, 0] > 0.5
    out[right, 0] = 1.0 - out[right, 0]  # mirrored UVs on the right half
    return out


def _collapse_first_triangles(uv: np.ndarray, tri: np.ndarray) -> np.ndarray:
    out = uv.copy()
    for t in tri[:3]:
        out[t] = out[t[0]]  # zero-area UV triangles
    return out


# ----------------------------------------------------------------------------- checks
def _check_render_and_grads(asset_path: Path, light: EnvLight, res: int = 40) -> dict:
    """Render a few views of the loaded asset; every output and texture gradient finite."""
    asset = load_asset(asset_path)
    for t in (asset.mesh.v_pos, asset.mesh.v_nrm, asset.mesh.v_tng):
        assert torch.isfinite(t).all()
    tn = asset.mesh.v_tng[:, :3].norm(dim=1)
    assert torch.allclose(tn, torch.ones_like(tn), atol=1e-4)
    assert set(asset.mesh.v_tng[:, 3].tolist()) <= {-1.0, 1.0}
    scene = make_scene(asset, CPU)
    tex = {k: v.clone().requires_grad_(True) for k, v in asset_textures(asset, CPU).items()}
    total = torch.zeros((), dtype=torch.float32)
    covered = 0
    for c in _front_cameras(res):
        gb = raster.rasterize(scene.mesh, c)
        covered += gb.num_pixels
        rgba = shade.shade(gb, scene.materials, tex, light)
        assert torch.isfinite(rgba).all()
        assert (rgba[:, :3] >= 0).all() and (rgba[:, 3].min() >= 0) and (rgba[:, 3].max() <= 1)
        srgb = shade.tonemap(rgba[:, :3])
        assert torch.isfinite(srgb).all() and srgb.min() >= 0 and srgb.max() <= 1
        img = shade.to_image(gb, srgb, torch.zeros(3))
        total = total + img.mean() + rgba[:, :3].clamp_max(1e3).mean() * 1e-3
    assert covered > 0
    total.backward()
    assert torch.isfinite(total)
    for k, t in tex.items():
        assert t.grad is not None, k
        assert torch.isfinite(t.grad).all(), k
    return {"asset": asset, "scene": scene}


def _check_maps(maps: dict[int, torch.Tensor], asset) -> None:
    for i, t in maps.items():
        t = torch.as_tensor(t)
        assert torch.isfinite(t).all(), i
        assert t.min() >= 0 and t.max() <= 1, i
        if kind_of(asset.images[i].roles) == "normal":
            n = t[..., :3].double() * 2 - 1
            assert torch.allclose(n.norm(dim=-1), torch.ones(n.shape[:2], dtype=n.dtype), atol=2e-3)
            assert (n[..., 2] > 0).all(), i


def _optimize(asset, scene, light, *, scale: int = 2, res: int = 32, iterations: int = 3):
    """A tiny PBR-SR run: real bicubic-prior pseudo-GT, fixed views, a few iterations."""
    prior = BicubicPrior()
    images = [img for img in asset.images if img.roles]
    lr = {img.index: asset_textures(asset, CPU)[img.index] for img in images}
    init = {
        img.index: torch.from_numpy(bicubic_map(img.pixels, kind_of(img.roles), scale))
        for img in images
    }
    # bicubic_map returns stored encoding; convert colour maps to linear like the pipeline
    from pbrsr_core.maps import encoded_to_param

    init = {i: encoded_to_param(t, kind_of(asset.images[i].roles)) for i, t in init.items()}
    config = get_preset("fast").with_(iterations=iterations, batch_views=2, lr=2e-2, log_every=1)
    res = optimize_pbrsr(
        scene.mesh,
        asset.materials,
        lr,
        init,
        {img.index: set(img.roles) for img in images},
        scale=scale,
        prior=prior,
        light=light,
        config=config,
        device=CPU,
        cameras=_front_cameras(res * scale // 2 * 2),
    )
    assert res.history
    for e in res.history:
        for name, v in e["losses"].items():
            assert math.isfinite(v), (name, v)
    _check_maps(res.maps, asset)
    return res


# ----------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def extreme_quad(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("extreme")
    return make_quad_asset(d / "q.gltf", _extreme_maps(8, 8), subdiv=2)


@pytest.mark.parametrize("light", ["procedural", "sun"])
def test_extreme_material_values_render_and_optimise_finite(extreme_quad, light):
    """Roughness/metallic/albedo/occlusion exactly 0 and 1, zero/unnormalised/negative-z
    normals, emissive 0/1, under the built-in sky and a 1e5 sun."""
    env = EnvLight.procedural() if light == "procedural" else _sun_light()
    out = _check_render_and_grads(extreme_quad, env)
    _optimize(out["asset"], out["scene"], env)


@pytest.mark.parametrize("half", [1e-4, 1e4])
def test_tiny_and_huge_meshes(tmp_path, half):
    p = make_quad_asset(tmp_path / "q.gltf", _extreme_maps(4, 4), subdiv=2, half=half)
    out = _check_render_and_grads(p, _sun_light())
    # normalised to unit size whatever the input scale
    ext = out["scene"].mesh.v_pos.max(0).values - out["scene"].mesh.v_pos.min(0).values
    assert abs(float(ext.max()) - 1.0) < 1e-3
    _optimize(out["asset"], out["scene"], EnvLight.procedural())


@pytest.mark.parametrize("edit", [_mirror_half, _collapse_first_triangles])
def test_degenerate_tangent_frames(tmp_path, edit):
    p = make_quad_asset(
        tmp_path / "q.gltf",
        {"base_color": _checker(8, 8, 0.1, 0.9), "normal": _hostile_normals(8, 8)},
        subdiv=3,
    )
    _edit_uvs_and_drop_tangents(p, edit)
    out = _check_render_and_grads(p, EnvLight.procedural())
    if edit is _mirror_half:
        assert set(out["asset"].mesh.v_tng[:, 3].tolist()) == {-1.0, 1.0}
    _optimize(out["asset"], out["scene"], EnvLight.procedural())


def test_one_by_one_textures(tmp_path):
    maps = {k: v[:1, :1].copy() for k, v in _extreme_maps(2, 2).items()}
    p = make_quad_asset(tmp_path / "q.gltf", maps, subdiv=1)
    out = _check_render_and_grads(p, _sun_light())
    res = _optimize(out["asset"], out["scene"], EnvLight.procedural(), scale=4, res=16)
    assert all(tuple(t.shape[:2]) == (4, 4) for t in res.maps.values())


def test_non_square_npot_texture(tmp_path):
    """1000x600 maps (w x h) with exact 0/1 texels: one iteration at a small render size."""
    h, w = 600, 1000
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.stack([xx % 2, yy % 2, 0.5 + 0.5 * np.sin(xx / 7)], -1).astype(np.float32)
    p = make_quad_asset(tmp_path / "q.gltf", {"base_color": base}, subdiv=1)
    out = _check_render_and_grads(p, EnvLight.procedural(), res=32)
    light = EnvLight.procedural()
    res = _optimize(out["asset"], out["scene"], light, scale=2, res=32, iterations=1)
    assert tuple(res.maps[0].shape[:2]) == (1200, 2000)


def _precision_asset(folder: Path) -> Path:
    """A quad whose base colour is a 16-bit PNG and whose ORM and normal maps are float EXRs
    (with exact 0/1 and a little out-of-range float data)."""
    h = w = 8
    maps = _extreme_maps(h, w)
    p = make_quad_asset(folder / "q.gltf", maps, subdiv=2)
    ramp = np.linspace(0, 1, h * w * 3, dtype=np.float32).reshape(h, w, 3)
    write_image(folder / "base_color.png", ramp, 16, "png")
    orm = maps["metallic_roughness"].copy()
    orm[0, 0] = (1.5, -0.25, 2.0)  # float data outside [0, 1]: must be clamped, not propagated
    write_image(folder / "metallic_roughness.exr", orm, 32, "exr")
    write_image(folder / "normal.exr", maps["normal"], 16, "exr")

    def use_exr(doc):
        for img in doc["images"]:
            if img.get("uri") in ("metallic_roughness.png", "normal.png"):
                img["uri"] = img["uri"].replace(".png", ".exr")
                img.pop("mimeType", None)

    _edit_gltf(p, use_exr)
    return p


def test_16bit_png_and_float_exr_maps(tmp_path):
    p = _precision_asset(tmp_path)
    asset = load_asset(p)
    depths = {img.name: img.bit_depth for img in asset.images}
    assert depths["base_color.png"] == 16
    assert depths["metallic_roughness.exr"] == 32
    out = _check_render_and_grads(p, _sun_light())
    _optimize(out["asset"], out["scene"], _sun_light())


def test_pipeline_pbrsr_on_hard_asset(tmp_path, monkeypatch):
    """The whole pipeline (load -> init -> PBR-SR -> dilate -> bundle with previews), method
    "pbrsr" with the "fast" preset made tiny (few views and iterations, small renders), on the
    16-bit PNG / float EXR asset with extreme values, under an EXR environment with a 1e5 sun.
    The bundle's maps are finite and valid, 16-bit stays 16-bit."""
    import pbrsr_core.optim.presets as presets

    tiny = presets.get_preset("fast").with_(
        n_candidates=8, max_views=2, max_render_res=64, iterations=3, batch_views=1
    )
    real = presets.get_preset
    monkeypatch.setattr(presets, "get_preset", lambda n: tiny if n == "fast" else real(n))
    p = _precision_asset(tmp_path / "in")
    env = torch.full((16, 32, 3), 0.3)
    env[3, 10] = 1e5
    env_path = write_image(tmp_path / "sun.exr", env.numpy(), 32, "exr")
    out = tmp_path / "out"
    options = UpscaleOptions(
        method="pbrsr", preset="fast", prior="bicubic", scale=2, envmap=str(env_path)
    )
    report = upscale_asset(p, out, options)
    assert all(math.isfinite(v) for e in report.get("history", []) for v in e["losses"].values())
    assert report["images"]
    result = load_asset(out / p.name)
    lr_normal = next(i.pixels for i in load_asset(p).images if "normal" in i.roles)
    for img in result.images:
        if not img.roles:
            continue
        px = img.pixels
        assert np.isfinite(px).all() and px.min() >= 0 and px.max() <= 1, img.name
        if "normal" in img.roles:  # facing out, at the input's length
            n = px[..., :3].astype(np.float64) * 2 - 1
            lr_t = torch.from_numpy(lr_normal[..., :3]).permute(2, 0, 1)[None]
            want = normal_length(lr_t, 2)[0, 0].numpy()
            assert np.allclose(np.linalg.norm(n, axis=-1), want, atol=2e-2), img.name
            assert (n[..., 2] >= 0).all(), img.name
    depth = {Path(i["name"]).stem: i["bit_depth"] for i in report["images"]}
    assert depth["base_color"] == 16
    assert depth["metallic_roughness"] == 32


def test_rich_asset_with_hdr_sun(tmp_path):
    """The feature-rich test asset (sphere, ORM, emissive, texture transform, TEXCOORD_1,
    16-bit PNG) under the 1e5 sun: finite renders and gradients."""
    p = make_test_asset(tmp_path / "t.glb", size=8)
    _check_render_and_grads(p, _sun_light(), res=32)
