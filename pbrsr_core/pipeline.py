"""One upscale run, for every method: load, upscale the maps, write the bundle.

The bundle written into ``out_dir``:
``<input file name>`` the upscaled asset in the input's form; ``maps/`` every HR map as an
image; ``report.json``; ``preview.png`` (before/after under two environments) and
``previews/{before,after}_<env>.png``. The bundle is written into a sibling staging folder and
renamed into place, so nobody ever sees half of one.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from . import __version__
from .allocator import reuse_large_blocks
from .asset import (
    detect_kind,
    encode_images,
    extract_zip,
    load_asset,
    save_asset,
    write_image,
)
from .asset.model import MAP_ROLES, Asset
from .crops import write_map_crops
from .device import resolve_device
from .errors import PbrsrError, StorageError, UnprocessableAsset
from .footprint import check_memory, estimate_peak_bytes
from .limits import Limits, check_output_size
from .maps import (
    encoded_to_param,
    image_cutout,
    image_wrap,
    kind_of,
    map_file_stem,
    param_to_encoded,
    role_label,
    upscalable_images,
)
from .metrics import seam_ratio
from .options import UpscaleOptions
from .preview import write_previews
from .prior import load_prior
from .prior.blend import MARGIN, blend, blend_check
from .prior.direct import (
    bicubic_map,
    filled_cutout,
    keep_normal_length,
    project_map,
    restore_hidden,
    upscale_map,
)
from .prior.guided import CHANNELS as GUIDED_CHANNELS
from .prior.guided import guide_pairs, guided_check_upscale, guided_upscale
from .prior.selfcheck import (
    chosen,
    merge_channels,
    prior_self_check,
    upscale_channels,
    upscale_each,
)
from .progress import Progress, ProgressFn, emit
from .render.light import EnvLight
from .scene import make_scene, procedural_light
from .uvmask import coverage_masks

if TYPE_CHECKING:
    from .optim.presets import PbrsrConfig


class StageTimer:
    """Wall seconds per named stage, in order."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0


def _resolve_input(input_path: Path, work_dir: Path, limits: Limits) -> Path:
    kind = detect_kind(input_path)
    if kind == "zip":
        return extract_zip(input_path, work_dir / "unzipped", limits)
    return input_path


def _check_footprint(images, options: UpscaleOptions, config, budget: int) -> None:
    from .optim.presets import get_preset

    if options.method == "pbrsr" and config is None:
        config = get_preset(options.preset)
    sizes = [(img.width, img.height, int(img.pixels.shape[2])) for img in images]
    what = (
        f"x{options.scale} of {len(images)} maps (largest {max(max(w, h) for w, h, _ in sizes)} px)"
    )
    if options.method == "pbrsr":
        what += f" with the {options.preset} preset"
    estimate = estimate_peak_bytes(sizes, options.scale, options.method, config)
    check_memory(estimate, budget, what)


def load_light(envmap: str | None) -> EnvLight:
    return procedural_light() if not envmap else EnvLight.from_file(Path(envmap))


