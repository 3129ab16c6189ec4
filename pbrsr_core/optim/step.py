"""One optimisation step (stage 3, ``optimize``): render the batch, the pixel loss's backward,
the whole-map part of the gradient (PBR consistency and TV, :func:`regularize_grads`), then
Adam on the HR maps (projected to valid ranges) and on the per-view weight maps (clamped to
[0, 1]: a projected gradient, so W = 1 is reachable and the regulariser's gradient vanishes
there)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .adam import FusedAdam
from .batch_loss import pixel_batch_loss, view_batch_loss
from .gbuffers import RenderScene
from .losses import MapGroup, avg_pool_map, map_factor, pooled_consistency, ssim_target
from .presets import PbrsrConfig
from .schedule import ViewBatches
from .ssim import SsimTarget
from .training_views import TrainingViews
from .whole_map import MapAdam, Repeats, accumulate_map_grad_


def grad_masks(
    params: dict[int, torch.Tensor],
    groups: dict[int, list[MapGroup]],
    seen: dict[int, np.ndarray],
    mask_unseen: bool,
) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """Per map, the ((H, W) texels, (C,) channels) that may change: the channels a PBR map
    owns, and with ``mask_unseen`` only the texels a visible triangle covers."""
    out = {}
    for i, p in params.items():
        h, w, c = p.shape
        ch = torch.zeros(c, dtype=torch.bool, device=p.device)
        for g in groups[i]:
            ch[list(g.channels)] = True
        texel = (
            torch.from_numpy(seen[i]).to(p.device)
            if mask_unseen
            else torch.ones(h, w, dtype=torch.bool, device=p.device)
        )
        out[i] = (texel.contiguous(), ch)
    return out


def regularize_grads(
    params: dict[int, torch.Tensor],
    lr_maps: dict[int, torch.Tensor],
    ssim_targets: dict[int, SsimTarget],
    groups: dict[int, list[MapGroup]],
    grad_masks: dict[int, tuple[torch.Tensor, torch.Tensor]],
    config: PbrsrConfig,
    repeats: dict[int, Repeats] | None = None,
) -> tuple[float, float]:
    """The step's whole-map part, after the pixel loss's backward: add the PBR-consistency
    gradient (differentiated at LR size, on the pooled map) and TV's to each map's gradient
    and mask it, one pass per map (whole_map). ``ssim_targets[i]``: ``ssim_target(lr_maps[i])``,
    made once per run; ``grad_masks[i]`` = ((H, W) texels, (C,) channels) that may change;
    ``repeats[i]``: whether map i tiles along x and y (its TV wraps around; default no).
    Returns the values of ``L_pbr`` and ``L_tv``."""
    repeats = repeats or {}
    l_pbr_total, l_tv = 0.0, 0.0
    for i, p in params.items():
        if p.grad is None:  # no view of this batch samples the image
            p.grad = torch.zeros_like(p)
        scale = map_factor(p, lr_maps[i])  # each map at its own factor (max_size)
        pooled = avg_pool_map(p.detach(), scale).requires_grad_(True)
        l_pbr = pooled_consistency(
            pooled, lr_maps[i], groups[i], config.lambda_ssim, ssim_targets[i]
        )[0]
        pool_grad = torch.zeros_like(pooled)
        if l_pbr.requires_grad:
            (pool_grad,) = torch.autograd.grad(config.lambda_pbr * l_pbr, pooled)
        l_pbr_total += float(l_pbr.detach())
        l_tv += accumulate_map_grad_(
            p, p.grad, groups[i], config.lambda_tv, pool_grad, scale, *grad_masks[i],
            repeats.get(i, (False, False)),
        )  # fmt: skip
    return l_pbr_total, l_tv


@dataclass
class StepLosses:
    """What one step measured: the pixel part ``loss`` (a tensor), its terms, the whole-map
    terms' values and the views it rendered."""

    loss: torch.Tensor
    l_pix: torch.Tensor
    l_reg: torch.Tensor
    l_pbr: float
    l_tv: float
    batch: list[int]

    def report(self, config: PbrsrConfig) -> dict[str, float]:
        """The loss values as history and progress report them."""
        return {
            "total": float(self.loss.detach())
            + config.lambda_pbr * self.l_pbr
            + config.lambda_tv * self.l_tv,
            "pix": float(self.l_pix.detach()),
            "reg": float(self.l_reg.detach()),
            "pbr": self.l_pbr,
            "tv": self.l_tv,
        }


