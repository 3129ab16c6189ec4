"""Cameras and the rasterizer: fast numba path vs the torch reference, geometry checks."""

import math

import numpy as np
import pytest
import torch

from pbrsr_core.asset.model import Mesh
from pbrsr_core.render import camera, raster, shapes


def _clutter(seed: int = 0, n: int = 300) -> Mesh:
    """Random overlapping triangles in a unit box (many depth conflicts, both windings)."""
    g = torch.Generator().manual_seed(seed)
    centre = torch.rand(n, 1, 3, generator=g) - 0.5
    pos = (centre + 0.25 * (torch.rand(n, 3, 3, generator=g) - 0.5)).reshape(-1, 3)
    nrm = torch.nn.functional.normalize(torch.randn(n * 3, 3, generator=g), dim=1)
    tng = torch.cat(
        [
            torch.nn.functional.normalize(torch.randn(n * 3, 3, generator=g), dim=1),
            torch.ones(n * 3, 1),
        ],
        1,
    )
    return Mesh(
        v_pos=pos,
        v_nrm=nrm,
        v_tng=tng,
        v_uv={0: torch.rand(n * 3, 2, generator=g), 1: torch.rand(n * 3, 2, generator=g)},
        t_pos_idx=torch.arange(n * 3).view(n, 3),
        t_mat=torch.arange(n) % 3,
    )


def test_paper_cameras_counts_and_no_coincidence():
    train = camera.paper_train_cameras(64)
    ev = camera.paper_eval_cameras(64)
    assert len(train) == 750 and len(ev) == 240
    te = np.stack([c.eye for c in train])
    ee = np.stack([c.eye for c in ev])
    np.testing.assert_allclose(np.linalg.norm(te, axis=1), 3.25)
    dmin = np.linalg.norm(te[:, None] - ee[None], axis=2).min()
    assert dmin > 1e-3
    assert all(c.fov_deg == 10.0 for c in train)


def test_look_at_projects_target_to_image_centre_and_up_is_up():
    cam = camera.look_at((1.0, 2.0, 3.0), (0.1, 0.2, 0.3), fov_deg=30, resolution=(40, 60))
    pts = torch.tensor([[0.1, 0.2, 0.3], [0.1, 0.25, 0.3]])
    _, sx, sy, iw = raster.project(pts, cam)
    assert sx[0].item() == pytest.approx(30.0) and sy[0].item() == pytest.approx(20.0)
    assert sy[1] < sy[0]  # +y in the world is up on screen (row index decreases)
    assert iw[0] > 0


def test_normalize_transform_and_frame():
    pts = torch.tensor([[10.0, 0.0, 0.0], [14.0, 2.0, 1.0], [float("nan"), 0, 0]])
    c, s = camera.normalize_transform(pts)
    np.testing.assert_allclose(c, [12.0, 1.0, 0.5])
    assert s == pytest.approx(0.25)
    # a framed camera sees the un-normalised mesh exactly as the plain camera sees the
    # normalised one
    mesh = shapes.uv_sphere(8, 16, radius=0.5)
    big = Mesh(
        mesh.v_pos * 40.0 + torch.tensor([3.0, -2.0, 7.0]),
        mesh.v_nrm,
        mesh.v_tng,
        mesh.v_uv,
        mesh.t_pos_idx,
        mesh.t_mat,
    )
    frame = camera.normalize_transform(big.v_pos)
    a = camera.orbit_cameras(2, 3, 2.0, 40, 32)[4]
    b = camera.orbit_cameras(2, 3, 2.0, 40, 32, frame=frame)[4]
    ga, gb_ = raster.rasterize(mesh, a), raster.rasterize(big, b)
    assert torch.equal(ga.pix, gb_.pix)
    torch.testing.assert_close(ga.view, gb_.view, atol=1e-4, rtol=0)
    np.testing.assert_allclose(b.eye, a.eye * 40.0 + [3.0, -2.0, 7.0], atol=1e-9)


@pytest.mark.parametrize("seed", [0, 1])
def test_numba_matches_torch_reference(seed):
    mesh = _clutter(seed)
    cam = camera.look_at((0.3, 0.4, 2.0), (0, 0, 0), fov_deg=40, resolution=(61, 83))
    t_n, b_n, _ = raster.coverage(mesh, cam, "numba")
    t_t, b_t, _ = raster.coverage(mesh, cam, "torch")
    assert torch.equal(t_n >= 0, t_t >= 0)  # same coverage
    same = t_n == t_t
    assert same.float().mean() > 0.995  # ids differ only at exact depth ties
    cov = (t_n >= 0) & same
    assert cov.sum() > 500
    assert (b_n[cov] - b_t[cov]).abs().max() < 1e-4
    # the fused G-buffer interpolation matches the plain torch one
    g_n = raster.rasterize(mesh, cam, "numba")
    pix = g_n.pix
    g_t = raster.build_gbuffer_torch(mesh, cam, pix, g_n.tri, g_n.bary)
    for name in ("bary", "pos", "nrm", "tng", "view"):
        torch.testing.assert_close(getattr(g_n, name), getattr(g_t, name), atol=1e-5, rtol=0)
    for k in (0, 1):
        torch.testing.assert_close(g_n.uv[k], g_t.uv[k], atol=1e-5, rtol=0)
        torch.testing.assert_close(g_n.uv_grad[k], g_t.uv_grad[k], atol=1e-4, rtol=1e-3)
    assert torch.equal(g_n.mat, mesh.t_mat[g_n.tri])
    assert torch.equal(g_n.backface, g_t.backface)