def _upscale_maps(
    asset: Asset,
    options: UpscaleOptions,
    device: torch.device,
    timer: StageTimer,
    progress: ProgressFn | None,
    work_dir: Path,
    snapshots: Snapshots | None = None,
    config: PbrsrConfig | None = None,
) -> tuple[dict[int, np.ndarray], dict]:
    """HR maps (stored encoding) for every used image, and method-specific report fields."""
    images = upscalable_images(asset)
    s = options.scale
    wraps = {img.index: image_wrap(asset, img.index) for img in images}  # tiling maps
    cutouts = {img.index: image_cutout(asset, img.index) for img in images}
    if options.method == "bicubic":
        with timer("upscale"):
            return {
                img.index: bicubic_map(
                    img.pixels, kind_of(img.roles), s, wraps[img.index], cutouts[img.index]
                )
                for img in images
            }, {}

    with timer("load_prior"):
        emit(progress, Progress(stage="load_prior", message=options.prior))
        prior = load_prior(options.prior, device)
    if options.method == "direct":
        from .optim.presets import BALANCED, CHECK_PRIOR_CPU

        # where the prior offers candidates, the self-check picks one per colour and data map
        offered = [img for img in images if len(prior.candidates(kind_of(img.roles))) > 1]
        lr_pixels = {img.index: img.pixels for img in offered}
        found = _self_checks(asset, offered, prior, lr_pixels, s, CHECK_PRIOR_CPU, None, timer,
                             progress)  # fmt: skip
        picks = {
            img.index: _unread_channels_follow(
                chosen(prior, kind_of(img.roles), found.get(img.index), 1),
                prior_channels(img, BALANCED),
            )
            for img in offered
        }
        out = {}
        with timer("prior"):
            tiles = MapProgress(progress, "prior", images)
            for img in images:
                kind = kind_of(img.roles)
                out[img.index] = upscale_channels(
                    picks.get(img.index, [prior]), img.pixels, kind, s, progress=tiles.on(img),
                    wrap=wraps[img.index], cutout=cutouts[img.index],
                )  # fmt: skip
        names = {img.index: img.name for img in images}
        return out, {
            "prior_picks": {names[i]: [p.name for p in ps] for i, ps in picks.items()}
        } if picks else {}

    from .optim.presets import get_preset

    config = config or get_preset(options.preset)
    lr_pixels, deblocked = _deblocked(images, config, timer)
    for img in images:  # a cutout's hidden colour takes no part (init, losses, projection)
        if (seen_from := cutouts[img.index]) is not None:
            lr_pixels[img.index] = filled_cutout(lr_pixels[img.index], seen_from)
    kept: dict[int, dict] | None = {} if config.blend_data else None
    channels, checks, sources = _prior_channels_checked(asset, images, prior, lr_pixels, s,
                                                        config, timer, progress, kept)  # fmt: skip
    blends = _blended_channels(asset, images, prior, channels, checks, sources, kept, lr_pixels,
                               config, timer)  # fmt: skip
    del kept
    init_encoded, init, lr = _init_maps(images, sources, blends, lr_pixels, s, wraps, config,
                                        timer, progress)  # fmt: skip
    if checks is not None and not any(any(c) for c in channels.values()):
        prior = load_prior("bicubic", device)  # for the pseudo-GT
    out, report = _optimise(
        asset, images, init_encoded, init, lr, lr_pixels, channels, prior, options, config,
        device, timer, progress, work_dir, snapshots, wraps,
    )  # fmt: skip
    for img in images:
        if cutouts[img.index] is not None:
            out[img.index] = restore_hidden(out[img.index], img.pixels, s)
    return out, {
        **report,
        "prior_check": checks,
        "prior_used": prior.name,
        "prior_init": sorted(img.name for img in images if any(channels[img.index])),
        "jpeg_deblocked": deblocked,
    }


class MapProgress:
    """Progress of a stage that runs the prior over several maps, tile by tile: the fraction
    of all the maps' pixels done (out of ``STEPS``), the map and tile in the message, and an
    ETA from the time per pixel so far."""

    STEPS = 1000

    def __init__(self, progress: ProgressFn | None, stage: str, images) -> None:
        self.progress, self.stage = progress, stage
        self.pixels = {img.index: img.width * img.height for img in images}
        self.before: dict[int, int] = {}
        done = 0
        for img in images:
            self.before[img.index] = done
            done += self.pixels[img.index]
        self.total = max(done, 1)
        self.t0 = time.perf_counter()
        emit(progress, Progress(stage=stage, step=0, total=self.STEPS))

    def on(self, img) -> Callable[[int, int], None]:
        """The prior's tile callback for ``img``: ``(tiles done, tiles)``."""

        def tile(done: int, total: int) -> None:
            pixels = self.before[img.index] + self.pixels[img.index] * done / max(total, 1)
            fraction = pixels / self.total
            elapsed = time.perf_counter() - self.t0
            eta = elapsed * (1 - fraction) / fraction if fraction > 0 else None
            event = Progress(
                stage=self.stage,
                step=int(self.STEPS * fraction),
                total=self.STEPS,
                eta_s=eta,
                message=f"{img.name}: tile {done}/{total}",
            )
            emit(self.progress, event)

        return tile


