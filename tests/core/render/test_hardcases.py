"""Numerical hard cases (issue 6): outputs and gradients stay finite, maps in range."""

import pytest
import torch

from pbrsr_core.asset.model import Material, Mesh, TextureRef
from pbrsr_core.render import camera, light, raster, shade, shapes

MAT = Material(
    index=0,
    base_color=TextureRef(0),
    metallic_roughness=TextureRef(1),
    normal=TextureRef(2),
    occlusion=TextureRef(1),
    emissive=TextureRef(0),
    emissive_factor=(1.0, 1.0, 1.0),
)


@pytest.fixture(scope="module")
def env():
    return light.EnvLight.procedural()


@pytest.fixture(scope="module")
def sphere_gb():
    mesh = shapes.uv_sphere(16, 32, radius=0.5)
    return raster.rasterize(mesh, camera.look_at((0.3, 0.4, 2.5), fov_deg=30, resolution=(40, 40)))


def _run(gb, env, base, mr, nrm, mat=MAT):
    tex = {
        0: base.clone().requires_grad_(),
        1: mr.clone().requires_grad_(),
        2: nrm.clone().requires_grad_(),
    }
    out = shade.shade(gb, [mat], tex, env)
    img = shade.tonemap(shade.to_image(gb, out, 0.0))
    (img.sum() + out.sum()).backward()
    assert torch.isfinite(out).all()
    assert img.min() >= 0 and img.max() <= 1
    for t in tex.values():
        assert torch.isfinite(t.grad).all()
    return out, tex


def _c(vals, h=3, w=3):
    return torch.tensor(vals, dtype=torch.float32).view(1, 1, -1).repeat(h, w, 1)


FLAT = (0.5, 0.5, 1.0)


@pytest.mark.parametrize("rough", [0.0, 1.0])
@pytest.mark.parametrize("metal", [0.0, 1.0])
@pytest.mark.parametrize("albedo", [0.0, 1.0])
def test_extreme_material_values(sphere_gb, env, rough, metal, albedo):
    out, _ = _run(sphere_gb, env, _c((albedo,) * 3 + (1.0,)), _c((1.0, rough, metal)), _c(FLAT))
    if albedo == 0.0 and metal == 1.0:
        # black metal: F0 = 0 so only the Fresnel B term (plus emissive 0) remains
        assert out[:, :3].max() < 0.5 * env.radiance.max()


@pytest.mark.parametrize(
    "texel",
    [(0.5, 0.5, 0.5), (1.0, 1.0, 1.0), (0.5, 0.5, 0.0), (0.0, 0.0, 0.0), (0.5, 0.5, 0.4999)],
    ids=["zero", "unnormalised", "negative-z", "corner", "near-zero"],
)
def test_bad_normal_map_vectors(sphere_gb, env, texel):
    out, tex = _run(sphere_gb, env, _c((0.8, 0.6, 0.4, 1.0)), _c((1.0, 0.5, 0.0)), _c(texel))
    assert (out[:, :3] >= 0).all()


