"""The PBR-SR optimiser (paper section 3; METHOD.md): Adam over the HR maps and per-view weight
maps, minimising ``L_robust + lambda_pbr L_pbr + lambda_tv L_tv`` against pseudo-GT renders.

Stages (each timed and reported through ``progress``):

1. ``gbuffers``: choose the training views (paper sphere or texel coverage, views.py), pick the
   render resolution, rasterise every view once at the HR render resolution and at the LR one
   (res / scale). G-buffers never change while only textures are optimised.
2. ``pseudo_gt``: render each view from the init maps at LR resolution, tonemap, upscale by the
   prior; cached (pseudo_gt.py).
3. ``optimize``: per step, render ``batch_views`` whole views (or ``pixels_per_step`` random
   covered pixels across all views, ``sampling="pixels"``), compute the losses (losses.py),
   step Adam, project maps to valid ranges.

Parameters: one tensor per image in ``init_maps`` (an image shared by several materials is one
parameter; constant factors are not parameters). Only channels some material role reads get
gradients (alpha and unused channels keep their init), and with ``mask_unseen`` texels outside
every visible triangle's UV footprint keep their init.

Weight maps W_i are stored directly in [0, 1] (init 1) and clamped back into [0, 1] after each
step (projected gradient), rather than through a sigmoid: W = 1 is reachable, and at W = 1 the
regulariser's gradient vanishes, so W only moves where the pixel loss pushes it.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Collection
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from ..asset.model import Material, Mesh
from ..errors import UnprocessableAsset
from ..prior.direct import upscale_rgb
from ..progress import Eta, Progress, ProgressFn, emit
from ..render import camera as cam
from . import views as vsel
from .adam import FusedAdam
from .losses import (
    MapGroup,
    avg_pool_map,
    consistency_psnr,
    pooled_consistency,
    robust_pixel_terms,
    sample_weights,
    ssim_target,
    upsample_weights,
)
from .presets import PbrsrConfig
from .pseudo_gt import content_hash, load_cached, mapped, quantize, store_cached
from .ssim import SsimTarget
from .texel_ops import MapAdam, accumulate_map_grad_, project_

PROBE_RES = 128  # side of the low-resolution renders used to select views and measure density
BACKGROUND = 0.0


# ---------------------------------------------------------------------------------------------
# Maps: which channels are which PBR map, projection to valid ranges
# ---------------------------------------------------------------------------------------------


def map_groups(roles: set[str], channels: int, config: PbrsrConfig) -> list[MapGroup]:
    """The PBR maps inside one image, from the roles that read it (glTF packing: occlusion R,
    roughness G, metallic B; colour and normal RGB). Channels beyond the image's are dropped."""
    spec: list[tuple[str, tuple[int, ...], float]] = []
    if "base_color" in roles:
        spec.append(("base_color", (0, 1, 2), config.w_other))
    if "emissive" in roles:
        spec.append(("emissive", (0, 1, 2), config.w_other))
    if "normal" in roles:
        spec.append(("normal", (0, 1, 2), config.w_other))
    if "occlusion" in roles:
        spec.append(("occlusion", (0,), config.w_other))
    if "metallic_roughness" in roles:
        spec.append(("roughness", (1,), config.w_other))
        spec.append(("metallic", (2,), config.w_metallic))
    out, taken = [], set()
    for name, ch, w in spec:
        ch = tuple(c for c in ch if c < channels and c not in taken)
        if ch:
            taken.update(ch)
            out.append(MapGroup(name, ch, w))
    return out


def channel_lr(groups: list[MapGroup], channels: int, config: PbrsrConfig) -> torch.Tensor:
    """(C,) Adam learning rates of one image's channels: ``config.lr`` times the map's factor
    in ``config.map_lr``; channels no group owns get 0 (they keep their init)."""
    out = torch.zeros(channels, dtype=torch.float64)  # exact config values for Adam
    for g in groups:
        out[list(g.channels)] = config.lr * config.map_lr.get(g.name, 1.0)
    return out


