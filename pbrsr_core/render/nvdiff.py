"""Optional CUDA coverage through nvdiffrast (used only when ``nvdiffrast.torch`` imports and
the mesh is on a CUDA device; never required). Produces the same dense ``tri``/``bary`` as the
CPU kernels, so :func:`pbrsr_core.render.raster.build_gbuffer` finishes the job.

nvdiffrast's image row 0 is at NDC y = -1 (bottom), so its output is flipped to pbrsr's
top-row-first convention; its barycentrics (u, v) weight vertices 0 and 1 and are
perspective-correct; triangle ids are offset by one (0 = empty).
"""

from __future__ import annotations

import torch

from ..asset.model import Mesh
from .camera import Camera

_CONTEXTS: dict[str, object] = {}


def _context(device: torch.device):
    import nvdiffrast.torch as dr

    key = str(device)
    if key not in _CONTEXTS:
        _CONTEXTS[key] = dr.RasterizeCudaContext(device=device)
    return _CONTEXTS[key]


def raster_nvdiffrast(mesh: Mesh, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense ``tri`` (H*W,) int64 (-1 uncovered) and ``bary`` (H*W, 3) float32."""
    import nvdiffrast.torch as dr

    from .raster import project

    dev = mesh.v_pos.device
    h, w = camera.resolution
    clip, _, _, _ = project(mesh.v_pos, camera)
    rast, _ = dr.rasterize(
        _context(dev),
        clip.float()[None].contiguous(),
        mesh.t_pos_idx.int().contiguous(),
        resolution=[h, w],
    )
    rast = rast[0].flip(0).reshape(h * w, 4)
    tri = rast[:, 3].round().long() - 1
    bary = torch.stack([rast[:, 0], rast[:, 1], 1.0 - rast[:, 0] - rast[:, 1]], 1)
    return tri, bary.float()