def test_degenerate_tangents_and_mirrored_uvs(env):
    q = shapes.quad(1.0, n_sub=2)
    nv = q.v_pos.shape[0]
    for v_tng in (
        torch.zeros(nv, 4),  # zero tangents
        torch.cat([q.v_nrm, -torch.ones(nv, 1)], 1),  # parallel to the normal, mirrored w
        torch.full((nv, 4), float("nan")),
    ):
        uv = q.v_uv[0].clone()
        uv[:, 0] = 1.0 - uv[:, 0]  # mirrored UVs
        uv[: nv // 2] = 0.5  # a zero-area UV region
        mesh = Mesh(q.v_pos, q.v_nrm, v_tng, {0: uv}, q.t_pos_idx, q.t_mat)
        cam = camera.look_at((0.2, 0.1, 1.5), fov_deg=50, resolution=(24, 24))
        gb = raster.rasterize(mesh, cam)
        assert torch.isfinite(gb.tng).all() and torch.isfinite(gb.uv_grad[0]).all()
        torch.testing.assert_close(gb.tng[:, :3].norm(dim=1), torch.ones(gb.num_pixels))
        _run(gb, env, _c((0.8, 0.6, 0.4, 1.0)), _c((1.0, 0.3, 0.5)), _c((0.7, 0.3, 0.9)))


@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_tiny_and_huge_meshes(env, scale):
    s = shapes.uv_sphere(16, 32, radius=0.5)
    offset = torch.tensor([3.0, -1.0, 2.0]) * scale
    mesh = Mesh(s.v_pos * scale + offset, s.v_nrm, s.v_tng, s.v_uv, s.t_pos_idx, s.t_mat)
    ref = raster.rasterize(s, camera.orbit_cameras(1, 1, 2.0, 40, 32)[0])
    frame = camera.normalize_transform(mesh.v_pos)
    gb = raster.rasterize(mesh, camera.orbit_cameras(1, 1, 2.0, 40, 32, frame=frame)[0])
    assert abs(gb.num_pixels - ref.num_pixels) <= 0.02 * ref.num_pixels
    for name in ("pos", "nrm", "tng", "view", "bary"):
        assert torch.isfinite(getattr(gb, name)).all()
    torch.testing.assert_close(gb.view.norm(dim=1), torch.ones(gb.num_pixels))
    _run(gb, env, _c((0.8, 0.6, 0.4, 1.0)), _c((1.0, 0.3, 0.5)), _c(FLAT))


@pytest.mark.parametrize("hw", [(1, 1), (600, 1000)])
def test_tiny_and_non_power_of_two_textures(sphere_gb, env, hw):
    g = torch.Generator().manual_seed(0)
    base = torch.rand(*hw, 4, generator=g)
    mr = torch.rand(*hw, 3, generator=g)
    nrm = torch.rand(*hw, 3, generator=g)
    _run(sphere_gb, env, base, mr, nrm)


def test_hdr_with_a_1e5_sun_and_nan_pixels(sphere_gb):
    from pbrsr_core.render.envmaps import texel_directions

    d = texel_directions(64, 128)
    rad = 0.2 + 1e5 * ((d - torch.tensor([0.3, 0.8, 0.52])).norm(dim=-1) < 0.05).double()
    rad = rad[..., None].repeat(1, 1, 3)
    rad[0, 0, 0] = float("nan")
    rad[1, 1, 1] = float("inf")
    env = light.EnvLight(rad)
    assert torch.isfinite(env.spec_levels).all() and torch.isfinite(env.diffuse_map).all()
    assert env.spec_levels.min() >= 0 and env.diffuse_map.min() >= 0
    out, _ = _run(sphere_gb, env, _c((0.8, 0.6, 0.4, 1.0)), _c((1.0, 0.0, 1.0)), _c(FLAT))
    assert out[:, :3].max() > 10  # the sun shows up in a mirror


def test_nan_vertices_and_degenerate_triangles_do_not_break_raster(env):
    q = shapes.quad(1.0, n_sub=4)
    pos = q.v_pos.clone()
    pos[3] = float("nan")
    tris = torch.cat([q.t_pos_idx, torch.tensor([[0, 0, 1], [2, 2, 2]])])
    mesh = Mesh(pos, q.v_nrm, q.v_tng, q.v_uv, tris, torch.zeros(tris.shape[0], dtype=torch.long))
    cam = camera.look_at((0.0, 0.0, 1.5), fov_deg=50, resolution=(32, 32))
    for backend in ("numba", "torch"):
        gb = raster.rasterize(mesh, cam, backend)
        assert gb.num_pixels > 100
        assert not torch.isin(gb.tri, torch.tensor([tris.shape[0] - 2, tris.shape[0] - 1])).any()
        assert not (mesh.t_pos_idx[gb.tri] == 3).any()
        assert torch.isfinite(gb.pos).all()


def test_shading_an_empty_gbuffer():
    cam = camera.look_at((0, 0, -3), (0, 0, -6), resolution=(8, 8))  # looking away
    gb = raster.rasterize(shapes.quad(1.0), cam)
    assert gb.num_pixels == 0
    out = shade.shade(gb, [MAT], {0: _c((1, 1, 1, 1))}, light.EnvLight.uniform(1.0))
    assert out.shape == (0, 4)
    assert shade.to_image(gb, out, 0.5).shape == (8, 8, 4)
