"""Stage 2 of the optimiser, ``pseudo_gt``: the target image of each training view. The
paper's pseudo-GT is an LR render of the init maps upscaled by the image prior
(:func:`pseudo_gt_view`); an oracle run renders reference maps instead. Targets are kept
quantised to 16 bits and cached by content (pseudo_gt.py)."""

from __future__ import annotations

import numpy as np
import torch

from ..prior.direct import upscale_rgb
from ..progress import Progress, emit
from . import views as vsel
from .gbuffers import BACKGROUND, RenderScene
from .pseudo_gt import content_hash, load_cached, mapped, quantize, store_cached

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


def pseudo_gt_view(k, c, gbs, tex0, scene: RenderScene, prior, scale, config):
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
        hr_img = scene.shade.to_image(gb, scene.render(gb, tex0), bg)
    if config.lr_render == "supersample":
        assert hr_img is not None  # rendered above
        lr_img = F.avg_pool2d(hr_img.permute(2, 0, 1)[None], scale)
        box = covered_box(gb.pix, (h, w), scale, PRIOR_CONTEXT)
    else:
        lgb = scene.rasterize(vsel.with_resolution(c, (h // scale, w // scale)))
        lr_img = scene.shade.to_image(lgb, scene.render(lgb, tex0), bg)
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
        assert hr_img is not None  # rendered above
        up = hr_img.permute(2, 0, 1)[None] + up - base
    return up.clamp(0.0, 1.0)[0].permute(1, 2, 0)


def make_targets(
    views,
    init_dev,
    static,
    scene: RenderScene,
    prior,
    scale: int,
    config,
    device,
    *,
    reference_maps=None,
    cache_dir=None,
    progress=None,
) -> list[np.ndarray]:
    """(H, W, 3) uint16 sRGB targets of every training view: renders of ``reference_maps``
    when given, else the pseudo-GT from the init maps (cached by content in ``cache_dir``)."""
    targets: list[np.ndarray] = []
    with torch.no_grad():
        if reference_maps is not None:
            ref = {**static, **{i: t.to(device, torch.float32) for i, t in reference_maps.items()}}
            bg = torch.full((3,), BACKGROUND, device=device)
            for k in range(len(views)):
                gb = views.gbs.get(k)
                img = scene.shade.to_image(gb, scene.render(gb, ref), bg)
                targets.append(quantize(img))
                emit(progress, Progress(stage="pseudo_gt", step=k + 1, total=len(views)))
            return targets
        common = content_hash(
            init_dev,
            static,
            scene.mesh,
            scene.materials,
            scene.light,
            getattr(prior, "name", type(prior)),
            prior.precision_in_use() if hasattr(prior, "precision_in_use") else "fp32",
            scale,
            BACKGROUND,
            config.lr_render,
            config.target,
            config.max_prior_scale,
            config.pseudo_gt_self_ensemble,
            PRIOR_CONTEXT,
        )
        tex0 = {**static, **init_dev}
        for k, c in enumerate(views.cameras):
            key = content_hash(common, c.world_to_cam, c.proj, c.resolution)
            q = load_cached(key, cache_dir)
            if q is None:
                up = pseudo_gt_view(k, c, views.gbs, tex0, scene, prior, scale, config)
                q = quantize(up)
                store_cached(key, q, cache_dir)
            # on disk: read through a memory map (750 paper targets are ~4.7 GB)
            targets.append(mapped(key, cache_dir, q))
            emit(progress, Progress(stage="pseudo_gt", step=k + 1, total=len(views)))
    return targets


def target_pixels(targets: list[np.ndarray], v: int, pix: torch.Tensor, device) -> torch.Tensor:
    """(P, 3) float sRGB target of view ``v`` at its flat pixel indices ``pix``."""
    q = np.asarray(targets[v].reshape(-1, 3)[pix.cpu().numpy()], dtype=np.float32)
    return (torch.from_numpy(q) / 65535.0).to(device)
