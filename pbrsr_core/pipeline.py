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
from collections.abc import Callable, Collection
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
from .degrade import lr_model
from .device import resolve_device
from .errors import PbrsrError, StorageError, UnprocessableAsset
from .footprint import check_memory, estimate_peak_bytes
from .initial_maps import (
    blended_channels,
    check_gains,
    checked_kinds,
    deblocked_lr,
    initial_maps,
    prior_channels,
    prior_channels_checked,
    read_channels_only,
    self_checks,
)
from .kernel_estimate import estimate_kernel
from .limits import Limits, check_output_size
from .maps import (
    bicubic_only,
    encoded_to_param,
    image_cutout,
    image_wrap,
    kind_of,
    listed,
    map_file_stem,
    map_scales,
    param_to_encoded,
    role_label,
    to_param,
    upscalable_images,
)
from .metrics import seam_ratio
from .optim.losses import map_factor
from .options import UpscaleOptions
from .preview import write_previews
from .prior import load_prior
from .prior.direct import (
    bicubic_map,
    filled_cutout,
    keep_normal_length,
    project_map,
    restore_hidden,
)
from .prior.selfcheck import (
    GAIN_KINDS,
    chosen,
    merge_channels,
    upscale_channels,
    with_gain,
)
from .progress import MapProgress, Progress, ProgressFn, StageTimer, emit
from .render.light import EnvLight
from .render_reach import render_reach, unseen_entries
from .scene import make_scene, procedural_light
from .uvmask import coverage_masks

if TYPE_CHECKING:
    from .asset.model import ImageData
    from .optim.presets import PbrsrConfig
    from .prior.base import Prior


def _resolve_input(input_path: Path, work_dir: Path, limits: Limits) -> Path:
    kind = detect_kind(input_path)
    if kind == "zip":
        return extract_zip(input_path, work_dir / "unzipped", limits)
    return input_path


def _check_footprint(images, options: UpscaleOptions, config, budget: int) -> None:
    """Refuse a run whose peak memory estimate is over ``budget``: the largest of its factor
    groups' (they run one after the other), with the float32 HR maps of the groups before it."""
    from .optim.presets import run_config

    if options.method == "pbrsr" and config is None:
        config = run_config(options.preset, options.iterations)
    factors = map_scales(images, options.scale, options.max_size, options.maps, options.other_maps)
    plain = bicubic_only(images, factors, options.maps)
    sizes = {img.index: (img.width, img.height, int(img.pixels.shape[2])) for img in images}
    upscaled = [sizes[i] for i, f in factors.items() if f > 1]
    largest = max(max(w, h) for w, h, _ in upscaled)
    what = f"x{options.scale} of {len(upscaled)} maps (largest {largest} px)"
    if options.max_size is not None:
        what += f" at most {options.max_size} px"
    if options.method == "pbrsr":
        what += f" with the {options.preset} preset"
    # the maps bicubic alone upscales (other_maps) are held from the start
    estimate = held = sum(4 * w * h * c * factors[i] ** 2 for i, (w, h, c) in sizes.items()
                          if i in plain)  # fmt: skip
    for f in sorted({f for i, f in factors.items() if f > 1 and i not in plain}, reverse=True):
        group = [sizes[i] for i, g in factors.items() if g == f and i not in plain]
        estimate = max(estimate, held + estimate_peak_bytes(group, f, options.method, config))
        held += sum(4 * w * h * c * f * f for w, h, c in group)
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
    """HR maps (stored encoding) for every used image ``options.maps`` and ``max_size`` do not
    keep, each at its factor (:func:`~.maps.map_scales`), and method-specific report fields.
    The images of unlisted roles that ``other_maps`` has upscaled are bicubic's. The prior's
    check, init and blends run on the maps of each factor together, the larger factors first
    (a metallic-roughness map whose colour map has another factor, or is kept, is blended
    without it as guide); PBR-SR's optimisation and export take every map at once, a kept map
    and a bicubic-only one rendered as they are."""
    images = upscalable_images(asset)
    factors = map_scales(images, options.scale, options.max_size, options.maps, options.other_maps)
    wraps = {img.index: image_wrap(asset, img.index) for img in images}  # tiling maps
    cutouts = {img.index: image_cutout(asset, img.index) for img in images}
    if options.method == "bicubic":
        with timer("upscale"):
            hr = _bicubic_maps(images, factors, wraps, cutouts, set(factors))
        return hr, {"made_by": {i: ["bicubic"] for i in hr}}
    plain: dict[int, np.ndarray] = {}
    if only := bicubic_only(images, factors, options.maps):
        with timer("upscale"):
            plain = _bicubic_maps(images, factors, wraps, cutouts, only)
    groups = {
        f: [img for img in images if factors[img.index] == f and img.index not in plain]
        for f in sorted({f for i, f in factors.items() if i not in plain} - {1}, reverse=True)
    }
    plain_report = {"made_by": {i: ["bicubic (maps)"] for i in plain}}
    if not groups:  # every listed map is over max_size: bicubic's maps are the run's
        return plain, plain_report
    with timer("load_prior"):
        emit(progress, Progress(stage="load_prior", message=options.prior))
        prior = load_prior(options.prior, device)
    from .optim.presets import BALANCED, run_config

    if options.method == "direct":
        unseen, reach = _render_reach(asset, groups, prior, BALANCED, device, timer, progress)
        out: dict[int, np.ndarray] = dict(plain)
        report: dict = reach
        for f, group in groups.items():
            hr, part = _direct_maps(asset, group, prior, f, wraps, cutouts, unseen, timer,
                                    progress)  # fmt: skip
            out.update(hr)
            _merge_report(report, part)
        _merge_report(report, plain_report)
        return out, report
    config = config or run_config(options.preset, options.iterations)
    unseen, reach = _render_reach(asset, groups, prior, config, device, timer, progress)
    # rendered as they are, never optimised: the kept maps and bicubic's
    kinds = {img.index: kind_of(img.roles) for img in images}
    static = {img.index: to_param(img) for img in images if factors[img.index] == 1}
    static.update({i: encoded_to_param(torch.from_numpy(hr), kinds[i]) for i, hr in plain.items()})
    out, report = _pbrsr_maps(asset, groups, static, prior, options, config, device, timer,
                              progress, work_dir, snapshots, wraps, cutouts, unseen)  # fmt: skip
    _merge_report(report, {**plain_report, **reach})
    return {**plain, **out}, report