def _deblocked(images, config: PbrsrConfig, timer: StageTimer):
    """The LR maps as the method sees them: JPEG block artefacts reduced with the file's own
    tables (asset/jpeg.py) when the preset says so, so that the consistency term does not copy
    them to the HR maps; and the names of the images deblocked."""
    from .asset.jpeg import deblock

    lr_pixels = {img.index: img.pixels for img in images}
    deblocked = []
    if config.deblock_jpeg:
        with timer("deblock"):
            for img in images:
                if img.jpeg is not None:
                    lr_pixels[img.index] = deblock(img.pixels, img.jpeg)
                    deblocked.append(img.name)
    return lr_pixels, deblocked


def _self_checks(asset, images, prior, lr_pixels, s, kinds, max_prior_scale, timer, progress,
                 kept=None):  # fmt: skip
    """The self-check (prior/selfcheck.py) of each image of a kind in ``kinds``, over the
    texels a viewer sees: {image index: report, or None for a map too small to check}.
    ``kept``: filled with {data image index: what its check compared}."""
    checks: dict[int, dict | None] = {}
    todo = [img for img in images if kind_of(img.roles) in kinds]
    if not todo:
        return checks
    with timer("prior_check"):
        emit(progress, Progress(stage="prior_check"))
        covered = coverage_masks(asset)  # at the LR size: the texels the check compares
        for img in todo:
            seen = covered.get(img.index)
            hidden_to = image_cutout(asset, img.index)
            if hidden_to is not None:  # score the texels a viewer can see
                px = img.pixels
                visible = px[..., px.shape[2] - 1] > hidden_to
                seen = visible if seen is None else seen & visible
            checks[img.index] = prior_self_check(
                prior,
                lr_pixels[img.index],
                s,
                kind_of(img.roles),
                max_prior_scale=max_prior_scale,
                covered=seen,
                cutout=hidden_to,
                keep=kept.setdefault(img.index, {})
                if kept is not None and kind_of(img.roles) == "data"
                else None,
            )
    return checks


def _prior_channels_checked(asset, images, prior, lr_pixels, s, config, timer, progress,
                            kept=None):  # fmt: skip
    """Which channels of each image the prior initialises (paper 3.1: the maps the preset
    names in ``prior_maps``; an ORM image's channels one by one; bicubic the rest), and with
    ``check_prior`` only those where the prior beats bicubic one scale down (``kept``: as
    :func:`_self_checks` fills it). Returns
    ({image: [bool per channel]}, the self-check reports or None when nothing was checked,
    {image: per channel, the prior's candidate the check chose, or None for bicubic})."""
    channels = {img.index: prior_channels(img, config) for img in images}
    if not (config.check_prior and prior.name != "bicubic" and any(map(any, channels.values()))):
        return channels, None, {i: [prior if c else None for c in ch] for i, ch in channels.items()}
    used = [img for img in images if any(channels[img.index])]
    found = _self_checks(asset, used, prior, lr_pixels, s, set(config.check_prior),
                         config.max_prior_scale, timer, progress, kept)  # fmt: skip
    checks: list[dict] = []
    for img in used:
        kind = kind_of(img.roles)
        if img.index not in found:
            note = {"use_prior": True, "note": f"{kind} maps are not checked"}
            checks.append({"image": img.name, "index": img.index, **note})
            continue
        c = found[img.index]
        too_small = {"use_prior": True, "note": f"under {4 * s} texels a side"}
        if c is not None:
            use = [a and b for a, b in zip(channels[img.index], c["channels"], strict=True)]
            c = {**c, "channels": use, "use_prior": any(use)}
            channels[img.index] = use
        checks.append({"image": img.name, "index": img.index, **(c or too_small)})
    sources = {
        img.index: [
            p if use else None
            for p, use in zip(
                chosen(prior, kind_of(img.roles), found.get(img.index), len(channels[img.index])),
                channels[img.index],
                strict=True,
            )
        ]
        for img in used
    }
    return channels, checks, sources


