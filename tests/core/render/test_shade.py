"""Shading and lighting against analytic references: furnace, a quad with constant maps,
the BRDF table, diffuse irradiance, gradients, symmetry, energy."""

import math

import pytest
import torch

from pbrsr_core.asset.model import Material, Mesh, TextureRef
from pbrsr_core.render import camera, light, raster, shade, shapes


@pytest.fixture(scope="module")
def sphere_gb():
    mesh = shapes.uv_sphere(32, 64, radius=0.5)
    return raster.rasterize(mesh, camera.look_at((0.0, 0.5, 3.0), fov_deg=30, resolution=(64, 64)))


@pytest.fixture(scope="module")
def white():
    return light.EnvLight.uniform(1.0)


def _const(*vals, dtype=torch.float32, size=2, grad=False):
    t = torch.tensor(vals, dtype=dtype).view(1, 1, -1).repeat(size, size, 1)
    return t.requires_grad_(grad)


def test_white_furnace_diffuse_is_one(sphere_gb, white):
    mat = Material(
        index=0,
        metallic_factor=0.0,
        roughness_factor=0.7,
        base_color=TextureRef(0),
        metallic_roughness=TextureRef(1),
    )
    tex = {0: _const(1.0, 1.0, 1.0, 1.0), 1: _const(0.0, 1.0, 1.0)}
    t = shade.shade_terms(sphere_gb, [mat], tex, white)
    d = t["diffuse"]
    assert (d - 1.0).abs().max() < 0.01
    assert torch.isfinite(t["rgb"]).all()


def test_furnace_metal_rough_energy_at_most_one(sphere_gb, white):
    mat = Material(
        index=0, base_color_factor=(1, 1, 1, 1), metallic_factor=1.0, roughness_factor=1.0
    )
    out = shade.shade(sphere_gb, [mat], {}, white)
    assert out[:, :3].max() <= 1.0 + 1e-4
    assert out[:, :3].min() > 0.3  # and not black: rough metal still reflects the furnace