# ---------------------------------------------------------------------------------------------
# G-buffer helpers (generic over the renderer's GBuffer dataclass fields)
# ---------------------------------------------------------------------------------------------


def _num_pixels(gb) -> int:
    return int(gb.pix.shape[0])


def subset_gbuffer(gb, idx: torch.Tensor):
    """The G-buffer restricted to covered pixels ``idx`` (indices into its P entries)."""
    p = _num_pixels(gb)
    changes = {}
    for f in fields(gb):
        v = getattr(gb, f.name)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == p:
            changes[f.name] = v[idx]
        elif isinstance(v, dict) and all(
            isinstance(x, torch.Tensor) and x.shape[0] == p for x in v.values()
        ):
            changes[f.name] = {k: x[idx] for k, x in v.items()}
    return replace(gb, **changes)


def concat_gbuffers(gbs: list):
    """One G-buffer holding the covered pixels of several (same-resolution) G-buffers."""
    first = gbs[0]
    p = _num_pixels(first)
    changes = {}
    for f in fields(first):
        v = getattr(first, f.name)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == p:
            changes[f.name] = torch.cat([getattr(g, f.name) for g in gbs])
        elif isinstance(v, dict) and all(
            isinstance(x, torch.Tensor) and x.shape[0] == p for x in v.values()
        ):
            changes[f.name] = {k: torch.cat([getattr(g, f.name)[k] for g in gbs]) for k in v}
    return replace(first, **changes)


def render_srgb(gb, materials, textures, light, shade_mod) -> torch.Tensor:
    """Shade the covered pixels of ``gb`` and tonemap: (P, 3) sRGB."""
    rgba = shade_mod.shade(gb, materials, textures, light)
    return shade_mod.tonemap(rgba[:, :3])


def gbuffer_bytes(gb) -> int:
    """Bytes held by a G-buffer's tensors."""
    n = 0
    for f in fields(gb):
        v = getattr(gb, f.name)
        vals = v.values() if isinstance(v, dict) else [v]
        n += sum(t.numel() * t.element_size() for t in vals if isinstance(t, torch.Tensor))
    return n


class GBufferStore:
    """The G-buffers of a fixed list of cameras, rasterised once each and kept while they fit
    in ``max_bytes`` (least recently used ones are dropped and rasterised again on demand: the
    paper's 750 views at 1024^2 would need ~80 GB). Records covered pixel counts and the
    triangles each view sees on the first pass."""

    def __init__(self, cameras: list, rasterize, max_bytes: int):
        self.cameras = cameras
        self.rasterize = rasterize
        self.max_bytes = max_bytes
        self.items: OrderedDict[int, object] = OrderedDict()
        self.bytes = 0
        self.npix: dict[int, int] = {}
        self.visible: dict[int, torch.Tensor] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def get(self, k: int):
        gb = self.items.get(k)
        if gb is not None:
            self.items.move_to_end(k)
            return gb
        gb = self.rasterize(self.cameras[k])
        if k not in self.npix:
            self.npix[k] = _num_pixels(gb)
            self.visible[k] = vsel.visible_triangles([gb])
        size = gbuffer_bytes(gb)
        if size <= self.max_bytes:
            self.items[k] = gb
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, old = self.items.popitem(last=False)
                self.bytes -= gbuffer_bytes(old)
        return gb


# ---------------------------------------------------------------------------------------------
# Pseudo-GT
PRIOR_CONTEXT = 16
"""LR pixels of context the prior gets around a view's covered pixels (the background beyond
is not run through it). RRDN's output changes < 1e-6 beyond 14 LR pixels from a cut edge
(prior/rrdn.py)."""