def _render_reach(asset, groups, prior, config, device, timer, progress):
    """The maps of ``groups`` whose errors the renders do not show (render_reach.py), as
    {image: its unseen entries}, and the report field (``render_reach``; none when not
    measured: ``config.reach_db`` None, or the prior is bicubic)."""
    if config.reach_db is None or prior.name == "bicubic":
        return {}, {}
    images = [img for group in groups.values() for img in group]
    channels = {img.index: prior_channels(img, config) for img in images}
    with timer("render_reach"):
        emit(progress, Progress(stage="render_reach"))
        reach = render_reach(asset, channels, config, device)
    return unseen_entries(reach, channels), ({"render_reach": reach} if reach else {})


def _bicubic_maps(images, factors, wraps, cutouts, which) -> dict[int, np.ndarray]:
    """Bicubic's HR map of each image in ``which`` that its factor upscales."""
    out = {}
    for img in images:
        i = img.index
        if i in which and factors[i] > 1:
            out[i] = bicubic_map(img.pixels, kind_of(img.roles), factors[i], wraps[i], cutouts[i])
    return out


def _merge_report(into: dict, part: dict) -> None:
    """One factor group's report into the run's: lists joined, mappings merged, the first
    group's other values kept."""
    for k, v in part.items():
        if isinstance(v, list) and isinstance(into.get(k), list):
            into[k] = into[k] + v
        elif isinstance(v, dict) and isinstance(into.get(k), dict):
            into[k] = {**into[k], **v}
        else:
            into.setdefault(k, v)