def _spec_integral(n_dot_v: float, rough: float, f0: float, n: int = 600) -> float:
    """int f_spec(l, v) cos(l) dl over the hemisphere by a midpoint rule (GGX D, Smith G
    (separable, exact G1), Schlick F), the analytic reference for the split-sum LUT."""
    a = max(rough * rough, light.ALPHA_MIN)
    th = (torch.arange(n, dtype=torch.float64) + 0.5) * (math.pi / 2 / n)
    ph = (torch.arange(2 * n, dtype=torch.float64) + 0.5) * (math.pi / n)
    T, P = torch.meshgrid(th, ph, indexing="ij")
    lx, ly, lz = T.sin() * P.cos(), T.sin() * P.sin(), T.cos()
    vx, vz = math.sqrt(1 - n_dot_v**2), n_dot_v
    hx, hy, hz = lx + vx, ly, lz + vz
    hn = torch.sqrt(hx * hx + hy * hy + hz * hz)
    hz, v_dot_h = hz / hn, (vx * hx + vz * (lz + vz)) / hn
    d = a * a / (math.pi * (hz * hz * (a * a - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + torch.sqrt(a * a + (1 - a * a) * c * c))

    f = f0 + (1 - f0) * (1 - v_dot_h) ** 5
    brdf = d * f * g1(torch.tensor(n_dot_v)) * g1(lz) / (4 * lz * n_dot_v)
    dw = T.sin() * (math.pi / 2 / n) * (math.pi / n)
    return float((brdf * lz * dw).sum())


def test_quad_constant_maps_against_analytic_split_sum():
    mesh = shapes.quad(1.0)
    cam = camera.look_at((0.3, 0.2, 1.2), (0, 0, 0), fov_deg=60, resolution=(24, 24))
    gb = raster.rasterize(mesh, cam)
    env_rgb = (1.0, 0.8, 0.5)
    env = light.EnvLight.uniform(env_rgb)
    base, rough, metal = (0.6, 0.4, 0.2), 0.5, 0.3
    mat = Material(
        index=0,
        base_color=TextureRef(0),
        metallic_roughness=TextureRef(1),
        emissive_factor=(0.1, 0.0, 0.05),
        emissive_strength=2.0,
    )
    tex = {0: _const(*base, 1.0), 1: _const(0.0, rough, metal)}
    out = shade.shade(gb, [mat], tex, env)
    nv = (gb.view * gb.nrm).sum(1)
    for p in torch.linspace(0, gb.num_pixels - 1, 3).long().tolist():
        c = nv[p].item()
        s0, s1 = _spec_integral(c, rough, 0.0, 400), _spec_integral(c, rough, 1.0, 400)
        for ch in range(3):
            f0 = 0.04 * (1 - metal) + metal * base[ch]
            spec = s0 + f0 * (s1 - s0)  # the integral is affine in F0
            want = env_rgb[ch] * (base[ch] * (1 - metal) + spec)
            want += (0.2, 0.0, 0.1)[ch]
            assert out[p, ch].item() == pytest.approx(want, rel=0.01)
    assert (out[:, 3] == 1).all()


@pytest.mark.parametrize("rough", [0.2, 0.6, 1.0])
@pytest.mark.parametrize("n_dot_v", [0.2, 0.95])
def test_brdf_lut_against_quadrature(rough, n_dot_v):
    lut = light.brdf_lut()
    a, b = light.lookup_brdf(lut, torch.tensor([[n_dot_v]]), torch.tensor([[rough]]))
    for f0 in (0.04, 1.0):
        ref = _spec_integral(n_dot_v, rough, f0, n=500)
        assert f0 * a.item() + b.item() == pytest.approx(ref, rel=0.03, abs=2e-3)


def test_brdf_lut_is_cached_on_disk(tmp_path, monkeypatch, set_runtime):
    set_runtime(cache_dir=tmp_path)
    monkeypatch.setattr(light, "_LUT_MEMO", {})
    lut = light.brdf_lut(size=8, samples=64)
    files = list(tmp_path.glob("brdf_lut_*.npz"))
    assert len(files) == 1
    monkeypatch.setattr(light, "_LUT_MEMO", {})
    torch.testing.assert_close(light.brdf_lut(size=8, samples=64), lut)
    # A + B is the directional albedo of a white (F0 = 1) GGX surface: never above 1
    assert light.brdf_lut().sum(-1).max() <= 1.0 + 2e-3


def test_prefiltered_environment_is_cached_on_disk(tmp_path, monkeypatch, set_runtime):
    from pbrsr_core.render.envmaps import procedural_sky

    set_runtime(cache_dir=tmp_path)
    sky = procedural_sky()
    first = light.EnvLight(sky)
    files = list(tmp_path.glob("envlight_*.npz"))
    assert len(files) == 1
    calls = []
    real = light._convolve
    monkeypatch.setattr(light, "_convolve", lambda *a: calls.append(1) or real(*a))
    again = light.EnvLight(sky)  # read back, nothing convolved
    assert calls == []
    torch.testing.assert_close(again.spec_levels, first.spec_levels, rtol=0, atol=0)
    torch.testing.assert_close(again.diffuse_map, first.diffuse_map, rtol=0, atol=0)
    # a damaged file is computed again (and rewritten), with the same values
    files[0].write_bytes(files[0].read_bytes()[:100])
    fixed = light.EnvLight(sky)
    assert calls and fixed.spec_levels.equal(first.spec_levels)
    # another environment is another entry
    light.EnvLight(torch.roll(sky, 7, dims=1))
    assert len(list(tmp_path.glob("envlight_*.npz"))) == 2
    # an unwritable cache only costs the computation
    set_runtime(cache_dir=tmp_path / "file")
    (tmp_path / "file").write_text("not a folder")
    assert light.EnvLight(sky).diffuse_map.equal(first.diffuse_map)


def test_diffuse_of_a_linear_environment_is_analytic():
    # L(d) = 1 + 0.5 y + 0.25 x: cosine convolution keeps the constant and scales the
    # linear band by 2/3 (irradiance / pi)
    from pbrsr_core.render.envmaps import texel_directions

    d = texel_directions(64, 128)
    env = light.EnvLight((1.0 + 0.5 * d[..., 1] + 0.25 * d[..., 0])[..., None].expand(64, 128, 3))
    n = torch.nn.functional.normalize(
        torch.randn(200, 3, generator=torch.Generator().manual_seed(3)), dim=1
    )
    want = 1.0 + (2.0 / 3.0) * (0.5 * n[:, 1] + 0.25 * n[:, 0])
    got = env.diffuse(n)[:, 0]
    assert (got - want).abs().max() < 0.02


def test_specular_prefilter_keeps_direction_and_smooths():
    from pbrsr_core.render.envmaps import texel_directions

    d = texel_directions(64, 128)
    spot = torch.exp((d[..., 1] - 1.0) / 0.01)  # a bright spot at the zenith
    env = light.EnvLight((0.1 + 10 * spot)[..., None].expand(64, 128, 3))
    up = torch.tensor([[0.0, 1.0, 0.0]])
    side = torch.tensor([[1.0, 0.0, 0.0]])
    vals = [env.specular(up, torch.tensor([[r]]))[0, 0].item() for r in (0.0, 0.4, 1.0)]
    assert vals[0] > vals[1] > vals[2] > 0.1  # peak spreads as roughness grows
    assert env.specular(side, torch.tensor([[0.0]]))[0, 0].item() == pytest.approx(0.1, rel=0.05)


def test_gradcheck_shade_wrt_textures():
    mesh = shapes.quad(1.0, n_sub=2)
    gb = raster.rasterize(mesh, camera.look_at((0.2, 0.1, 1.3), fov_deg=50, resolution=(6, 6)))
    env = light.EnvLight.uniform((1.0, 0.7, 0.4))
    g = torch.Generator().manual_seed(4)
    base = (0.2 + 0.6 * torch.rand(3, 3, 4, generator=g, dtype=torch.float64)).requires_grad_()
    mr = (0.2 + 0.6 * torch.rand(3, 3, 3, generator=g, dtype=torch.float64)).requires_grad_()
    nrm = torch.rand(3, 3, 3, generator=g, dtype=torch.float64)
    nrm[..., 2] = 0.8 + 0.2 * nrm[..., 2]
    nrm.requires_grad_()
    mat = Material(
        index=0,
        base_color=TextureRef(0),
        metallic_roughness=TextureRef(1),
        normal=TextureRef(2),
        normal_scale=0.8,
        occlusion=TextureRef(1),
        alpha_mode="BLEND",
    )

    def f(b, m, n):
        return shade.shade(gb, [mat], {0: b, 1: m, 2: n}, env)

    assert torch.autograd.gradcheck(f, (base, mr, nrm), atol=1e-5, rtol=1e-3)


def _symmetric_sphere() -> Mesh:
    """A UV sphere made exactly mirror-symmetric in x: the x >= 0 half plus its mirror."""
    s = shapes.uv_sphere(24, 48, radius=0.5)
    col = torch.arange(s.v_pos.shape[0]) % 49
    keep = (col[s.t_pos_idx] <= 24).all(1)
    tris = s.t_pos_idx[keep]
    nv = s.v_pos.shape[0]
    flip = torch.tensor([-1.0, 1.0, 1.0])
    return Mesh(
        v_pos=torch.cat([s.v_pos, s.v_pos * flip]),
        v_nrm=torch.cat([s.v_nrm, s.v_nrm * flip]),
        v_tng=torch.cat([s.v_tng, s.v_tng * torch.tensor([-1.0, 1, 1, -1])]),
        v_uv={0: torch.cat([s.v_uv[0], s.v_uv[0]])},
        t_pos_idx=torch.cat([tris, tris.flip(1) + nv]),
        t_mat=torch.zeros(2 * tris.shape[0], dtype=torch.long),
    )


def test_symmetric_scene_renders_mirror_symmetric():
    from pbrsr_core.render.envmaps import texel_directions

    d = texel_directions(64, 128)
    ax = d[..., 0].abs()
    rad = (
        0.3
        + 0.4 * (d[..., 1] > 0)
        + 5.0 * torch.exp(((ax - 0.6) ** 2 + (d[..., 1] - 0.4) ** 2) / -0.02)
    )
    env = light.EnvLight(torch.stack([rad, rad * 0.8 + 0.1 * d[..., 2], rad * 0.5], -1))
    mesh = _symmetric_sphere()
    cam = camera.look_at((0.0, 0.6, 2.5), (0, 0, 0), fov_deg=30, resolution=(48, 64))
    gb = raster.rasterize(mesh, cam)
    mat = Material(
        index=0, base_color_factor=(0.7, 0.5, 0.3, 1.0), metallic_factor=0.5, roughness_factor=0.35
    )
    img = shade.to_image(gb, shade.shade(gb, [mat], {}, env)[:, :3], 0.0)
    assert img.abs().sum() > 0
    asym = (img - img.flip(1)).abs().max() / img.max()
    assert asym < 1e-3
    # and the environment is not trivially symmetric in every direction: front/back differ
    assert (img - img.flip(0)).abs().max() > 0.05


def test_to_image_and_tonemap():
    gb = raster.rasterize(
        shapes.quad(1.0), camera.look_at((0, 0, 2), fov_deg=40, resolution=(8, 10))
    )
    vals = torch.full((gb.num_pixels, 3), 4.0, requires_grad=True)
    img = shade.to_image(gb, vals, torch.tensor([0.0, 0.5, 1.0]))
    assert img.shape == (8, 10, 3)
    m = gb.mask()
    assert (img[m] == 4.0).all() and (img[~m] == torch.tensor([0.0, 0.5, 1.0])).all()
    img.sum().backward()
    assert (vals.grad == 1).all()
    t = shade.tonemap(torch.tensor([[0.0, 0.0031308, 0.18, 1.0, 50.0]]).T.expand(5, 3))
    torch.testing.assert_close(
        t[:, 0], torch.tensor([0.0, 0.04045, 0.4614, 1.0, 1.0]), atol=2e-4, rtol=0
    )
    rgba = shade.tonemap(torch.tensor([[0.5, 0.5, 0.5, 0.3]]))
    assert rgba[0, 3].item() == pytest.approx(0.3)


def test_multiple_materials_and_cached_taps_agree():
    q = shapes.quad(1.0, n_sub=4)
    t_mat = torch.arange(q.num_triangles) % 2
    t_mat[:4] = -1  # a few triangles use glTF's default material
    mesh = Mesh(q.v_pos, q.v_nrm, q.v_tng, q.v_uv, q.t_pos_idx, t_mat)
    gb = raster.rasterize(mesh, camera.look_at((0.1, 0.2, 1.4), fov_deg=50, resolution=(32, 32)))
    env = light.EnvLight.uniform((0.9, 1.0, 1.1))
    g = torch.Generator().manual_seed(5)
    tex = {0: torch.rand(5, 7, 4, generator=g), 1: torch.rand(4, 4, 3, generator=g)}
    mats = [
        Material(index=0, base_color=TextureRef(0), metallic_roughness=TextureRef(1)),
        Material(
            index=1,
            base_color=TextureRef(0, uv_transform=(2, 0, 0, 0, 2, 0, 0, 0, 1)),
            roughness_factor=0.3,
            metallic_factor=0.0,
        ),
    ]
    first = shade.shade(gb, mats, tex, env)
    assert len(gb.cache) > 0
    again = shade.shade(gb, mats, tex, env)  # from the cached taps
    torch.testing.assert_close(first, again)
    for m in (-1, 0, 1):  # each material alone gives the same pixels
        sel = gb.mat == m
        one = Mesh(q.v_pos, q.v_nrm, q.v_tng, q.v_uv, q.t_pos_idx, torch.full_like(t_mat, m))
        g1 = raster.rasterize(one, camera.look_at((0.1, 0.2, 1.4), fov_deg=50, resolution=(32, 32)))
        assert torch.equal(g1.pix, gb.pix)
        torch.testing.assert_close(shade.shade(g1, mats, tex, env)[sel], first[sel])


@pytest.mark.parametrize("backside", [False, True])
def test_normal_map_convention_tangent_x_and_opengl_green_up(backside):
    """On a quad (u along +x, v along -y), tangent-space +X tilts the normal toward +x and
    +Y (green, OpenGL) toward +y (up in the image); from behind the frame is mirrored."""
    mesh = shapes.quad(1.0)
    z = -1.5 if backside else 1.5
    gb = raster.rasterize(mesh, camera.look_at((0.0, 0.0, z), fov_deg=20, resolution=(8, 8)))
    env = light.EnvLight.uniform(1.0)
    mat = Material(index=0, normal=TextureRef(0), normal_scale=1.0)
    for texel, axis in (((0.8, 0.5, 0.9), 0), ((0.5, 0.8, 0.9), 1)):
        n = shade.shade_terms(gb, [mat], {0: _const(*texel)}, env)["normal"]
        tilt = (2 * texel[axis] - 1) / math.hypot(2 * texel[axis] - 1, 2 * 0.9 - 1)
        sign = -1.0 if backside else 1.0
        torch.testing.assert_close(n[:, axis], torch.full_like(n[:, axis], sign * tilt))
        assert (n[:, 2] * sign > 0).all()


def test_alpha_modes_and_factors():
    gb = raster.rasterize(
        shapes.quad(1.0), camera.look_at((0, 0, 2), fov_deg=40, resolution=(8, 8))
    )
    env = light.EnvLight.uniform(1.0)
    tex = {0: _const(0.5, 0.5, 0.5, 0.3)}
    kw = dict(index=0, base_color=TextureRef(0), base_color_factor=(1.0, 1.0, 1.0, 2.0))
    alpha = {
        mode: shade.shade(gb, [Material(alpha_mode=mode, alpha_cutoff=0.5, **kw)], tex, env)[:, 3]
        for mode in ("OPAQUE", "MASK", "BLEND")
    }
    assert (alpha["OPAQUE"] == 1).all()
    assert (alpha["MASK"] == 1).all()  # 0.3 * 2.0 = 0.6 >= 0.5
    torch.testing.assert_close(alpha["BLEND"], torch.full_like(alpha["BLEND"], 0.6))
    # a factor multiplies the texture: half the albedo, half the diffuse term
    a = shade.shade_terms(gb, [Material(**kw)], tex, env)["diffuse"]
    kw["base_color_factor"] = (0.5, 0.5, 0.5, 1.0)
    b = shade.shade_terms(gb, [Material(**kw)], tex, env)["diffuse"]
    torch.testing.assert_close(b, a * 0.5)


def test_cache_is_not_shared_by_replaced_gbuffers():
    import dataclasses

    gb = raster.rasterize(
        shapes.quad(1.0), camera.look_at((0, 0, 2), fov_deg=40, resolution=(16, 16))
    )
    env = light.EnvLight.uniform(1.0)
    mat = [Material(index=0, base_color=TextureRef(0))]
    tex = {0: torch.rand(4, 4, 4, generator=torch.Generator().manual_seed(0))}
    full = shade.shade(gb, mat, tex, env)
    half = dataclasses.replace(
        gb,
        **{
            k: getattr(gb, k)[::2]
            for k in ("pix", "tri", "bary", "pos", "nrm", "tng", "mat", "view")
        },
        uv={0: gb.uv[0][::2]},
        uv_grad={0: gb.uv_grad[0][::2]},
    )
    torch.testing.assert_close(shade.shade(half, mat, tex, env), full[::2])
    gb.cache["material_rows"] = "stale"  # a cache filled for other pixels is dropped
    gb.pix = gb.pix.clone()
    torch.testing.assert_close(shade.shade(gb, mat, tex, env), full)