def test_bary_reconstructs_pixel_centres_on_a_quad():
    mesh = shapes.quad(1.0, n_sub=3)
    cam = camera.look_at((0.2, -0.1, 1.5), (0, 0, 0), fov_deg=50, resolution=(48, 48))
    gb = raster.rasterize(mesh, cam)
    assert gb.num_pixels > 300
    clip = torch.cat([gb.pos.double(), torch.ones(gb.num_pixels, 1, dtype=torch.float64)], 1)
    clip = clip @ torch.as_tensor(cam.full_proj).T
    x = (clip[:, 0] / clip[:, 3] + 1) * 24
    y = (1 - clip[:, 1] / clip[:, 3]) * 24
    torch.testing.assert_close(x, (gb.pix % 48).double() + 0.5, atol=1e-3, rtol=0)
    torch.testing.assert_close(y, (gb.pix // 48).double() + 0.5, atol=1e-3, rtol=0)
    torch.testing.assert_close(gb.bary.sum(1), torch.ones(gb.num_pixels), atol=1e-5, rtol=0)


def test_uv_grad_matches_finite_differences():
    mesh = shapes.quad(1.0, n_sub=1)
    cam = camera.look_at((0.4, 0.3, 1.2), (0, 0, 0), fov_deg=60, resolution=(64, 64))
    gb = raster.rasterize(mesh, cam)
    uv = torch.full((64 * 64, 2), float("nan"))
    uv[gb.pix] = gb.uv[0]
    uv = uv.view(64, 64, 2)
    ddx = (uv[:, 2:] - uv[:, :-2]) / 2  # central differences, (64, 62, 2)
    ddy = (uv[2:] - uv[:-2]) / 2
    g = torch.full((64 * 64, 4), float("nan"))
    g[gb.pix] = gb.uv_grad[0]
    g = g.view(64, 64, 4)
    # u, v are rational in screen space: compare where the stencil is inside one triangle
    tri = torch.full((64 * 64,), -1)
    tri[gb.pix] = gb.tri
    tri = tri.view(64, 64)
    okx = (tri[:, 2:] == tri[:, 1:-1]) & (tri[:, :-2] == tri[:, 1:-1]) & (tri[:, 1:-1] >= 0)
    oky = (tri[2:] == tri[1:-1]) & (tri[:-2] == tri[1:-1]) & (tri[1:-1] >= 0)
    assert okx.sum() > 500 and oky.sum() > 500
    torch.testing.assert_close(g[:, 1:-1, :2][okx], ddx[okx], atol=2e-4, rtol=2e-2)
    torch.testing.assert_close(g[1:-1, :, 2:][oky], ddy[oky], atol=2e-4, rtol=2e-2)


def test_back_faces_are_kept_and_flipped_toward_viewer():
    mesh = shapes.quad(1.0)
    front = raster.rasterize(mesh, camera.look_at((0, 0, 2), fov_deg=40, resolution=(32, 32)))
    back = raster.rasterize(mesh, camera.look_at((0, 0, -2), fov_deg=40, resolution=(32, 32)))
    assert front.num_pixels == back.num_pixels > 100
    assert not front.backface.any() and back.backface.all()
    torch.testing.assert_close(front.nrm, torch.tensor([[0.0, 0, 1]]).expand_as(front.nrm))
    torch.testing.assert_close(back.nrm, torch.tensor([[0.0, 0, -1]]).expand_as(back.nrm))
    assert (back.tng[:, 3] == -1).all()  # whole TBN mirrored
    assert ((back.nrm * back.view).sum(1) > 0).all()


def test_sphere_coverage_area_and_unit_frames():
    mesh = shapes.uv_sphere(32, 64, radius=0.5)
    cam = camera.look_at((0, 0, 3.0), fov_deg=30, resolution=(128, 128))
    gb = raster.rasterize(mesh, cam)
    # projected disc radius: tan(asin(r / d)) / tan(fov / 2) * H / 2
    rpix = math.tan(math.asin(0.5 / 3.0)) / math.tan(math.radians(15)) * 64
    assert gb.num_pixels == pytest.approx(math.pi * rpix**2, rel=0.02)
    torch.testing.assert_close(gb.nrm.norm(dim=1), torch.ones(gb.num_pixels))
    torch.testing.assert_close(gb.tng[:, :3].norm(dim=1), torch.ones(gb.num_pixels))
    assert (gb.nrm * gb.tng[:, :3]).sum(1).abs().max() < 1e-5


def test_gbuffer_to_and_mask():
    mesh = shapes.quad(1.0)
    gb = raster.rasterize(mesh, camera.look_at((0, 0, 2), fov_deg=40, resolution=(16, 20)))
    m = gb.mask()
    assert m.shape == (16, 20) and int(m.sum()) == gb.num_pixels
    g2 = gb.to("cpu")
    assert torch.equal(g2.pix, gb.pix) and g2.uv.keys() == gb.uv.keys()


def test_unknown_backend_is_an_error():
    with pytest.raises(ValueError, match="unknown raster backend"):
        raster.rasterize(shapes.quad(), camera.look_at((0, 0, 2)), backend="opengl")
