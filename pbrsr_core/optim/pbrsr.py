"""The PBR-SR optimiser (paper section 3; METHOD.md): Adam over the HR maps and per-view weight
maps, minimising ``L_robust + lambda_pbr L_pbr + lambda_tv L_tv`` against pseudo-GT renders.

Stages (each timed and reported through ``progress``):

1. ``gbuffers`` (training_views.py): choose the training views, pick the render resolution,
   rasterise every view once at the HR render resolution (gbuffers.py keeps them).
2. ``pseudo_gt`` (targets.py): render each view from the init maps at LR resolution, upscale
   by the prior; cached (pseudo_gt.py).
3. ``optimize`` (step.py, batch_loss.py, schedule.py): per step, render ``batch_views`` whole
   views (or ``pixels_per_step`` random covered pixels across all views,
   ``sampling="pixels"``), compute the losses (losses.py), step Adam, project maps to valid
   ranges.

Parameters: one tensor per image in ``init_maps`` (an image shared by several materials is one
parameter; constant factors are not parameters). Only channels some material role reads get
gradients (alpha and unused channels keep their init; groups.py), and with ``mask_unseen``
texels outside every visible triangle's UV footprint keep their init.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from pathlib import Path

import torch

from ..asset.model import Material, Mesh
from ..errors import UnprocessableAsset
from ..progress import Eta, Progress, ProgressFn, emit
from ..render import camera as cam
from .gbuffers import RenderScene
from .groups import map_groups
from .presets import PbrsrConfig
from .result import PbrsrResult, consistency_metrics, optimised_result, unoptimised_result
from .schedule import Snapshots, channel_lr, logged
from .step import Optimisation
from .targets import make_targets
from .training_views import training_views
from .whole_map import Repeats, project_


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
    repeats: dict[int, Repeats] | None = None,
    snapshot_at: Collection[int] = (),
    on_snapshot: Callable[[int, dict[int, torch.Tensor]], None] | None = None,
) -> PbrsrResult:
    """Optimise the HR maps of the images in ``init_maps`` (see the module docstring).

    Maps are keyed by glTF image index, (H, W, C) float32: colour maps linear, data maps as
    stored, normals encoded in [0, 1]; ``lr_maps`` (H, W, C), ``init_maps`` (sH, sW, C).
    ``mesh`` is normalised to unit size. ``prior.upscale((N, 3, h, w) sRGB, scale)`` makes the
    pseudo-GT. Test/benchmark hooks: ``cameras`` replaces view selection (their resolution is
    the HR render resolution, a multiple of ``scale``); ``repeats[i]``: whether map ``i``
    tiles along x and y (sampler REPEAT where the scene repeats it), so its TV wraps around;
    ``reference_maps`` replaces the
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
    mesh = mesh.to(device)
    images = sorted(init_maps)
    groups = {i: map_groups(roles[i], int(init_maps[i].shape[2]), config) for i in images}
    rates = {i: channel_lr(groups[i], int(init_maps[i].shape[2]), config) for i in images}
    # maps whose every rate is 0 (map_lr) keep their init: rendered, never differentiated;
    # with 0 iterations nothing is optimised: no views, no G-buffers, no pseudo-GT
    trained = [i for i in images if bool(rates[i].any())] if config.iterations else []
    if not trained:
        result = unoptimised_result(
            init_maps, lr_maps, roles, groups, images, scale, config, seed, device
        )
        if on_snapshot is not None and 0 in snapshot_at:
            on_snapshot(0, result.maps)
        return result

    def rasterize(c):
        return raster.rasterize(mesh, c).to(device)

    scene = RenderScene(mesh, materials, light, shade, rasterize)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    hr_sizes = {i: (int(init_maps[i].shape[0]), int(init_maps[i].shape[1])) for i in images}
    views = training_views(
        mesh, materials, images, hr_sizes, scale, config, rasterize, cameras, progress
    )
    timings["gbuffers"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    init_dev, lr_dev, static = _device_maps(init_maps, lr_maps, roles, images, device)
    targets = make_targets(
        views, init_dev, static, scene, prior, scale, config, device,
        reference_maps=reference_maps, cache_dir=cache_dir, progress=progress,
    )  # fmt: skip
    timings["pseudo_gt"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    params = {i: init_dev.pop(i).requires_grad_(True) for i in trained}
    fixed = {i: init_dev.pop(i) for i in images if i not in trained}
    normal = {i: "normal" in roles[i] for i in images}
    run = Optimisation(
        params, fixed, static, lr_dev, groups, rates, normal, views, targets, scene, config,
        gen, device, repeats,
    )  # fmt: skip
    snapshot = Snapshots(snapshot_at, on_snapshot, run.maps)
    history = _iterate(run, lr_dev, groups, config, scale, snapshot, progress, t0)
    timings["optimize"] = time.perf_counter() - t0
    return optimised_result(
        run, views, history, timings, lr_dev, groups, rates, config, seed, scale
    )


def _iterate(run: Optimisation, lr_dev, groups, config, scale, snapshot, progress, t0):
    """``config.iterations`` steps of ``run``; the logged iterations' history."""
    history: list[dict] = []
    eta = Eta(config.iterations)
    for it in range(config.iterations):
        snapshot(it)
        step = run.step()
        done = it + 1
        if logged(done, config):
            losses = step.report(config)
            metrics = consistency_metrics(run.maps(), lr_dev, groups)
            history.append(
                {
                    "it": done,
                    "losses": losses,
                    "time": round(time.perf_counter() - t0, 4),
                    "views": list(step.batch) if config.sampling == "views" else len(step.batch),
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
    return history


def _device_maps(init_maps, lr_maps, roles, images, device):
    """The run's own copies of the init maps on ``device`` in valid ranges (optimised in
    place as the parameters), the LR maps, and the LR maps of the images a material samples
    that are not optimised (rendered as they are)."""
    init_dev = {i: init_maps[i].detach().to(device, torch.float32, copy=True) for i in images}
    lr_dev = {i: lr_maps[i].detach().to(device, torch.float32) for i in images}
    static = {
        i: t.detach().to(device, torch.float32) for i, t in lr_maps.items() if i not in init_dev
    }
    for i in images:  # valid ranges from the start (the init is bicubic: normals not unit)
        project_(init_dev[i], "normal" in roles[i])
    return init_dev, lr_dev, static


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
        f = max(1, min(scale, int(t.shape[0]) // max(int(lr.shape[0]), 1)))  # its own factor
        want = (lr.shape[0] * f, lr.shape[1] * f, lr.shape[2])
        if tuple(t.shape) != want:
            raise UnprocessableAsset(
                f"image {i}: the init map is {tuple(t.shape)}, expected {want} (LR x{f}, "
                f"x1 to x{scale})"
            )
        if not roles.get(i):
            raise UnprocessableAsset(f"image {i} has no material role")


__all__ = ["PbrsrResult", "optimize_pbrsr"]
