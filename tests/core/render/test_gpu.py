"""The CUDA paths against the CPU ones. They run only where a GPU is present (a render farm,
or a task that is lent one); on a CPU-only machine they are skipped, saying why."""

from __future__ import annotations

import pytest
import torch

from pbrsr_core.asset.model import Material, TextureRef
from pbrsr_core.render import camera as cam
from pbrsr_core.render import raster, shade, shapes
from pbrsr_core.render.light import EnvLight
from pbrsr_core.render.raster import nvdiffrast_available

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")


def _scene():
    mesh = shapes.uv_sphere(24, 48)
    mat = Material(
        index=0,
        base_color=TextureRef(0),
        metallic_roughness=TextureRef(1),
        normal=TextureRef(2),
    )
    g = torch.Generator().manual_seed(0)
    tex = {
        0: torch.rand(32, 32, 4, generator=g),
        1: torch.rand(32, 32, 3, generator=g),
        2: torch.cat([torch.rand(32, 32, 2, generator=g), torch.ones(32, 32, 1)], -1),
    }
    c = cam.orbit_cameras(1, 1, 3.25, 30.0, (128, 128), elev_range_deg=(20.0, 20.0))[0]
    return mesh, [mat], tex, c


@pytest.mark.parametrize("backend", ["torch", "nvdiffrast"])
def test_gpu_raster_matches_cpu(backend):
    mesh, _, _, c = _scene()
    if backend == "nvdiffrast" and not nvdiffrast_available(torch.device("cuda")):
        pytest.skip("nvdiffrast is not installed")
    cpu = raster.rasterize(mesh, c, backend="numba")
    gpu = raster.rasterize(mesh.to("cuda"), c, backend=backend).to("cpu")
    differ = set(cpu.pix.tolist()) ^ set(gpu.pix.tolist())
    assert len(differ) <= 0.005 * cpu.pix.numel()


def test_gpu_shading_and_gradients_match_cpu():
    mesh, mats, tex, c = _scene()
    light = EnvLight.procedural()
    out = {}
    for dev in ("cpu", "cuda"):
        t = {k: v.to(dev).requires_grad_(True) for k, v in tex.items()}
        gb = raster.rasterize(mesh.to(dev), c, backend="torch" if dev == "cuda" else "numba")
        rgb = shade.shade(gb, mats, t, light.to(dev))
        rgb[:, :3].sum().backward()
        out[dev] = (gb.pix.cpu(), rgb.detach().cpu(), {k: v.grad.cpu() for k, v in t.items()})
    (pc, vc, gc), (pg, vg, gg) = out["cpu"], out["cuda"]
    common = torch.isin(pc, pg)
    idx_g = {p: i for i, p in enumerate(pg.tolist())}
    sel = torch.tensor([idx_g[p] for p in pc[common].tolist()])
    assert torch.allclose(vc[common], vg[sel], atol=2e-3)
    for k in gc:
        assert torch.allclose(gc[k], gg[k], atol=5e-3, rtol=5e-2)
