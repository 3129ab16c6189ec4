"""Stage 1 of the optimiser, ``gbuffers``: choose the training views (the paper's orbit or
texel coverage, views.py), pick the render resolution from texel density, rasterise every
view once at the HR render resolution, drop the views that see nothing, and measure which
texels the kept views see. G-buffers never change while only textures are optimised."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import UnprocessableAsset
from ..progress import Progress, ProgressFn, emit
from ..render import camera as cam
from . import views as vsel
from .gbuffers import GBufferStore, gbuffer_bytes
from .presets import PbrsrConfig

PROBE_RES = 128  # side of the low-resolution renders used to select views and measure density


def camera_dict(c: cam.Camera) -> dict:
    """A camera as the report lists it."""
    return {
        "eye": [round(float(x), 5) for x in c.eye],
        "fov_deg": c.fov_deg,
        "resolution": list(c.resolution),
    }


def choose_views(mesh, materials, images, sizes, scale, config, rasterize):
    """Cameras (at the HR render resolution) and a summary for the report."""
    info: dict = {"mode": config.view_mode}
    if config.view_mode == "orbit":
        cams = cam.orbit_cameras(
            config.n_elev,
            config.n_azim,
            config.distance,
            config.fov_deg,
            PROBE_RES,
            config.elev_range_deg,
        )
        probe = cams[:: max(1, len(cams) // 8)][:8]
    else:
        cand = vsel.sphere_cameras(config.n_candidates, config.distance, config.fov_deg, PROBE_RES)
        chosen, sel_info = vsel.select_coverage_views(
            mesh,
            materials,
            images,
            cand,
            rasterize,
            max_views=config.max_views,
            min_new_texels=config.min_new_texels,
            image_sizes=sizes,
            views_per_texel=config.views_per_texel,
        )
        cams = [cand[k] for k in chosen]
        probe = cams
        info.update(candidates=len(cand), gains=[round(g, 4) for g in sel_info["gains"]])
    if config.render_res is not None:
        res = max(scale, int(round(config.render_res / scale)) * scale)
    else:
        fps = [vsel.median_footprint(rasterize(c), materials, sizes) for c in probe]
        res = vsel.texel_density_resolution(
            fps,
            PROBE_RES,
            texel_footprint=config.texel_footprint,
            scale=scale,
            min_res=config.min_render_res,
            max_res=config.max_render_res,
        )
        info["probe_footprints"] = [None if f is None else round(f, 3) for f in fps]
    return [vsel.with_resolution(c, res) for c in cams], res, info


@dataclass
class TrainingViews:
    """The kept training views: ``cameras`` at the HR render resolution ``res``, their
    G-buffers ``gbs``, covered pixels ``npix`` per view; per image, ``seen`` (texels a visible
    triangle covers), ``islands`` (texels any triangle covers) and ``coverage`` (the fraction
    of island texels seen); ``info`` summarises the selection for the report."""

    cameras: list[cam.Camera]
    res: int
    info: dict
    gbs: GBufferStore
    npix: list[int]
    seen: dict[int, np.ndarray]
    islands: dict[int, np.ndarray]
    coverage: dict[int, float]

    def __len__(self) -> int:
        return len(self.cameras)


def training_views(
    mesh, materials, images, hr_sizes, scale, config: PbrsrConfig, rasterize, cameras, progress
) -> TrainingViews:
    """Choose (or take the ``cameras`` given), rasterise and keep the views that see the mesh."""
    emit(progress, Progress(stage="gbuffers", message="choosing views"))
    if cameras is not None:
        if not cameras:
            raise UnprocessableAsset("no training views were given")
        res = int(cameras[0].resolution[0])
        hr_cams, view_info = list(cameras), {"mode": "given"}
    else:
        hr_cams, res, view_info = choose_views(
            mesh, materials, images, hr_sizes, scale, config, rasterize
        )
    for c in hr_cams:
        h, w = c.resolution
        if h % scale or w % scale:
            raise UnprocessableAsset(f"render resolution {w}x{h} is not a multiple of x{scale}")
    gbs, keep = _rasterise_kept(hr_cams, rasterize, int(config.gbuffer_cache_mb) * 2**20, progress)
    vis = torch.unique(torch.cat([gbs.visible[k] for k in range(len(keep))]))
    seen = {i: vsel.uv_texel_mask(mesh, materials, i, hr_sizes[i], vis) for i in images}
    islands = {i: vsel.uv_texel_mask(mesh, materials, i, hr_sizes[i]) for i in images}
    coverage = {
        i: float((seen[i] & islands[i]).sum()) / max(int(islands[i].sum()), 1) for i in images
    }
    return TrainingViews(
        cameras=gbs.cameras,
        res=res,
        info=view_info,
        gbs=gbs,
        npix=[gbs.npix[k] for k in range(len(keep))],
        seen=seen,
        islands=islands,
        coverage=coverage,
    )


def _rasterise_kept(hr_cams, rasterize, budget: int, progress: ProgressFn | None):
    """Rasterise every camera once; a store of the views that cover a pixel (what is already
    rasterised moves over, nothing is redone) and the kept cameras' indices."""
    probe = GBufferStore(hr_cams, rasterize, budget)
    for k in range(len(hr_cams)):
        probe.get(k)
        emit(progress, Progress(stage="gbuffers", step=k + 1, total=len(hr_cams)))
    keep = [k for k in range(len(hr_cams)) if probe.npix[k] > 0]
    if not keep:
        raise UnprocessableAsset("no training view sees the mesh; is the mesh empty?")
    gbs = GBufferStore([hr_cams[k] for k in keep], rasterize, budget)
    for j, k in enumerate(keep):
        gbs.npix[j], gbs.visible[j] = probe.npix[k], probe.visible[k]
        if k in probe.items:
            gbs.items[j] = probe.items[k]
            gbs.bytes += gbuffer_bytes(probe.items[k])
    return gbs, keep