def _blended_channels(asset, images, prior, channels, checks, sources, kept, lr_pixels, config,
                      timer):  # fmt: skip
    """With ``blend_data``: each checked data map's channels (those the preset lets a prior
    initialise) as a blend of the prior's candidates, bicubic and, for the roughness and
    metallic of a metallic-roughness map, the upscale guided by its colour map
    (prior/blend.py, prior/guided.py), weighted one scale down from the upscales its check
    compared (``kept``); a channel whose blend beats bicubic by less than ``MARGIN`` stays
    bicubic's. Updates ``channels``, ``sources`` (None: blended or bicubic) and the ``checks``
    entries (``blend``); returns {image: (the blend's sources, a candidate or "guided"; per
    channel their weights; the guide image or None)}."""
    if not config.blend_data or checks is None or not kept:
        return {}
    by_index = {img.index: img for img in images}
    entries = {c["index"]: c for c in checks if "margins" in c}
    pairs = guide_pairs(asset, set(by_index))
    blends = {}
    with timer("prior_check"):
        for i, k in kept.items():
            if i not in entries or not k:
                continue
            n = len(channels[i])
            todo = [c for c, ok in enumerate(prior_channels(by_index[i], config)) if ok]
            guided, g = {}, pairs.get(i)
            gc = [c for c in GUIDED_CHANNELS if c in todo]
            if g is not None and gc:
                src = (sources.get(g) or [None])[0]

                def upscale_guide(px, f, src=src):
                    if src is None:
                        return bicubic_map(px, "colour", f)
                    return upscale_map(src, px, "colour", f, max_prior_scale=config.max_prior_scale)

                size = lr_pixels[i].shape[:2]
                up = guided_check_upscale(k, size, lr_pixels[g], upscale_guide, gc)
                guided = {c: up[..., m] for m, c in enumerate(gc)}
            fits = blend_check(k, todo, guided)
            names = list(k["ups"]) + (["guided"] if guided else [])
            weights = [[0.0] * len(names) for _ in range(n)]
            use = [False] * n
            for c, (fit_names, w, gain) in fits.items():
                if gain > MARGIN:
                    use[c] = True
                    for name, wk in zip(fit_names, w, strict=True):
                        weights[c][names.index(name)] = wk
            kept_at = [m for m in range(len(names)) if any(w[m] for w in weights)]
            names, weights = [names[m] for m in kept_at], [[w[m] for m in kept_at] for w in weights]
            guide = g if "guided" in names else None
            entry = entries[i]
            entry["blend"] = {  # the upscales the run blends (each network runs once)
                "sources": names,
                "guide": by_index[g].name if guide is not None and g is not None else None,
                "weights": weights,
                "margins": [fits[c][2] if c in fits else None for c in range(n)],
            }
            entry["channels"], entry["use_prior"] = use, any(use)
            channels[i], sources[i] = use, [None] * n
            if any(use):
                by_name = {p.name: p for p in prior.candidates(kind_of(by_index[i].roles))}
                blends[i] = ([by_name.get(m, "guided") for m in names], weights, guide)
    return blends


def _init_maps(images, sources, blends, lr_pixels, s, wraps, config, timer, progress):
    """The optimiser's start: bicubic, with a prior's upscale in the channels ``sources``
    gives one for (per image, per channel: the prior or None), and the blends of ``blends``
    (:func:`_blended_channels`; the colour maps that guide one come first). Returns
    ({image: HR map, stored encoding}, the same as optimisation parameters, the LR maps as
    parameters)."""
    init_encoded, init, lr = {}, {}, {}
    leading = {g for _, _, g in blends.values() if g is not None}
    order = sorted(images, key=lambda im: im.index not in leading)
    with timer("init"):
        tiles = MapProgress(progress, "init", order)
        for img in order:
            kind = kind_of(img.roles)
            px = lr_pixels[img.index]
            hr = bicubic_map(px, kind, s, wraps[img.index])  # px: a cutout's already filled
            tiles.on(img)(0, 1)
            if img.index in blends:  # hr is this call's own array
                hr = _blend_map(hr, px, blends[img.index], init_encoded, lr_pixels, s, kind,
                                wraps[img.index], config, tiles.on(img))  # fmt: skip
            else:
                hr = upscale_channels(sources.get(img.index, [None]), px, kind, s, hr,
                                      max_prior_scale=config.max_prior_scale,
                                      progress=tiles.on(img), wrap=wraps[img.index])  # fmt: skip
            tiles.on(img)(1, 1)  # done, whether a prior ran on it or not
            init_encoded[img.index] = hr
            init[img.index] = encoded_to_param(torch.from_numpy(hr), kind)
            lr[img.index] = encoded_to_param(torch.from_numpy(px), kind)
    return init_encoded, init, lr


