"""Evaluation by the paper's protocol: PSNR of each map over the texels the mesh's UVs cover
(SSIM over the whole map), and PSNR of renderings from the evaluation views (predicted maps
against ground truth maps, same lighting). Keys: ``maps.<name>.psnr``, ``maps.<name>.ssim``,
``render.psnr``, and with several lights ``render.<light>.psnr`` per light.

A ground truth stored as JPEG has lost what its file drops (with 4:2:0, the chroma above half
the resolution: in an occlusion-roughness-metallic map, most of a metallic mask's edges).
:func:`stored_like` stores a prediction's maps the same way, so that the scores compare what
the ground truth's files can hold (``pbrsr eval --store-like-gt``, ``pbrsr bench upscale
--store-like-gt``)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from .asset import load_asset
from .asset.model import Asset
from .errors import UnprocessableAsset
from .optim.ssim import ssim_per_channel
from .render import camera as cam
from .render.light import EnvLight
from .scene import asset_textures, make_scene, procedural_light, render_views
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


def ssim(pred: np.ndarray, gt: np.ndarray) -> float:
    """Mean SSIM (Gaussian window 11, sigma 1.5) of (H, W, C) maps, channels averaged. Over
    the whole map: an SSIM window spans island borders, so masking it would not isolate
    covered texels anyway (PSNR is the masked metric)."""
    p = torch.from_numpy(pred.astype(np.float64)).permute(2, 0, 1)[None]
    g = torch.from_numpy(gt.astype(np.float64)).permute(2, 0, 1)[None]
    return float(ssim_per_channel(p, g).mean())


def stored_like(pred: Asset, gt: Asset) -> Asset:
    """``pred`` with each map whose ground truth is a JPEG file (one that asset/jpeg.py
    models: ``ImageData.jpeg``) stored as that file is, with its quantisation tables and
    chroma sampling (``jpeg.stored_as``), where the two maps have one size; its other maps
    as they are."""
    from .asset.jpeg import stored_as

    images = [
        dataclasses.replace(im, pixels=stored_as(im.pixels, ref.jpeg, deblocked=False))
        if ref.jpeg is not None and im.pixels.shape[:2] == ref.pixels.shape[:2]
        else im
        for im, ref in zip(pred.images, gt.images, strict=False)
    ]
    return dataclasses.replace(pred, images=images + list(pred.images[len(images) :]))


def images_for(asset: Asset, role: str) -> list[int]:
    """Indices of the images any material uses in ``role`` (each once, in material order)."""
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
        ids = images_for(gt, role)
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
            ss.append(ssim(pc, gc))
            ws.append(float(m.sum()))
        if ps:
            w = np.asarray(ws) / sum(ws)
            finite = [p if math.isfinite(p) else 100.0 for p in ps]
            out[f"maps.{name}.psnr"] = float(np.dot(w, finite))
            out[f"maps.{name}.ssim"] = float(np.dot(w, ss))
    return out


class RenderEvaluator:
    """Render PSNR of predicted maps against a ground-truth asset over fixed evaluation views
    and lights. Rasterises the views and renders the ground truth once, so evaluating many
    predictions (benchmark snapshots) costs only their shading."""

    def __init__(
        self,
        gt: Asset,
        *,
        cameras: list[cam.Camera],
        lights: list[EnvLight],
        device: torch.device | None = None,
    ):
        from .render import raster

        self.device = device or torch.device("cpu")
        self.scene = make_scene(gt, self.device)
        self.cameras = cameras
        self.lights = [light.to(self.device) for light in lights]
        self.gbuffers = [raster.rasterize(self.scene.mesh, c) for c in cameras]
        tex = asset_textures(gt, self.device)
        self.gt_images = [self._render(tex, light) for light in self.lights]

    def _render(self, textures, light) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        return render_views(self.scene, textures, self.cameras, light, gbuffers=self.gbuffers)

    def _light_keys(self) -> list[str]:
        """``render.<light>.psnr`` per light, named by the light (a repeated name numbered)."""
        keys: list[str] = []
        for light in self.lights:
            key, k = f"render.{light.name}.psnr", 2
            while key in keys:
                key, k = f"render.{light.name}#{k}.psnr", k + 1
            keys.append(key)
        return keys

    def __call__(self, pred: Asset) -> dict[str, float]:
        """``render.psnr`` over every view and light, and the same per light
        (:meth:`_light_keys`): a map's error can show under one light and not another (a
        highlight the tonemap clips hides errors of one sign)."""
        tex = asset_textures(pred, self.device)
        per_light = []
        for light, (img_gt, masks) in zip(self.lights, self.gt_images, strict=True):
            img_pr, _ = self._render(tex, light)
            sq, n = 0.0, 0
            for a, b, m in zip(img_pr, img_gt, masks, strict=True):
                d = ((a - b) ** 2)[m]
                sq += float(d.double().sum())
                n += int(d.numel())
            per_light.append((sq, n))
        out = {"render.psnr": _psnr_of(sum(s for s, _ in per_light), sum(n for _, n in per_light))}
        if len(self.lights) > 1:
            for key, (sq, n) in zip(self._light_keys(), per_light, strict=True):
                out[key] = _psnr_of(sq, n)
        return out


def _psnr_of(sq: float, n: int) -> float:
    """PSNR (peak 1) of a sum of ``n`` squared errors; NaN for none, inf for no error."""
    if n == 0:
        return float("nan")
    mse = sq / n
    return float("inf") if mse == 0 else 10 * math.log10(1 / mse)


def eval_cameras(resolution: int, num_views: int | None = None) -> list[cam.Camera]:
    """The paper's 240 evaluation views (6 x 40), or an even subset of ``num_views``."""
    cameras = cam.paper_eval_cameras((resolution, resolution))
    if num_views is not None and num_views < len(cameras):
        cameras = cameras[:: max(1, len(cameras) // num_views)][:num_views]
    return cameras


def evaluate(
    pred_path: Path,
    gt_path: Path,
    *,
    resolution: int = 256,
    envmaps: list[Path] | None = None,
    num_views: int | None = None,
    device: torch.device | None = None,
    store_like_gt: bool = False,
) -> dict[str, float]:
    """All metrics of a predicted asset against its ground truth; with ``store_like_gt``,
    of the prediction's maps stored as the ground truth's JPEG files are (:func:`stored_like`)."""
    pred, gt = load_asset(pred_path), load_asset(gt_path)
    if store_like_gt:
        pred = stored_like(pred, gt)
    out = map_metrics(pred, gt)
    lights = [EnvLight.from_file(p) for p in envmaps] if envmaps else [procedural_light()]
    evaluator = RenderEvaluator(
        gt, cameras=eval_cameras(resolution, num_views), lights=lights, device=device
    )
    out.update(evaluator(pred))
    out.update(seam_metrics(pred, gt))
    return out


def seam_metrics(pred: Asset, gt: Asset) -> dict[str, float]:
    """``seam.<image>.x|y`` for every map the scene shows repeating (maps.image_wrap): the
    predicted map's seam ratio over the ground truth's on that axis (1: the repeat is as
    seamless as the original's)."""
    from .maps import image_wrap

    out: dict[str, float] = {}
    for img in gt.images:
        wrap = image_wrap(gt, img.index) if img.roles else None
        if wrap is None or img.index >= len(pred.images):
            continue
        mine, ref = seam_ratio(pred.images[img.index].pixels), seam_ratio(img.pixels)
        for axis, name in ((0, "x"), (1, "y")):
            if wrap[axis] == "repeat" and ref[axis] > 0:
                out[f"seam.{img.index}.{name}"] = mine[axis] / ref[axis]
    return out


def seam_ratio(pixels: np.ndarray) -> tuple[float, float]:
    """(x, y): the mean absolute step across the map's wrap edge (last column to first; last
    row to first) over the mean step between neighbouring columns (rows) inside it. About 1
    for a map that tiles seamlessly; well above 1 where the repeat shows a seam."""
    a = np.asarray(pixels, dtype=np.float64)
    if a.ndim == 2:
        a = a[..., None]
    out = []
    for axis in (1, 0):
        inside = np.abs(np.diff(a, axis=axis)).mean()
        first = np.take(a, 0, axis=axis)
        last = np.take(a, -1, axis=axis)
        across = np.abs(first - last).mean()
        out.append(float(across / inside) if inside > 0 else (0.0 if across == 0 else np.inf))
    return out[0], out[1]
