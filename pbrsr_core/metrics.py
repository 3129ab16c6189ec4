"""Evaluation by the paper's protocol: PSNR and SSIM of each map over the texels the mesh's
UVs cover, and PSNR of renderings from the evaluation views (predicted maps against ground
truth maps, same lighting). Keys: ``maps.<name>.psnr``, ``maps.<name>.ssim``,
``render.psnr``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from .asset import load_asset
from .asset.model import Asset
from .errors import UnprocessableAsset
from .optim.ssim import ssim_map
from .render import camera as cam
from .render.light import EnvLight
from .scene import asset_textures, make_scene, render_views
from .uvmask import coverage_masks

# map name -> (role that holds it, channels of that image)
MAP_CHANNELS: dict[str, tuple[str, slice]] = {
    "albedo": ("base_color", slice(0, 3)),
    "roughness": ("metallic_roughness", slice(1, 2)),
    "metallic": ("metallic_roughness", slice(2, 3)),
    "normal": ("normal", slice(0, 3)),
    "occlusion": ("occlusion", slice(0, 1)),
    "emissive": ("emissive", slice(0, 3)),
}


def psnr(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB for values in [0, 1]; ``mask`` (H, W) selects texels. Identical -> inf."""
    diff = (pred.astype(np.float64) - gt.astype(np.float64)) ** 2
    if mask is not None:
        diff = diff[mask]
    if diff.size == 0:
        return float("nan")
    mse = float(diff.mean())
    return float("inf") if mse == 0 else 10.0 * math.log10(1.0 / mse)


def ssim(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM (Gaussian window 11, sigma 1.5) over the masked texels, channels averaged."""
    p = torch.from_numpy(pred.astype(np.float64)).permute(2, 0, 1)[None]
    g = torch.from_numpy(gt.astype(np.float64)).permute(2, 0, 1)[None]
    s = ssim_map(p, g)[0].mean(0).numpy()  # (H, W)
    if mask is not None:
        s = s[mask]
    return float(s.mean()) if s.size else float("nan")


def _images_for(asset: Asset, role: str) -> list[int]:
    seen: list[int] = []
    for m in asset.materials:
        ref = m.texture(role)  # type: ignore[arg-type]
        if ref is not None and ref.image not in seen:
            seen.append(ref.image)
    return seen


def map_metrics(pred: Asset, gt: Asset) -> dict[str, float]:
    """Per-map PSNR/SSIM of ``pred`` against ``gt`` (same document structure, any sizes are
    compared at the ground truth's size), over UV-covered texels, averaged over the images
    holding each map (weighted by covered texels)."""
    masks = coverage_masks(gt)
    out: dict[str, float] = {}
    for name, (role, ch) in MAP_CHANNELS.items():
        ids = _images_for(gt, role)
        if not ids:
            continue
        ps, ss, ws = [], [], []
        for i in ids:
            g, p = gt.images[i].pixels, pred.images[i].pixels
            if p.shape[:2] != g.shape[:2]:
                raise UnprocessableAsset(
                    f"image {i} ({gt.images[i].name}) is {p.shape[1]}x{p.shape[0]} in the "
                    f"prediction but {g.shape[1]}x{g.shape[0]} in the ground truth"
                )
            if g.shape[2] <= ch.start:
                continue
            gc, pc = g[..., ch], p[..., ch]
            m = masks[i]
            if not m.any():
                m = np.ones_like(m)
            ps.append(psnr(pc, gc, m))
            ss.append(ssim(pc, gc, m))
            ws.append(float(m.sum()))
        if ps:
            w = np.asarray(ws) / sum(ws)
            finite = [p if math.isfinite(p) else 100.0 for p in ps]
            out[f"maps.{name}.psnr"] = float(np.dot(w, finite))
            out[f"maps.{name}.ssim"] = float(np.dot(w, ss))
    return out


def render_metrics(
    pred: Asset,
    gt: Asset,
    *,
    resolution: int = 256,
    lights: list[EnvLight] | None = None,
    cameras: list[cam.Camera] | None = None,
    device: torch.device | None = None,
) -> dict[str, float]:
    """Render PSNR over the evaluation views (default: the paper's 240) under each light, on
    covered pixels of tonemapped sRGB renders."""
    device = device or torch.device("cpu")
    lights = lights or [EnvLight.procedural()]
    cameras = cameras or cam.paper_eval_cameras((resolution, resolution))
    scene = make_scene(gt, device)
    tex_gt = asset_textures(gt, device)
    tex_pred = asset_textures(pred, device)
    from .render import raster

    gbs = [raster.rasterize(scene.mesh, c) for c in cameras]
    sq, n = 0.0, 0
    for light in lights:
        light = light.to(device)
        img_gt, masks = render_views(scene, tex_gt, cameras, light, gbuffers=gbs)
        img_pr, _ = render_views(scene, tex_pred, cameras, light, gbuffers=gbs)
        for a, b, m in zip(img_pr, img_gt, masks, strict=True):
            d = ((a - b) ** 2)[m]
            sq += float(d.double().sum())
            n += int(d.numel())
    if n == 0:
        return {"render.psnr": float("nan")}
    mse = sq / n
    return {"render.psnr": float("inf") if mse == 0 else 10 * math.log10(1 / mse)}


def evaluate(
    pred_path: Path,
    gt_path: Path,
    *,
    resolution: int = 256,
    envmaps: list[Path] | None = None,
    num_views: int | None = None,
    device: torch.device | None = None,
) -> dict[str, float]:
    """All metrics of a predicted asset against its ground truth."""
    pred, gt = load_asset(pred_path), load_asset(gt_path)
    out = map_metrics(pred, gt)
    lights = [EnvLight.from_file(p) for p in envmaps] if envmaps else None
    cameras = cam.paper_eval_cameras((resolution, resolution))
    if num_views is not None:
        cameras = cameras[:: max(1, len(cameras) // num_views)][:num_views]
    out.update(
        render_metrics(pred, gt, resolution=resolution, lights=lights, cameras=cameras,
                       device=device)
    )
    return out