def covered_box(pix: torch.Tensor, resolution, step: int, context: int):
    """The box (y0, y1, x0, x1) of LR pixels (``step`` x ``step`` blocks of a ``resolution``
    (H, W) image) that hold a covered pixel of ``pix`` (flat indices), widened by ``context``
    and clipped to the LR image; None when no pixel is covered."""
    if pix.numel() == 0:
        return None
    h, w = int(resolution[0]), int(resolution[1])
    rows, cols = pix // w, pix % w
    lh, lw = h // step, w // step
    y0 = max(int(rows.min()) // step - context, 0)
    x0 = max(int(cols.min()) // step - context, 0)
    y1 = min(int(rows.max()) // step + 1 + context, lh)
    x1 = min(int(cols.max()) // step + 1 + context, lw)
    if y0 >= y1 or x0 >= x1:
        return None
    return y0, y1, x0, x1


def pseudo_gt_view(k, c, gbs, tex0, materials, light, prior, scale, config, rasterize, shade):
    """The pseudo-GT of training view ``k`` (camera ``c``): an LR render of the init maps,
    upscaled by the prior -> (sH, sW, 3) sRGB. The prior sees only the box around the view's
    covered pixels (:func:`covered_box`); the background beyond, which no loss reads, is
    bicubic.

    ``config.lr_render``: "supersample" renders the init maps at the HR resolution and
    area-averages s x s pixels (an antialiased LR render: the HR G-buffer is cached anyway);
    "raster" rasterises at LR resolution with one sample per pixel (aliased: with HR init maps
    each pixel point-samples one of s x s texels). ``config.target``: "prior" is the prior's
    output (the paper); "detail" adds only what the prior adds over bicubic to the HR render
    of the init maps, so silhouettes and shading keep the renderer's exact geometry.
    """
    import torch.nn.functional as F

    bg = torch.full((3,), BACKGROUND, device=tex0[next(iter(tex0))].device)
    h, w = c.resolution
    hr_img = None
    if config.lr_render == "supersample" or config.target == "detail":
        gb = gbs.get(k)
        hr_img = shade.to_image(gb, render_srgb(gb, materials, tex0, light, shade), bg)
    if config.lr_render == "supersample":
        lr_img = F.avg_pool2d(hr_img.permute(2, 0, 1)[None], scale)
        box = covered_box(gb.pix, (h, w), scale, PRIOR_CONTEXT)
    else:
        lgb = rasterize(vsel.with_resolution(c, (h // scale, w // scale)))
        lr_img = shade.to_image(lgb, render_srgb(lgb, materials, tex0, light, shade), bg)
        lr_img = lr_img.permute(2, 0, 1)[None]
        box = covered_box(lgb.pix, (h // scale, w // scale), 1, PRIOR_CONTEXT)
    base = F.interpolate(lr_img, scale_factor=scale, mode="bicubic", align_corners=False)
    up = base.clone()
    if box is not None:  # the prior where the object is (with context); no pixel beyond is used
        y0, y1, x0, x1 = box
        crop = lr_img[..., y0:y1, x0:x1].contiguous()
        up[..., y0 * scale : y1 * scale, x0 * scale : x1 * scale] = upscale_rgb(
            prior, crop, scale, max_prior_scale=config.max_prior_scale
        )
    if config.target == "detail":
        up = hr_img.permute(2, 0, 1)[None] + up - base
    return up.clamp(0.0, 1.0)[0].permute(1, 2, 0)


# ---------------------------------------------------------------------------------------------
# Result


@dataclass
class PbrsrResult:
    """What one run produced. ``maps``: image index -> (sH, sW, C) float32 HR map in
    optimisation space (valid ranges). ``history``: one dict per logged iteration (``it``,
    ``losses``, ``time``). ``timings``: seconds per stage. ``views``: the training views.
    ``coverage``: per image, fraction of UV-covered texels a view sees. ``consistency_psnr``:
    ``"<image>:<map>"`` -> PSNR (dB) of AvgPool_s(HR) against LR."""

    maps: dict[int, torch.Tensor]
    history: list[dict] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    views: list[dict] = field(default_factory=list)
    coverage: dict[int, float] = field(default_factory=dict)
    consistency_psnr: dict[str, float] = field(default_factory=dict)
    render_res: int = 0
    optimized: dict[int, list[str]] = field(default_factory=dict)
    seen_masks: dict[int, torch.Tensor] = field(default_factory=dict)
    config: dict = field(default_factory=dict)

    def report(self) -> dict:
        """JSON-serialisable summary for ``report.json``."""
        return {
            "config": self.config,
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
            "render_resolution": self.render_res,
            "views": self.views,
            "num_views": len(self.views),
            "coverage": {str(k): round(v, 4) for k, v in self.coverage.items()},
            "optimized_maps": {str(k): v for k, v in self.optimized.items()},
            "consistency_psnr_db": {k: round(v, 3) for k, v in self.consistency_psnr.items()},
            "history": self.history,
        }


# ---------------------------------------------------------------------------------------------
# The optimiser
# ---------------------------------------------------------------------------------------------


def _unoptimised(init_maps, lr_maps, roles, groups, images, scale, config, seed, device):
    """The result of a run with nothing to optimise (0 iterations, or every rate 0): the init
    maps in valid ranges, with their consistency against the LR maps."""
    maps = {}
    for i in images:
        maps[i] = init_maps[i].detach().to(device, torch.float32, copy=True)
        project_(maps[i], "normal" in roles[i])
    lr_dev = {i: lr_maps[i].detach().to(device, torch.float32) for i in images}
    return PbrsrResult(
        maps=maps,
        consistency_psnr={
            f"{i}:{g.name}": consistency_psnr(maps[i], lr_dev[i], scale, g)
            for i in images
            for g in groups[i]
        },
        optimized={i: [] for i in images},
        config={**config.to_dict(), "views": {"mode": "none"}, "seed": seed, "scale": scale},
    )


def _check_inputs(lr_maps, init_maps, roles, scale):
    if scale < 1:
        raise UnprocessableAsset(f"scale must be >= 1, got {scale}")
    if not init_maps:
        raise UnprocessableAsset("nothing to optimise: no texture maps were given")
    for i, t in init_maps.items():
        if i not in lr_maps:
            raise UnprocessableAsset(f"image {i} has an init map but no LR map")
        lr = lr_maps[i]
        if t.ndim != 3 or lr.ndim != 3:
            raise UnprocessableAsset(f"image {i}: maps must be (H, W, C)")
        want = (lr.shape[0] * scale, lr.shape[1] * scale, lr.shape[2])
        if tuple(t.shape) != want:
            raise UnprocessableAsset(
                f"image {i}: the init map is {tuple(t.shape)}, expected {want} (LR x{scale})"
            )
        if not roles.get(i):
            raise UnprocessableAsset(f"image {i} has no material role")


def _camera_dict(c: cam.Camera) -> dict:
    return {
        "eye": [round(float(x), 5) for x in c.eye],
        "fov_deg": c.fov_deg,
        "resolution": list(c.resolution),
    }


def _choose_views(mesh, materials, images, sizes, scale, config, rasterize):
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


def regularize_grads(
    params: dict[int, torch.Tensor],
    lr_maps: dict[int, torch.Tensor],
    ssim_targets: dict[int, SsimTarget],
    groups: dict[int, list[MapGroup]],
    grad_masks: dict[int, tuple[torch.Tensor, torch.Tensor]],
    config: PbrsrConfig,
    scale: int,
) -> tuple[float, float]:
    """The step's whole-map part, after the pixel loss's backward: add the PBR-consistency
    gradient (differentiated at LR size, on the pooled map) and TV's to each map's gradient
    and mask it, one pass per map (texel_ops). ``ssim_targets[i]``: ``ssim_target(lr_maps[i])``,
    made once per run; ``grad_masks[i]`` = ((H, W) texels, (C,) channels) that may change.
    Returns the values of ``L_pbr`` and ``L_tv``."""
    l_pbr_total, l_tv = 0.0, 0.0
    for i, p in params.items():
        if p.grad is None:  # no view of this batch samples the image
            p.grad = torch.zeros_like(p)
        pooled = avg_pool_map(p.detach(), scale).requires_grad_(True)
        l_pbr = pooled_consistency(
            pooled, lr_maps[i], groups[i], config.lambda_ssim, ssim_targets[i]
        )[0]
        pool_grad = torch.zeros_like(pooled)
        if l_pbr.requires_grad:
            (pool_grad,) = torch.autograd.grad(config.lambda_pbr * l_pbr, pooled)
        l_pbr_total += float(l_pbr.detach())
        l_tv += accumulate_map_grad_(
            p, p.grad, groups[i], config.lambda_tv, pool_grad, scale, *grad_masks[i]
        )
    return l_pbr_total, l_tv


def optimize_pbrsr(
    mesh: Mesh,
    materials: list[Material],
    lr_maps: dict[int, torch.Tensor],
    init_maps: dict[int, torch.Tensor],
    roles: dict[int, set[str]],
    *,
    scale: int,
    prior,
    light,
    config: PbrsrConfig,
    device: torch.device,
    progress: ProgressFn | None = None,
    cache_dir: Path | None = None,
    seed: int = 0,
    cameras: list[cam.Camera] | None = None,
    reference_maps: dict[int, torch.Tensor] | None = None,
    snapshot_at: Collection[int] = (),
    on_snapshot: Callable[[int, dict[int, torch.Tensor]], None] | None = None,
) -> PbrsrResult:
    """Optimise the HR maps of the images in ``init_maps`` (see the module docstring).

    Maps are keyed by glTF image index, (H, W, C) float32: colour maps linear, data maps as
    stored, normals encoded in [0, 1]; ``lr_maps`` (H, W, C), ``init_maps`` (sH, sW, C).
    ``mesh`` is normalised to unit size. ``prior.upscale((N, 3, h, w) sRGB, scale)`` makes the
    pseudo-GT. Test/benchmark hooks: ``cameras`` replaces view selection (their resolution is
    the HR render resolution, a multiple of ``scale``); ``reference_maps`` replaces the
    pseudo-GT by renders of those maps at the HR resolution (an oracle target, no prior);
    ``on_snapshot(it, maps)`` sees the maps before each iteration in ``snapshot_at`` (and
    after the last one, ``it == iterations``), for speed-against-error curves.
    ``progress`` may raise ``Cancelled``; it propagates.
    """
    from ..render import raster, shade  # imported here: the renderer is a heavy import

    _check_inputs(lr_maps, init_maps, roles, scale)
    if reference_maps is None and hasattr(prior, "check_scale"):
        prior.check_scale(scale)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    timings: dict[str, float] = {}
    mesh = mesh.to(device)
    images = sorted(init_maps)
    hr_sizes = {i: (int(init_maps[i].shape[0]), int(init_maps[i].shape[1])) for i in images}
    groups = {i: map_groups(roles[i], int(init_maps[i].shape[2]), config) for i in images}
    rates = {i: channel_lr(groups[i], int(init_maps[i].shape[2]), config) for i in images}
    # maps whose every rate is 0 (map_lr) keep their init: rendered, never differentiated;
    # with 0 iterations nothing is optimised: no views, no G-buffers, no pseudo-GT
    trained = [i for i in images if bool(rates[i].any())] if config.iterations else []

    def rasterize(c):
        return raster.rasterize(mesh, c).to(device)

    if not trained:  # nothing to optimise: no views, G-buffers, pseudo-GT or steps
        result = _unoptimised(
            init_maps, lr_maps, roles, groups, images, scale, config, seed, device
        )
        if on_snapshot is not None and 0 in snapshot_at:
            on_snapshot(0, result.maps)
        return result

    # ---- 1. views and G-buffers -------------------------------------------------------------
    t0 = time.perf_counter()
    emit(progress, Progress(stage="gbuffers", message="choosing views"))
    if cameras is not None:
        if not cameras:
            raise UnprocessableAsset("no training views were given")
        res = int(cameras[0].resolution[0])
        hr_cams, view_info = list(cameras), {"mode": "given"}
    else:
        hr_cams, res, view_info = _choose_views(
            mesh, materials, images, hr_sizes, scale, config, rasterize
        )
    for c in hr_cams:
        h, w = c.resolution
        if h % scale or w % scale:
            raise UnprocessableAsset(f"render resolution {w}x{h} is not a multiple of x{scale}")
    budget = int(config.gbuffer_cache_mb) * 2**20
    probe = GBufferStore(hr_cams, rasterize, budget)
    for k in range(len(hr_cams)):
        probe.get(k)
        emit(progress, Progress(stage="gbuffers", step=k + 1, total=len(hr_cams)))
    keep = [k for k in range(len(hr_cams)) if probe.npix[k] > 0]
    if not keep:
        raise UnprocessableAsset("no training view sees the mesh; is the mesh empty?")
    vis = torch.unique(torch.cat([probe.visible[k] for k in keep]))
    hr_cams = [hr_cams[k] for k in keep]
    gbs = GBufferStore(hr_cams, rasterize, budget)
    for j, k in enumerate(keep):  # move what is already rasterised; nothing is redone
        gbs.npix[j], gbs.visible[j] = probe.npix[k], probe.visible[k]
        if k in probe.items:
            gbs.items[j] = probe.items[k]
            gbs.bytes += gbuffer_bytes(probe.items[k])
    del probe
    n_views = len(hr_cams)
    npix = [gbs.npix[k] for k in range(n_views)]
    seen = {i: vsel.uv_texel_mask(mesh, materials, i, hr_sizes[i], vis) for i in images}
    islands = {i: vsel.uv_texel_mask(mesh, materials, i, hr_sizes[i]) for i in images}
    coverage = {
        i: float((seen[i] & islands[i]).sum()) / max(int(islands[i].sum()), 1) for i in images
    }
    timings["gbuffers"] = time.perf_counter() - t0

    # ---- 2. pseudo-GT -----------------------------------------------------------------------
    t0 = time.perf_counter()
    # own copies (projected in place below, then optimised in place as the parameters)
    init_dev = {i: init_maps[i].detach().to(device, torch.float32, copy=True) for i in images}
    lr_dev = {i: lr_maps[i].detach().to(device, torch.float32) for i in images}
    # images a material samples but that are not optimised render from their LR map
    static = {
        i: t.detach().to(device, torch.float32) for i, t in lr_maps.items() if i not in init_dev
    }
    for i in images:  # valid ranges from the start (the init is bicubic: normals not unit)
        project_(init_dev[i], "normal" in roles[i])
    targets: list[np.ndarray] = []
    with torch.no_grad():
        if reference_maps is not None:
            ref = {**static, **{i: t.to(device, torch.float32) for i, t in reference_maps.items()}}
            for k in range(n_views):
                gb = gbs.get(k)
                img = shade.to_image(
                    gb,
                    render_srgb(gb, materials, ref, light, shade),
                    torch.full((3,), BACKGROUND, device=device),
                )
                targets.append(quantize(img))
                emit(progress, Progress(stage="pseudo_gt", step=k + 1, total=n_views))
        else:
            common = content_hash(
                init_dev,
                static,
                mesh,
                materials,
                light,
                getattr(prior, "name", type(prior)),
                prior.uses_bf16() if hasattr(prior, "uses_bf16") else False,
                scale,
                BACKGROUND,
                config.lr_render,
                config.target,
                config.max_prior_scale,
                PRIOR_CONTEXT,
            )
            tex0 = {**static, **init_dev}
            for k, c in enumerate(hr_cams):
                key = content_hash(common, c.world_to_cam, c.proj, c.resolution)
                q = load_cached(key, cache_dir)
                if q is None:
                    up = pseudo_gt_view(
                        k, c, gbs, tex0, materials, light, prior, scale, config, rasterize, shade
                    )
                    q = quantize(up)
                    store_cached(key, q, cache_dir)
                # on disk: read through a memory map (750 paper targets are ~4.7 GB)
                targets.append(mapped(key, cache_dir, q))
                emit(progress, Progress(stage="pseudo_gt", step=k + 1, total=n_views))
    timings["pseudo_gt"] = time.perf_counter() - t0

    # ---- 3. optimise ------------------------------------------------------------------------
    t0 = time.perf_counter()
    params = {i: init_dev.pop(i).requires_grad_(True) for i in trained}
    fixed = {i: init_dev.pop(i) for i in images if i not in params}
    grad_masks = {}  # image -> ((H, W) texels, (C,) channels) that may change
    for i in trained:
        h, w, c = params[i].shape
        ch = torch.zeros(c, dtype=torch.bool, device=device)
        for g in groups[i]:
            ch[list(g.channels)] = True
        texel = (
            torch.from_numpy(seen[i]).to(device)
            if config.mask_unseen
            else torch.ones(h, w, dtype=torch.bool, device=device)
        )
        grad_masks[i] = (texel.contiguous(), ch)
    ssim_targets = {i: ssim_target(lr_dev[i]) for i in trained}
    wres = config.weight_map_res
    wmaps = torch.ones(n_views, wres, wres, device=device, requires_grad=True)
    map_opt = MapAdam(
        params,
        {i: rates[i] for i in trained},
        {i: "normal" in roles[i] for i in trained},
        {i: grad_masks[i][1] for i in trained},
    )
    wmap_opt = FusedAdam([(config.weight_map_lr, [wmaps])])

    def target(v: int, pix: torch.Tensor) -> torch.Tensor:  # (P, 3) pseudo-GT at pixels
        q = np.asarray(targets[v].reshape(-1, 3)[pix.cpu().numpy()], dtype=np.float32)
        return (torch.from_numpy(q) / 65535.0).to(device)

    offsets = torch.tensor([0, *np.cumsum(npix).tolist()], dtype=torch.long)
    order: list[int] = []
    history: list[dict] = []
    eta = Eta(config.iterations)

    def current() -> dict[int, torch.Tensor]:
        return {i: (params[i] if i in params else fixed[i]).detach() for i in images}

    def consistency_metrics() -> dict[str, float]:
        maps = current()
        return {
            f"{i}:{g.name}": consistency_psnr(maps[i], lr_dev[i], scale, g)
            for i in images
            for g in groups[i]
        }

    def snapshot(it: int) -> None:
        if on_snapshot is not None and it in snapshot_at:
            on_snapshot(it, current())

    for it in range(config.iterations):
        snapshot(it)
        textures = {**static, **fixed, **params}
        if config.sampling == "views":
            while len(order) < config.batch_views:
                order.extend(torch.randperm(n_views, generator=gen).tolist())
            batch, order = order[: config.batch_views], order[config.batch_views :]
            sq_all, w_all, v_all, cov_all = [], [], [], []
            for b, v in enumerate(batch):
                gb = gbs.get(v)
                h, w = gb.resolution
                pred = render_srgb(gb, materials, textures, light, shade)
                sq = ((pred - target(v, gb.pix)) ** 2).sum(-1)
                full = torch.zeros(h * w, dtype=sq.dtype, device=device).index_put((gb.pix,), sq)
                cov = torch.zeros(h * w, dtype=torch.bool, device=device)
                cov[gb.pix] = True
                wup = upsample_weights(wmaps[v : v + 1], (h, w)).reshape(-1)
                sq_all.append(full)
                w_all.append(wup)
                cov_all.append(cov)
                v_all.append(torch.full((h * w,), b, dtype=torch.long, device=device))
            l_pix, l_reg = robust_pixel_terms(
                torch.cat(sq_all),
                torch.cat(w_all),
                torch.cat(v_all),
                len(batch),
                torch.cat(cov_all),
            )
        else:
            total = int(offsets[-1])
            n = min(config.pixels_per_step, total)
            flat = torch.randint(total, (n,), generator=gen).sort().values
            vid = torch.searchsorted(offsets[1:], flat, right=True)
            local = flat - offsets[vid]
            present = torch.unique(vid).tolist()
            subs, tg, vv, xy = [], [], [], []
            for j, v in enumerate(present):
                sel = local[vid == v].to(device)
                sub = subset_gbuffer(gbs.get(v), sel)
                subs.append(sub)
                tg.append(target(v, sub.pix))
                h, w = sub.resolution
                px = (sub.pix % w).to(torch.float32)
                py = torch.div(sub.pix, w, rounding_mode="floor").to(torch.float32)
                xy.append(torch.stack([(2 * px + 1) / w - 1, (2 * py + 1) / h - 1], -1))
                vv.append(torch.full((sel.shape[0],), j, dtype=torch.long, device=device))
            pred = render_srgb(concat_gbuffers(subs), materials, textures, light, shade)
            sq = ((pred - torch.cat(tg)) ** 2).sum(-1)
            vcat = torch.cat(vv)
            wsel = wmaps[torch.tensor(present, device=device)]
            wv = sample_weights(wsel, vcat, torch.cat(xy))
            l_pix, l_reg = robust_pixel_terms(sq, wv, vcat, len(present))
            batch = present

        loss = config.lambda_pix * l_pix + config.lambda_reg * l_reg
        for t in (*params.values(), wmaps):
            t.grad = None
        loss.backward()
        l_pbr, l_tv = regularize_grads(
            params, lr_dev, ssim_targets, groups, grad_masks, config, scale
        )
        if wmaps.grad is None:
            wmaps.grad = torch.zeros_like(wmaps)
        torch.nan_to_num_(wmaps.grad, nan=0.0, posinf=0.0, neginf=0.0)
        map_opt.step()  # Adam, then the projection to valid ranges
        wmap_opt.step()
        with torch.no_grad():
            wmaps.clamp_(0.0, 1.0)

        done = it + 1
        if done % config.log_every == 0 or done == config.iterations or it == 0:
            losses = {
                "total": float(loss.detach()) + config.lambda_pbr * l_pbr + config.lambda_tv * l_tv,
                "pix": float(l_pix.detach()),
                "reg": float(l_reg.detach()),
                "pbr": l_pbr,
                "tv": l_tv,
            }
            metrics = consistency_metrics()
            history.append(
                {
                    "it": done,
                    "losses": losses,
                    "time": round(time.perf_counter() - t0, 4),
                    "views": list(batch) if config.sampling == "views" else len(batch),
                }
            )
            emit(
                progress,
                Progress(
                    stage="optimize",
                    step=done,
                    total=config.iterations,
                    losses=losses,
                    metrics=metrics,
                    eta_s=eta(done),
                ),
            )
    snapshot(config.iterations)
    timings["optimize"] = time.perf_counter() - t0

    maps = current()  # the parameters' own storage (detached): no copy of every HR map
    return PbrsrResult(
        maps=maps,
        history=history,
        timings=timings,
        views=[{**_camera_dict(c), "pixels": n} for c, n in zip(hr_cams, npix, strict=True)],
        coverage=coverage,
        consistency_psnr=consistency_metrics(),
        render_res=res,
        optimized={
            i: [g.name for g in groups[i] if bool(rates[i][list(g.channels)].any())] for i in images
        },
        seen_masks={i: torch.from_numpy(seen[i] & islands[i]) for i in images},
        config={**config.to_dict(), "views": view_info, "seed": seed, "scale": scale},
    )


__all__ = [
    "PbrsrResult",
    "channel_lr",
    "concat_gbuffers",
    "map_groups",
    "optimize_pbrsr",
    "regularize_grads",
    "subset_gbuffer",
]