def _blend_map(bicubic, px, how, init_encoded, lr_pixels, s, kind, wrap, config, progress):
    """A data map whose channels blend its upscales (``how``, as :func:`_blended_channels`
    gives it) over ``bicubic`` (this call's own array: the blended channels are written into
    it); the guide's HR map is in ``init_encoded``."""
    sources, weights, g = how
    priors = [p for p in sources if not isinstance(p, str)]
    ups = upscale_each(priors, px, kind, s, max_prior_scale=config.max_prior_scale,
                       progress=progress, wrap=wrap)  # fmt: skip
    by_source = dict(zip(priors, ups, strict=True))
    guided = {}
    if g is not None:
        k = sources.index("guided")
        gc = [c for c in GUIDED_CHANNELS if c < len(weights) and weights[c][k]]
        up = guided_upscale(px[..., gc], lr_pixels[g], init_encoded[g], s)
        guided = {c: up[..., m] for m, c in enumerate(gc)}
    for c, w in enumerate(weights):
        if any(w):
            bic = bicubic[..., c]
            chans = [guided.get(c, bic) if p == "guided" else by_source[p][..., c] for p in sources]
            bicubic[..., c] = blend(chans, bic, w)
    return bicubic


def _optimise(asset, images, init_encoded, init, lr, lr_pixels, channels, prior, options, config,
              device, timer, progress, work_dir, snapshots, wraps):  # fmt: skip
    """PBR-SR's optimisation from ``init_encoded``, then each map's export: back-projection
    onto its LR map where the preset says so, and island padding. A map the scene repeats
    (``wraps``) keeps its TV across the wrap edge. Returns (HR maps, report)."""
    from .optim.pbrsr import optimize_pbrsr
    from .optim.whole_map import pad_update

    s = options.scale
    kinds = {img.index: kind_of(img.roles) for img in images}
    with timer("load_light"):
        light = load_light(options.envmap).to(device)
    scene = make_scene(asset, device)
    # project_lr: only what the (back-projected) prior initialised goes back onto its LR map
    projected = {
        i: channels[i]
        if any(channels[i]) and prior.back_project and kinds[i] in config.project_lr
        else [False] * len(channels[i])
        for i in kinds
    }

    def export(i: int, t: torch.Tensor) -> np.ndarray:
        return _export_map(t, kinds[i], lr_pixels[i], s, projected[i])

    result = optimize_pbrsr(
        scene.mesh,
        asset.materials,
        {k: v.to(device) for k, v in lr.items()},
        {k: v.to(device) for k, v in init.items()},
        {img.index: set(img.roles) for img in images},
        scale=s,
        prior=prior
        if config.pseudo_gt_prior is None
        else load_prior(config.pseudo_gt_prior, device),
        light=light,
        config=config,
        device=device,
        progress=progress,
        cache_dir=work_dir / "pseudo_gt",
        seed=options.seed,
        repeats={i: (w[0] == "repeat", w[1] == "repeat") for i, w in wraps.items() if w},
        **_snapshot_kwargs(snapshots, lambda maps: {i: export(i, t) for i, t in maps.items()}),
    )
    for k, v in result.timings.items():
        timer.seconds[k] = timer.seconds.get(k, 0.0) + v
    init.clear()  # the HR maps live on in result.maps, init_encoded and final only
    with timer("project"):
        final = {}
        for i in list(result.maps):  # one HR map at a time, each released once exported
            final[i] = export(i, result.maps.pop(i))
    with timer("dilate"):
        sizes = {i: tuple(t.shape[:2]) for i, t in final.items()}
        islands = coverage_masks(asset, sizes)
        out = {
            i: pad_update(t, init_encoded[i], islands[i], 2 * s, normal=kinds[i] == "normal")
            for i, t in final.items()
        }
    return out, result.report()