def _direct_maps(asset, images, prior, s, wraps, cutouts, unseen, timer, progress):
    """The direct method on ``images`` at ``s``: JPEG maps deblocked with their own tables,
    as every preset does; where the prior offers candidates, the self-check picks one per
    colour and data map, and balanced's pick between candidates one per normal map
    (``PbrsrConfig.normal_pick_max_scale``); the entries ``unseen`` names ({image: entries})
    keep bicubic. The prior's detail in a checked map is scaled by balanced's share of its
    fitted gain (``PbrsrConfig.detail_gain``; a prior of one candidate is checked for the gain
    alone).
    Returns (HR maps, report fields)."""
    from .optim.presets import BALANCED

    lr_pixels, deblocked = deblocked_lr(images, BALANCED, timer)
    read = {img.index: prior_channels(img, BALANCED) for img in images}
    n = {i: len(r) for i, r in read.items()}  # channel entries

    def several(img) -> bool:
        return len(prior.candidates(kind_of(img.roles), s)) > 1

    offered = [
        img
        for img in images
        if (several(img) or BALANCED.detail_gain and prior.is_network)
        and len(unseen.get(img.index, ())) < n[img.index]
        and any(read[img.index])
    ]
    kinds, picked = checked_kinds(prior, s, BALANCED)
    found = self_checks(asset, offered, prior, lr_pixels, s, kinds, None, timer, progress,
                        storage=BALANCED.check_storage, picked=picked)  # fmt: skip
    picks = {
        img.index: _direct_picks(prior, img, found.get(img.index), s)
        for img in offered
        if several(img)
    }
    gains = check_gains([{"index": i, **c} for i, c in found.items() if c])
    chose = {  # a data map none of whose channels a material reads: bicubic's
        i: picks.get(i, [prior]) if any(r) else [None] * len(r) for i, r in read.items()
    }
    sources_of = {i: _without(chose[i], unseen.get(i), n[i]) for i in read}
    out = {}
    with timer("prior"):
        tiles = MapProgress(progress, "prior", images)
        for img in images:
            kind = kind_of(img.roles)
            sources = sources_of[img.index]
            px, wrap, cutout = lr_pixels[img.index], wraps[img.index], cutouts[img.index]
            takes_gain = BALANCED.detail_gain and kind in GAIN_KINDS and any(sources)
            gain = gains.get(img.index) if takes_gain else None
            plain = gain is not None or not any(sources)
            base = bicubic_map(px, kind, s, wrap, cutout) if plain else None
            hr = upscale_channels(
                sources, px, kind, s, base, wrap=wrap, cutout=cutout, progress=tiles.on(img)
            )
            if gain is not None and base is not None:  # base: bicubic's whenever gain is set
                hr = with_gain(hr, base, gain, kind, BALANCED.detail_gain)
            out[img.index] = hr
    names = {img.index: img.name for img in images}
    checked = [
        {"image": names[i], "index": i, **c, **({} if i in picks else _gain_only(c))}
        for i, c in found.items()
        if c
    ]
    made_by = _made_by(images, sources_of, {}, checked, unseen)
    return out, {
        "prior_precision": _precisions(prior, images),
        "jpeg_deblocked": deblocked,
        "made_by": made_by,
        **({"prior_check": checked} if checked else {}),
    }


def _gain_only(check: dict) -> dict:
    """A check's report where direct takes its gain alone (a prior of one candidate, which
    upscales each map the materials read): the channels say what direct used."""
    n = len(check["channels"])
    note = "the prior's only candidate upscales every channel; the check fits its gain"
    return {"channels": [True] * n, "use_prior": True, "note": note}


def _without(sources: list, entries: set[int] | None, n: int) -> list:
    """``sources`` (per channel entry, a prior or None) with ``entries`` set to None; a data
    map's single source is first spread over its ``n`` entries."""
    if not entries:
        return sources
    if len(sources) == 1:
        sources = sources * n
    return [None if c in entries else p for c, p in enumerate(sources)]


def _bicubic_why(check: dict | None, c: int, unseen: bool = False) -> str:
    """How a map's channel entry ``c`` that no prior upscales is named in ``made_by``."""
    if unseen:
        return "bicubic (unseen)"
    return "bicubic (flat)" if check and check.get("flat", [])[c : c + 1] == [True] else "bicubic"


