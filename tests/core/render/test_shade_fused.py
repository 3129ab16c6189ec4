"""The fused CPU shading kernels (render/shade_kernels.py) against the torch reference path of
shade.shade: forward values and gradients w.r.t. every texture on random materials with the
hard cases (roughness/metallic exactly 0 and 1, zero and negative-z normal samples,
back-facing pixels, MASK/BLEND alpha, factors != 1, occlusion/emissive present or absent,
several materials in one G-buffer), float64 exactness, a float64 gradcheck of the autograd
Function, and finiteness on hostile inputs."""

import numba
import pytest
import torch

from pbrsr_core.asset.model import Material, Mesh, TextureRef
from pbrsr_core.render import camera, light, raster, shade, shade_kernels, shapes


def _blocky(h, w, c, g, hard=(0.0, 1.0), p_hard=0.3):
    """Random (h, w, c) texture in [0, 1] whose 2x2 blocks are constant, a fraction
    ``p_hard`` of them set exactly to one of ``hard`` (so pixels see exact hard values)."""
    t = torch.rand(h // 2, w // 2, c, generator=g, dtype=torch.float64)
    pick = torch.rand(h // 2, w // 2, c, generator=g) < p_hard
    vals = torch.tensor(hard, dtype=torch.float64)[
        torch.randint(len(hard), (h // 2, w // 2, c), generator=g)
    ]
    t = torch.where(pick, vals, t)
    return t.repeat_interleave(2, 0).repeat_interleave(2, 1).float()


@pytest.fixture(scope="module")
def env():
    return light.EnvLight.procedural()


def _materials():
    return [
        Material(  # everything textured, BLEND, occlusion strength and normal scale != 1
            index=0,
            base_color=TextureRef(0),
            metallic_roughness=TextureRef(1),
            occlusion=TextureRef(1),
            occlusion_strength=0.7,
            normal=TextureRef(2),
            normal_scale=1.3,
            emissive=TextureRef(3),
            emissive_factor=(0.5, 0.2, 0.0),
            emissive_strength=2.0,
            alpha_mode="BLEND",
        ),
        Material(  # factors != 1 on textures, MASK, no occlusion / emissive
            index=1,
            base_color=TextureRef(0, uv_transform=(2, 0, 0.1, 0, 2, 0, 0, 0, 1)),
            base_color_factor=(0.8, 1.2, 0.5, 0.9),
            metallic_roughness=TextureRef(1),
            roughness_factor=0.6,
            metallic_factor=1.3,
            normal=TextureRef(2),
            normal_scale=-0.8,
            alpha_mode="MASK",
            alpha_cutoff=0.45,
        ),
        Material(  # untextured: constant factors, roughness exactly 0, metal exactly 1
            index=2, base_color_factor=(0.9, 0.6, 0.3, 1.0), roughness_factor=0.0
        ),
        Material(  # only a normal map (full of zero and negative-z samples) and emissive
            index=3,
            normal=TextureRef(4),
            emissive_factor=(0.1, 0.1, 0.1),
            roughness_factor=1.0,
            metallic_factor=0.0,
        ),
    ]


def _textures(seed=0):
    g = torch.Generator().manual_seed(seed)
    nrm = torch.rand(16, 16, 3, generator=g) * 0.5 + torch.tensor([0.25, 0.25, 0.5])
    hostile = torch.rand(8, 8, 3, generator=g)  # z < 0.5: tangent-space z negative
    hostile[::2, ::2] = 0.5  # exactly the zero vector after decoding
    return {
        0: _blocky(16, 16, 4, g),
        1: _blocky(16, 16, 3, g),
        2: nrm,
        3: _blocky(8, 8, 3, g, hard=(0.0,)),
        4: hostile.repeat_interleave(2, 0).repeat_interleave(2, 1),
    }


@pytest.fixture(scope="module")
def gbuffers():
    """A sphere (front faces), and a four-material subdivided quad seen from the front and
    from behind (back-facing pixels), with a few triangles on glTF's default material."""
    sphere = shapes.uv_sphere(16, 32, radius=0.5)
    sphere = Mesh(
        sphere.v_pos,
        sphere.v_nrm,
        sphere.v_tng,
        sphere.v_uv,
        sphere.t_pos_idx,
        torch.arange(sphere.num_triangles) % 4,
    )
    q = shapes.quad(1.0, n_sub=4)
    t_mat = torch.arange(q.num_triangles) % 4
    t_mat[:3] = -1
    quad = Mesh(q.v_pos, q.v_nrm, q.v_tng, q.v_uv, q.t_pos_idx, t_mat)
    gbs = [
        raster.rasterize(sphere, camera.look_at((0.4, 0.7, 1.8), fov_deg=40, resolution=(40, 40))),
        raster.rasterize(quad, camera.look_at((0.2, 0.3, 1.3), fov_deg=60, resolution=(36, 36))),
        raster.rasterize(quad, camera.look_at((0.3, -0.2, -1.2), fov_deg=60, resolution=(36, 36))),
    ]
    assert bool(gbs[2].backface.all()) and not bool(gbs[1].backface.any())
    return gbs


def _run(gb, mats, textures, env, dtype, reference, seed=1):
    params = {k: v.to(dtype).clone().requires_grad_(True) for k, v in textures.items()}
    out = shade.shade(gb, mats, params, env, reference=reference)
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    (out * w).sum().backward()
    grads = {k: (v.grad if v.grad is not None else torch.zeros_like(v)) for k, v in params.items()}
    return out.detach(), grads


@pytest.mark.parametrize("view", [0, 1, 2])
def test_fused_matches_reference_float32(gbuffers, env, view):
    gb, mats, tex = gbuffers[view], _materials(), _textures()
    assert shade.use_fused(gb, tex, env)
    ref, g_ref = _run(gb, mats, tex, env, torch.float32, reference=True)
    out, g_out = _run(gb, mats, tex, env, torch.float32, reference=False)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    for k in tex:
        assert torch.isfinite(g_out[k]).all()
        scale = float(g_ref[k].abs().max())
        err = float((g_out[k] - g_ref[k]).abs().max())
        assert err <= 1e-4 * scale + 1e-7, (k, err, scale)
    # the hard values really occur in this G-buffer
    m = shade.material_inputs(gb, mats, tex)
    assert (m["rough"] == 0).any() and (m["rough"] == 1).any()
    assert (m["metal"] == 0).any() and (m["metal"] == 1).any()
    assert (m["normal_ts"][:, 2] < 0).any() or view == 0


def test_fused_is_exact_in_float64(gbuffers, env):
    """In float64 the kernels reproduce the reference to rounding: the same function."""
    for gb in gbuffers:
        mats, tex = _materials(), _textures(seed=3)
        ref, g_ref = _run(gb, mats, tex, env, torch.float64, reference=True, seed=4)
        out, g_out = _run(gb, mats, tex, env, torch.float64, reference=False, seed=4)
        torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-12)
        for k in tex:
            torch.testing.assert_close(g_out[k], g_ref[k], atol=1e-11, rtol=1e-10)


def test_uniform_light_and_custom_lut(gbuffers):
    """Another environment (tiny 8x16 maps) and a caller-given BRDF table."""
    env = light.EnvLight.uniform((0.5, 1.0, 2.0))
    lut = light.brdf_lut().flip(0).contiguous()  # any (S, S, 2) table is looked up the same
    gb, mats, tex = gbuffers[0], _materials(), _textures(seed=5)
    p = {k: v.double().requires_grad_(True) for k, v in tex.items()}
    a = shade.shade(gb, mats, p, env, lut, reference=True)
    b = shade.shade(gb, mats, p, env, lut)
    torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
    ga = torch.autograd.grad(a.sum(), list(p.values()), allow_unused=True)
    gb_ = torch.autograd.grad(b.sum(), list(p.values()), allow_unused=True)
    for x, y in zip(ga, gb_, strict=True):
        if x is not None:
            torch.testing.assert_close(y, x, atol=1e-11, rtol=1e-10)


def _pixel_inputs(n, seed, dtype=torch.float64):
    """Per-pixel inputs of the fused Function away from clamps and table cells' edges."""
    g = torch.Generator().manual_seed(seed)

    def r(c, lo=0.05, hi=0.95):
        return (lo + (hi - lo) * torch.rand(n, c, generator=g, dtype=torch.float64)).to(dtype)

    nts = torch.nn.functional.normalize(r(3, -0.5, 0.5) + torch.tensor([0.0, 0.0, 0.8]), dim=1)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64))
    t = torch.nn.functional.normalize(
        torch.cross(nrm, torch.randn(n, 3, generator=g).double(), dim=1)
    )
    tng = torch.cat([t, torch.where(torch.rand(n, 1, generator=g) < 0.5, -1.0, 1.0).double()], 1)
    view = torch.nn.functional.normalize(nrm + 0.6 * torch.randn(n, 3, generator=g).double())
    ins = [r(4), r(1, 0.03, 0.17), r(1), r(1), r(3, -0.2, 0.8), nts.to(dtype), r(1)]
    ins[1][n // 2 :] += 0.61  # roughness in two level cells: (0.03, 0.17), (0.64, 0.78)
    return ins, (nrm.float(), tng.float(), view.float())


def test_gradcheck_fused_function(env):
    ins, (nrm, tng, view) = _pixel_inputs(6, seed=7)
    const = (
        nrm.numpy(),
        tng.numpy(),
        view.numpy(),
        *shade_kernels.light_tables(env, light.brdf_lut()),
    )
    ins = [t.requires_grad_(True) for t in ins]

    def f(*xs):
        return shade_kernels.FusedShade.apply(*xs, const)

    assert torch.autograd.gradcheck(f, ins, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_no_grad_forward_and_threads_agree(gbuffers, env):
    gb, mats, tex = gbuffers[1], _materials(), _textures(seed=9)
    with torch.no_grad():
        a = shade.shade(gb, mats, tex, env)  # scratch rows, no stored lookups
    p = {k: v.clone().requires_grad_(True) for k, v in tex.items()}
    b = shade.shade(gb, mats, p, env).detach()
    torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = shade.shade(gb, mats, tex, env)
        torch.set_num_threads(max(2, n))
        two = shade.shade(gb, mats, tex, env)
    finally:
        torch.set_num_threads(n)
    assert torch.equal(one, two)
    assert numba.get_num_threads() >= 1


def test_hostile_inputs_stay_finite(env):
    """Extreme per-pixel values straight into the Function: outputs and gradients finite,
    zero gradient past every clamp."""
    n = 64
    ins, (nrm, tng, view) = _pixel_inputs(n, seed=11, dtype=torch.float32)
    g = torch.Generator().manual_seed(12)
    big = torch.tensor([-1e4, -1.0, 0.0, 1.0, 1e4, 2.0, -0.0, 0.5])
    pick = lambda c: big[torch.randint(len(big), (n, c), generator=g)]  # noqa: E731
    ins = [pick(t.shape[1]) for t in ins]
    ins[5][:8] = 0.0  # zero tangent-space normals
    view[8:16] = -view[8:16]  # pixels seen from below the shading surface (N.V < 0)
    const = (
        nrm.numpy(),
        tng.numpy(),
        view.numpy(),
        *shade_kernels.light_tables(env, light.brdf_lut()),
    )
    ins = [t.requires_grad_(True) for t in ins]
    out = shade_kernels.FusedShade.apply(*ins, const)
    out.backward(torch.randn(out.shape, generator=g))
    assert torch.isfinite(out).all()
    for t in ins:
        assert torch.isfinite(t.grad).all()
    assert (ins[1].grad[(ins[1] < 0) | (ins[1] > 1)] == 0).all()  # roughness clamp
    assert (ins[2].grad[(ins[2] < 0) | (ins[2] > 1)] == 0).all()  # metallic clamp
    assert (ins[5].grad[:8] == 0).all()  # degenerate normal: the geometric one, no gradient


def test_reference_switch(gbuffers, env, set_runtime):
    gb, tex = gbuffers[0], _textures()
    assert shade.use_fused(gb, tex, env)
    set_runtime(shade_reference=True)
    assert not shade.use_fused(gb, tex, env)
    set_runtime(shade_reference=False)
    assert shade.use_fused(gb, tex, env)
    half = {k: v.half() for k, v in tex.items()}
    assert not shade.use_fused(gb, half, env)  # only float32/float64 kernels


def test_decode_normal_matches_torch_and_gradcheck():
    g = torch.Generator().manual_seed(13)
    t = torch.rand(40, 3, generator=g, dtype=torch.float64)
    t[:5] = 0.5  # the zero vector: (0, 0, 1), no gradient
    for s in (1.0, -0.7, 2.5):
        v = (2 * t - 1) * torch.tensor([s, s, 1.0], dtype=torch.float64)
        n2 = (v * v).sum(-1, keepdim=True)
        ref = torch.where(n2 > 1e-12, v / n2.sqrt(), torch.tensor([0.0, 0.0, 1.0]).double())
        torch.testing.assert_close(shade_kernels.DecodeNormal.apply(t, s), ref)
        x = t[5:15].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda a, s=s: shade_kernels.DecodeNormal.apply(a, s), (x,))
    x = t.clone().requires_grad_(True)
    shade_kernels.DecodeNormal.apply(x, 1.0).sum().backward()
    assert (x.grad[:5] == 0).all() and torch.isfinite(x.grad).all()