def _export_map(
    t: torch.Tensor, kind: str, lr: np.ndarray, scale: int, projected: list[bool]
) -> np.ndarray:
    """One optimised map (optimisation space) -> stored encoding, with the channels
    ``projected`` names (one entry for colour and normal maps, one per channel for data maps)
    back-projected onto its LR map; a normal map at its LR map's length
    (:func:`~.prior.direct.keep_normal_length`)."""
    hr = param_to_encoded(t, kind)
    if any(projected):
        hr = merge_channels(project_map(hr, lr, scale, kind), hr, projected)
    elif kind == "normal":
        hr = keep_normal_length(hr, lr, scale)
    return hr


def _unread_channels_follow(picks: list, read: list[bool]) -> list:
    """``picks`` per channel with a channel no material reads (the R of a metallic-roughness
    image without occlusion) given the prior of the first channel that is read, so that it
    runs no prior of its own."""
    if len(picks) != len(read) or not any(read):
        return picks
    first = picks[read.index(True)]
    return [p if r else first for p, r in zip(picks, read, strict=True)]


def prior_channels(img, config) -> list[bool]:
    """Which of an image's colour channels the preset lets the prior initialise: one entry
    for colour and normal maps (the image as a whole), one per channel for data maps (an ORM
    image's occlusion, roughness and metallic are separate maps, named in ``prior_maps``)."""
    from .optim.groups import map_groups

    n_colour = 3 if img.pixels.shape[2] >= 3 else 1
    if not img.roles & set(MAP_ROLES):  # KHR_materials_* maps only: as the core map of its kind
        like = {"colour": "base_color", "normal": "normal", "data": "roughness"}
        return [like[kind_of(img.roles)] in config.prior_maps] * (
            1 if kind_of(img.roles) != "data" else n_colour
        )
    named = {
        c
        for g in map_groups(set(img.roles), n_colour, config)
        if g.name in config.prior_maps
        for c in g.channels
    }
    if kind_of(img.roles) != "data":
        return [bool(named)]
    return [c in named for c in range(n_colour)]


Snapshots = tuple[Collection[int], Callable[[int, Callable[[], dict[int, np.ndarray]]], None]]
"""(iterations, callback(it, maps)): a benchmark hook that sees the PBR-SR maps at
intermediate iterations; ``maps()`` gives them as they would be exported then (stored
encoding, ``project_lr`` applied; before the island padding), so the hook can leave the
export's time out of its own."""


def _snapshot_kwargs(snapshots: Snapshots | None, export: Callable) -> dict:
    if snapshots is None:
        return {}
    at, fn = snapshots
    return {"snapshot_at": set(at), "on_snapshot": lambda it, maps: fn(it, lambda: export(maps))}


def upscale_asset(
    input_path: Path,
    out_dir: Path,
    options: UpscaleOptions,
    *,
    progress: ProgressFn | None = None,
    limits: Limits = Limits(),
    work_dir: Path | None = None,
    snapshots: Snapshots | None = None,
    config: PbrsrConfig | None = None,
    memory_budget: int | None = None,
    crops_dir: Path | None = None,
) -> dict:
    """Upscale every texture of the asset at ``input_path`` into a bundle at ``out_dir``.

    ``out_dir`` must not exist or be empty. ``work_dir`` keeps per-job intermediates (unzipped
    input, cached pseudo-GT) so a retried job reuses them; by default a temporary folder.
    ``config``: PBR-SR numbers to run instead of the options' preset (``pbrsr bench paper``
    runs a sample of the paper preset with it). ``memory_budget``: bytes the run may use; a
    run whose estimate (:mod:`pbrsr_core.footprint`, from the images' declared sizes) is
    over it is refused before anything is upscaled. ``crops_dir``: where to write every
    map's LR/HR detail crops (:mod:`pbrsr_core.crops`; not part of the bundle).
    Returns the report (also written to ``out_dir/report.json``).
    """
    input_path, out_dir = Path(input_path), Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise StorageError(f"output folder '{out_dir.name}' exists and is not empty")
    timer = StageTimer()
    t_start = time.perf_counter()
    torch.manual_seed(options.seed)
    device = resolve_device(options.device)
    own_work = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="pbrsr-work-")) if work_dir is None else Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        with timer("load"):
            emit(progress, Progress(stage="load"))
            asset_path = _resolve_input(input_path, work, limits)
            asset = load_asset(asset_path, limits, unwrap_missing_uvs=options.unwrap_missing_uvs)
            images = upscalable_images(asset)
            if not images:
                raise UnprocessableAsset(
                    "nothing to upscale: no material of this asset uses a texture"
                )
            check_output_size(images, options.scale, limits)
            if memory_budget is not None:
                _check_footprint(images, options, config, memory_budget)
        with reuse_large_blocks():
            hr, method_report = _upscale_maps(
                asset, options, device, timer, progress, work, snapshots, config
            )
        emit(progress, Progress(stage="export"))
        with timer("export"):
            report = _write_bundle(
                asset,
                asset_path.name,
                hr,
                out_dir,
                options,
                timer,
                method_report,
                device,
                t_start,
                progress,
            )
        if crops_dir is not None:
            write_map_crops(asset, hr, crops_dir)
        emit(progress, Progress(stage="done", step=1, total=1))
        return report
    finally:
        if own_work:
            shutil.rmtree(work, ignore_errors=True)