def _made_by(images, sources, blends, checks, unseen=None) -> dict[int, list[str]]:
    """Per image, per channel entry of ``sources`` (the prior or None for bicubic): what it
    was made from (a prior's network, a blend of upscales with their weights, as ``blends``
    gives them, or bicubic; for PBR-SR before the projection and the steps; ``unseen``:
    {image: entries the renders do not show})."""
    found = {c["index"]: c for c in checks or [] if "index" in c}
    out = {}
    for img in images:
        i = img.index
        names, weights, _ = blends.get(i, ([], [], None))
        srcs = sources[i]
        row = []
        for c in range(len(srcs)):
            w = weights[c] if c < len(weights) else []
            if any(w):
                parts = [
                    f"{p if isinstance(p, str) else p.name} {x:.2f}"
                    for p, x in zip(names, w, strict=True)
                    if x
                ]
                if abs(rest := 1.0 - sum(w)) >= 0.005:
                    parts.append(f"bicubic {rest:.2f}")
                row.append("blend: " + " + ".join(parts))
            else:
                p = srcs[c]
                kind = kind_of(img.roles)
                hidden = c in (unseen or {}).get(i, ())
                row.append(p.for_kind(kind).name if p else _bicubic_why(found.get(i), c, hidden))
        out[i] = row
    return out


def _pbrsr_maps(asset, groups, static, prior, options, config, device, timer, progress, work_dir,
                snapshots, wraps, cutouts, unseen):  # fmt: skip
    """PBR-SR: each factor's maps checked, blended and initialised together, then every map
    optimised and exported at once (``static``: {image: map in optimisation space} rendered as
    it is, never optimised; ``unseen``: {image: entries} the prior leaves to bicubic)."""
    from .prior.symmetry import averaged

    # the check, init and blends
    images = [img for group in groups.values() for img in group]
    init_encoded, init, lr, lr_pixels, channels = {}, {}, {}, {}, {}  # over every factor
    checks, deblocked, made_by = None, [], {}
    for s, group in groups.items():
        map_prior = averaged(prior, *config.copies(s))
        px, names = deblocked_lr(group, config, timer)
        for img in group:  # a cutout's hidden colour takes no part (init, losses, projection)
            if (seen_from := cutouts[img.index]) is not None:
                px[img.index] = filled_cutout(px[img.index], seen_from)
        blend_kept = {} if config.blend_data else None
        ch, found, sources = prior_channels_checked(
            asset, group, map_prior, px, s, config, timer, progress, blend_kept, unseen
        )
        blends = blended_channels(asset, group, map_prior, ch, found, sources, blend_kept, px,
                                  s, config, timer, unseen)  # fmt: skip
        del blend_kept
        every = {i: sources.get(i) or [None] * len(c) for i, c in ch.items()}
        made_by.update(_made_by(group, every, blends, found, unseen))
        enc, par, low = initial_maps(group, sources, blends, px, s, wraps, config, timer,
                                     progress, check_gains(found))  # fmt: skip
        init_encoded.update(enc)
        init.update(par)
        lr.update(low)
        lr_pixels.update(px)
        channels.update(ch)
        deblocked += names
        if found is not None:
            checks = (checks or []) + found
    lr.update(static)  # a map without an init: rendered as it is
    if checks is not None and not any(any(c) for c in channels.values()):
        prior = load_prior("bicubic", device)  # for the pseudo-GT
    out, report = _optimise(
        asset, images, init_encoded, init, lr, lr_pixels, channels, prior, max(groups), config,
        options, device, timer, progress, work_dir, snapshots, wraps,
    )  # fmt: skip
    for img in images:
        if cutouts[img.index] is not None:
            f = map_factor(out[img.index], img.pixels)
            out[img.index] = restore_hidden(out[img.index], img.pixels, f)
    return out, {
        **report,
        "prior_check": checks,
        "prior_used": prior.name,
        "prior_precision": _precisions(prior, images),
        "prior_init": sorted(img.name for img in images if any(channels[img.index])),
        "jpeg_deblocked": deblocked,
        "made_by": made_by,
    }