class Optimisation:
    """The state a run's steps share: the HR map parameters (``params``; ``fixed`` and
    ``static`` maps are rendered, never differentiated), the weight maps (one per view, init
    1) and their optimisers. ``rates[i]``: (C,) learning rates; ``normal[i]``: whether map
    ``i`` is a normal map; ``repeats[i]``: whether it tiles along x and y."""

    def __init__(
        self,
        params,
        fixed,
        static,
        lr_maps,
        groups,
        rates,
        normal,
        views: TrainingViews,
        targets,
        scene: RenderScene,
        config: PbrsrConfig,
        gen: torch.Generator,
        device,
        repeats: dict[int, Repeats] | None = None,
    ):
        self.params, self.fixed, self.static = params, fixed, static
        self.repeats = repeats or {}
        self.lr_maps, self.groups, self.views, self.targets = lr_maps, groups, views, targets
        self.scene = scene
        self.config, self.gen, self.device = config, gen, device
        self.grad_masks = grad_masks(params, groups, views.seen, config.mask_unseen)
        self.ssim_targets = {i: ssim_target(lr_maps[i]) for i in params}
        wres = config.weight_map_res
        self.wmaps = torch.ones(len(views), wres, wres, device=device, requires_grad=True)
        self.map_opt = MapAdam(
            params,
            {i: rates[i] for i in params},
            {i: normal[i] for i in params},
            {i: self.grad_masks[i][1] for i in params},
        )
        self.wmap_opt = FusedAdam([(config.weight_map_lr, [self.wmaps])])
        self.batches = ViewBatches(len(views), config.batch_views, gen)

    def maps(self) -> dict[int, torch.Tensor]:
        """Every image's current map (the parameters' own storage, detached)."""
        return {
            i: (self.params[i] if i in self.params else self.fixed[i]).detach()
            for i in sorted({**self.params, **self.fixed})
        }

    def pixel_loss(self) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
        """The batch's ``(L_pix, L_reg)`` from the current maps, and its views."""
        textures = {**self.static, **self.fixed, **self.params}

        def render(gb) -> torch.Tensor:
            return self.scene.render(gb, textures)

        gbs, cfg = self.views.gbs, self.config
        if cfg.sampling == "views":
            batch = self.batches.next()
            l_pix, l_reg = view_batch_loss(
                batch, gbs, self.targets, self.wmaps, render, self.device
            )
            return l_pix, l_reg, batch
        return pixel_batch_loss(
            cfg.pixels_per_step,
            self.views.npix,
            gbs,
            self.targets,
            self.wmaps,
            render,
            self.gen,
            self.device,
        )

    def step(self) -> StepLosses:
        """One iteration: losses, gradients, Adam, projection."""
        cfg = self.config
        l_pix, l_reg, batch = self.pixel_loss()
        loss = cfg.lambda_pix * l_pix + cfg.lambda_reg * l_reg
        for t in (*self.params.values(), self.wmaps):
            t.grad = None
        loss.backward()
        l_pbr, l_tv = regularize_grads(
            self.params,
            self.lr_maps,
            self.ssim_targets,
            self.groups,
            self.grad_masks,
            cfg,
            self.repeats,
        )
        wmaps = self.wmaps
        if wmaps.grad is None:
            wmaps.grad = torch.zeros_like(wmaps)
        torch.nan_to_num_(wmaps.grad, nan=0.0, posinf=0.0, neginf=0.0)
        self.map_opt.step()  # Adam, then the projection to valid ranges
        self.wmap_opt.step()
        with torch.no_grad():
            wmaps.clamp_(0.0, 1.0)
        return StepLosses(loss, l_pix, l_reg, l_pbr, l_tv, batch)