def _write_bundle(
    asset: Asset,
    file_name: str,
    hr: dict[int, np.ndarray],
    out_dir: Path,
    options: UpscaleOptions,
    timer: StageTimer,
    method_report: dict,
    device: torch.device,
    t_start: float,
    progress: ProgressFn | None = None,
) -> dict:
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        encoded = encode_images(asset, hr, options.image_format)
        save_asset(asset, stage / file_name, encoded)
        maps_dir = stage / "maps"
        maps_dir.mkdir()
        map_files = {}
        for i, px in hr.items():
            img = asset.images[i]
            bits = 16 if img.bit_depth >= 16 else 8
            name = f"{map_file_stem(img)}.png"
            if encoded[i].fmt == "png" and encoded[i].bit_depth == bits:
                (maps_dir / name).write_bytes(encoded[i].data)  # the asset's own PNG bytes
            else:
                write_image(maps_dir / name, px, bits, "png")
            map_files[i] = f"maps/{name}"
        with timer("preview"):
            previews = write_previews(asset, hr, stage, device, options.envmap, progress)
        report = {
            "pbrsr_version": __version__,
            "input": file_name,
            "options": options.model_dump(),
            "device": str(device),
            "threads": torch.get_num_threads(),  # torch's intra-op threads (numba follows)
            "images": [
                {
                    "index": img.index,
                    "name": img.name,
                    "roles": sorted(img.roles),
                    "kind": kind_of(img.roles),
                    # rendered: the renderer (previews, PBR-SR's losses) models one of its roles;
                    # otherwise (KHR_materials_* textures) it is upscaled as a map only
                    "rendered": bool(img.roles & set(MAP_ROLES)),
                    "label": role_label(img.roles),
                    "lr_size": [img.width, img.height],
                    "hr_size": [int(hr[img.index].shape[1]), int(hr[img.index].shape[0])],
                    "bit_depth": img.bit_depth,
                    "file": map_files[img.index],
                    **_seams(asset, img, hr[img.index]),
                }
                for img in asset.images
                if img.index in hr
            ],
            "timings": {k: round(v, 3) for k, v in timer.seconds.items()},
            "wall_seconds": round(time.perf_counter() - t_start, 3),
            "previews": previews,
            **method_report,
        }
        (stage / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
        if out_dir.exists():
            out_dir.rmdir()  # empty, checked at the start
        os.replace(stage, out_dir)
        return report
    except OSError as exc:
        shutil.rmtree(stage, ignore_errors=True)
        raise StorageError(f"could not write the result: {exc.strerror or exc}") from exc
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def _seams(asset: Asset, img, hr: np.ndarray) -> dict:
    """For a tiling image: its seam ratio (x, y) before and after (metrics.seam_ratio)."""
    wrap = image_wrap(asset, img.index)
    if wrap is None:
        return {}
    before, after = seam_ratio(img.pixels), seam_ratio(hr)
    return {"wrap": list(wrap), "seam": {"lr": [round(v, 3) for v in before],
                                         "hr": [round(v, 3) for v in after]}}  # fmt: skip


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, torch.Tensor):
        return o.tolist()
    if isinstance(o, (set, tuple)):
        return list(o)
    if isinstance(o, Path):
        return o.name
    if isinstance(o, PbrsrError):
        return o.message
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