def _direct_picks(prior: Prior, img: ImageData, check: dict | None, s: int) -> list[Prior | None]:
    """Per channel entry of a map (prior/selfcheck.py counts them), the candidate of
    ``prior`` direct upscales it with by ``s``: the one its self-check found closest one
    scale down, or None (bicubic) where bicubic was closer or no material reads the
    channel."""
    from .optim.presets import BALANCED

    picks: list[Prior | None] = list(chosen(prior, kind_of(img.roles), check, 1, s))
    if check is not None:
        picks = [p if use else None for p, use in zip(picks, check["channels"], strict=True)]
    return read_channels_only(picks, prior_channels(img, BALANCED))


def _pseudo_gt_prior(prior: Prior, config, device: torch.device) -> Prior:
    """The prior that upscales the LR renders into the pseudo-GT: ``config.pseudo_gt_prior``
    or the run's, on ``config.pseudo_gt_self_ensemble`` copies of each render."""
    from .prior.symmetry import averaged

    if config.pseudo_gt_prior is not None:
        prior = load_prior(config.pseudo_gt_prior, device)
    return averaged(prior, config.pseudo_gt_self_ensemble)


def _precisions(prior: Prior, images: list[ImageData]) -> dict[str, str]:
    """Per map kind of the asset, the precision its prior ran in (fp32, bf16, int8)."""
    kinds = sorted({kind_of(img.roles) for img in images})
    return {kind: prior.for_kind(kind).precision_in_use() for kind in kinds}


def _optimise(asset, images, init_encoded, init, lr, lr_pixels, channels, prior, s, config,
              options, device, timer, progress, work_dir, snapshots, wraps):  # fmt: skip
    """PBR-SR's optimisation from ``init_encoded`` (renders and pseudo-GT at ``s``, the largest
    factor; each map held to its LR map at its own), then each map's export: back-projection
    onto its LR map where the preset says so, and island padding. A map the scene repeats
    (``wraps``) keeps its TV across the wrap edge. ``lr`` may hold maps without an init,
    rendered as they are. Returns (HR maps, report)."""
    from .optim.pbrsr import optimize_pbrsr
    from .optim.whole_map import pad_update

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
        return _export_map(t, kinds[i], lr_pixels[i], map_factor(t, lr_pixels[i]), projected[i])

    result = optimize_pbrsr(
        scene.mesh,
        asset.materials,
        {k: v.to(device) for k, v in lr.items()},
        {k: v.to(device) for k, v in init.items()},
        {img.index: set(img.roles) for img in images},
        scale=s,
        prior=_pseudo_gt_prior(prior, config, device),
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
            i: pad_update(
                t,
                init_encoded[i],
                islands[i],
                2 * map_factor(t, lr_pixels[i]),
                normal=kinds[i] == "normal",
            )  # fmt: skip
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
            check_output_size(
                images,
                map_scales(
                    images, options.scale, options.max_size, options.maps, options.other_maps
                ),
                limits,
            )
            if memory_budget is not None:
                _check_footprint(images, options, config, memory_budget)
        kernel: str = options.lr_kernel
        lr_info = {"kernel": kernel, "estimated": False}
        if kernel == "auto":
            with timer("lr_kernel"):
                estimate = estimate_kernel([img.pixels for img in images])
            kernel, lr_info = estimate.kernel, estimate.to_json()
        with reuse_large_blocks(), lr_model(kernel):
            hr, method_report = _upscale_maps(
                asset, options, device, timer, progress, work, snapshots, config
            )
        method_report = {**method_report, "lr_model": lr_info}
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
    method_report = dict(method_report)
    made_by = method_report.pop("made_by", {})
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
                    "scale": int(hr[img.index].shape[1]) // img.width,
                    "bit_depth": img.bit_depth,
                    "file": map_files[img.index],
                    # per channel entry (one for colour and normal maps, one per channel of
                    # a data map): the prior, blend or bicubic it was made from
                    "made_by": made_by.get(img.index, []),
                    **_seams(asset, img, hr[img.index]),
                }
                for img in asset.images
                if img.index in hr
            ],
            # maps kept as they are (not in maps, or over max_size): their files are the input's
            "kept": [
                {
                    "index": img.index,
                    "name": img.name,
                    "label": role_label(img.roles),
                    "size": [img.width, img.height],
                    "reason": "maps"
                    if options.other_maps == "keep" and not listed(img, options.maps)
                    else "max_size",
                }
                for img in upscalable_images(asset)
                if img.index not in hr
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
