"""What a run of the optimiser hands back (:class:`PbrsrResult`), and how it is assembled: the
optimised maps with the training views, coverage and consistency they were made with, or
the init maps alone when there was nothing to optimise."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from .losses import MapGroup, consistency_psnr, map_factor
from .presets import PbrsrConfig
from .training_views import camera_dict
from .whole_map import project_


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


def consistency_metrics(maps, lr_maps, groups: dict[int, list[MapGroup]]):
    """``"<image>:<map>"`` -> PSNR (dB) of AvgPool_s(HR) against the LR map, ``s`` the map's
    own factor."""
    return {
        f"{i}:{g.name}": consistency_psnr(maps[i], lr_maps[i], map_factor(maps[i], lr_maps[i]), g)
        for i in maps
        for g in groups[i]
    }


def run_config(config: PbrsrConfig, view_info: dict, seed: int, scale: int) -> dict:
    """The numbers a run used, as its report lists them."""
    return {**config.to_dict(), "views": view_info, "seed": seed, "scale": scale}


def unoptimised_result(init_maps, lr_maps, roles, groups, images, scale, config, seed, device):
    """The result of a run with nothing to optimise (0 iterations, or every rate 0): the init
    maps in valid ranges, with their consistency against the LR maps."""
    maps = {}
    for i in images:
        maps[i] = init_maps[i].detach().to(device, torch.float32, copy=True)
        project_(maps[i], "normal" in roles[i])
    lr_dev = {i: lr_maps[i].detach().to(device, torch.float32) for i in images}
    return PbrsrResult(
        maps=maps,
        consistency_psnr=consistency_metrics(maps, lr_dev, groups),
        optimized={i: [] for i in images},
        config=run_config(config, {"mode": "none"}, seed, scale),
    )


def optimised_result(run, views, history, timings, lr_maps, groups, rates, config, seed, scale):
    """The result of a run that optimised: ``run``'s maps (its parameters' own storage, not a
    copy), the training ``views`` and what the steps logged."""
    maps = run.maps()
    return PbrsrResult(
        maps=maps,
        history=history,
        timings=timings,
        views=[
            {**camera_dict(c), "pixels": n} for c, n in zip(views.cameras, views.npix, strict=True)
        ],
        coverage=views.coverage,
        consistency_psnr=consistency_metrics(maps, lr_maps, groups),
        render_res=views.res,
        optimized={
            i: [g.name for g in groups[i] if bool(rates[i][list(g.channels)].any())] for i in maps
        },
        seen_masks={i: torch.from_numpy(views.seen[i] & views.islands[i]) for i in maps},
        config=run_config(config, views.info, seed, scale),
    )
