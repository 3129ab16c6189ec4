"""The maps the optimiser starts from (the init, paper 3.1), and the checks that decide them.

Each LR map is deblocked where it is a JPEG (asset/jpeg.py), self-checked one scale down
(prior/selfcheck.py), its data channels blended where the preset says so (prior/blend.py,
prior/guided.py), and upscaled: a prior's upscale in the channels it won, bicubic's in the
rest. pipeline.py runs these stages in order and reports what they decided.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from .asset.model import EXTENSION_CHANNELS, MAP_ROLES
from .maps import encoded_to_param, image_cutout, kind_of
from .prior.blend import blend, blend_check, blend_plan, check_picks
from .prior.direct import bicubic_map, upscale_map
from .prior.guided import CHANNELS as GUIDED_CHANNELS
from .prior.guided import guide_pairs, guided_check_upscale, guided_upscale
from .prior.selfcheck import (
    chosen,
    offered,
    prior_self_check,
    upscale_channels,
    upscale_each,
    with_gain,
)
from .progress import MapProgress, Progress, StageTimer, emit
from .uvmask import coverage_masks

if TYPE_CHECKING:
    from .optim.presets import PbrsrConfig


def deblocked_lr(images, config: PbrsrConfig, timer: StageTimer):
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


def checked_kinds(prior, s: int, config: PbrsrConfig) -> tuple[set[str], set[str]]:
    """(the map kinds checked at ``s``, those of them checked among the prior's candidates
    alone): ``check_prior``'s, and normal maps picked between the prior's normal candidates
    where ``normal_pick_max_scale`` reaches ``s`` and it offers several."""
    kinds = set(config.check_prior)
    top = config.normal_pick_max_scale
    if (
        "normal" not in kinds
        and top is not None
        and s <= top
        and len(offered(prior, "normal", s, config.max_prior_scale)) > 1
    ):
        return kinds | {"normal"}, {"normal"}
    return kinds, set()


def self_checks(asset, images, prior, lr_pixels, s, kinds, max_prior_scale, timer, progress,
                kept=None, storage=False, picked=frozenset()):  # fmt: skip
    """The self-check (prior/selfcheck.py) of each image of a kind in ``kinds``, over the
    texels a viewer sees: {image index: report, or None for a map too small to check}.
    ``kept``: filled with {data image index: what its check compared}. ``storage``: a JPEG
    map's check models its file one scale down (``PbrsrConfig.check_storage``). ``picked``:
    the kinds checked among the prior's candidates alone (never bicubic,
    :func:`checked_kinds`)."""
    from functools import partial

    from .asset.jpeg import stored_as

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
            as_read = lr_pixels[img.index] is img.pixels  # not deblocked
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
                stored=None if as_read else img.pixels,
                store=partial(stored_as, quant=img.jpeg, deblocked=not as_read)
                if storage and img.jpeg is not None
                else None,
                pick_only=kind_of(img.roles) in picked,
            )
    return checks


def prior_channels_checked(asset, images, prior, lr_pixels, s, config, timer, progress,
                            kept=None, unseen=None):  # fmt: skip
    """Which channels of each image the prior initialises (paper 3.1: the maps the preset
    names in ``prior_maps``; an ORM image's channels one by one; bicubic the rest; not the
    entries ``unseen`` names, {image: entries}, render_reach.py), and with ``check_prior``
    only those where the prior beats bicubic one scale down (``kept``: as
    :func:`self_checks` fills it); the normal maps :func:`checked_kinds` picks take the
    closest of the prior's candidates. Returns
    ({image: [bool per channel]}, the self-check reports or None when nothing was checked,
    {image: per channel, the prior's candidate the check chose, or None for bicubic})."""
    channels = {img.index: prior_channels(img, config) for img in images}
    for i, entries in (unseen or {}).items():
        if i in channels:
            channels[i] = [u and c not in entries for c, u in enumerate(channels[i])]
    kinds, picked = checked_kinds(prior, s, config)
    if not (kinds and prior.name != "bicubic" and any(map(any, channels.values()))):
        return channels, None, {i: [prior if c else None for c in ch] for i, ch in channels.items()}
    used = [img for img in images if any(channels[img.index])]
    found = self_checks(asset, used, prior, lr_pixels, s, kinds, config.max_prior_scale, timer,
                        progress, kept, config.check_storage, picked)  # fmt: skip
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
                chosen(
                    prior,
                    kind_of(img.roles),
                    found.get(img.index),
                    len(channels[img.index]),
                    s,
                    config.max_prior_scale,
                ),
                channels[img.index],
                strict=True,
            )
        ]
        for img in used
    }
    return channels, checks, sources


def blended_channels(asset, images, prior, channels, checks, sources, kept, lr_pixels, s,
                     config, timer, unseen=None):  # fmt: skip
    """With ``blend_data``: each checked data map's channels (those the preset lets a prior
    initialise, but the entries ``unseen`` names) as a blend of the prior's candidates,
    bicubic and, for the roughness and metallic of a metallic-roughness map, the upscale
    guided by its colour map (prior/blend.py, prior/guided.py), weighted one scale down from
    the upscales its check compared (``kept``); a channel whose blend beats bicubic by less
    than ``blend_margin`` stays bicubic's, and one whose check's pick beats bicubic keeps the
    pick unless its blend beats the pick by ``blend_pick_db``. Updates ``channels``,
    ``sources`` (None: blended or bicubic) and the ``checks`` entries (``blend``); returns
    {image: (the blend's sources, a candidate or "guided"; per channel their weights; the
    guide image or None)}."""
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
            flat = entries[i]["flat"]  # nothing for a network to sharpen: bicubic's
            hidden = (unseen or {}).get(i, ())
            todo = [
                c
                for c, ok in enumerate(prior_channels(by_index[i], config))
                if ok and not flat[c] and c not in hidden
            ]
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
            entry = entries[i]
            picks = check_picks(entry, todo)
            fits = blend_check(k, todo, guided, network_db=config.blend_network_db,
                               margin=config.blend_margin,
                               picks=picks if config.blend_pick_floor else None,
                               channel_db=config.blend_channel_db)  # fmt: skip
            names = list(k["ups"]) + (["guided"] if guided else [])
            names, weights, use = blend_plan(fits, names, n, config.blend_margin, picks,
                                             config.blend_pick_db)  # fmt: skip
            guide = g if "guided" in names else None
            entry["blend"] = {  # the upscales the run blends (each network runs once)
                "sources": names,
                "guide": by_index[g].name if guide is not None and g is not None else None,
                "weights": weights,
                "margins": [fits[c][2] if c in fits else None for c in range(n)],
            }
            entry["channels"], entry["use_prior"] = use, any(use)
            channels[i], sources[i] = use, [None] * n
            if any(use):
                kind = kind_of(by_index[i].roles)
                by_name = {p.name: p for p in offered(prior, kind, s, config.max_prior_scale)}
                blends[i] = ([by_name.get(m, "guided") for m in names], weights, guide)
    return blends


def check_gains(checks: list[dict] | None) -> dict[int, list[float]]:
    """{image: per channel entry, the detail gain its self-check fitted} from the reports of
    :func:`prior_channels_checked` (``PbrsrConfig.detail_gain``)."""
    return {c["index"]: c["gains"] for c in checks or () if "gains" in c}


def initial_maps(images, sources, blends, lr_pixels, s, wraps, config, timer, progress,
                 gains=None):  # fmt: skip
    """The optimiser's start: bicubic, with a prior's upscale in the channels ``sources``
    gives one for (per image, per channel: the prior or None), and the blends of ``blends``
    (:func:`blended_channels`; the colour maps that guide one come first); a map with
    ``gains`` ({image: per channel entry}, :func:`check_gains`) departs from bicubic by
    ``config.detail_gain`` of them (prior/selfcheck.py ``with_gain``). Returns
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
            plain = bicubic_map(px, kind, s, wraps[img.index])  # px: a cutout's already filled
            tiles.on(img)(0, 1)
            gain = (gains or {}).get(img.index) if config.detail_gain else None
            if img.index in blends:  # the blends are written into this call's own array
                hr = _blend_map(plain if gain is None else plain.copy(), px, blends[img.index],
                                init_encoded, lr_pixels, s, kind, wraps[img.index], config,
                                tiles.on(img))  # fmt: skip
            else:
                hr = upscale_channels(sources.get(img.index, [None]), px, kind, s, plain,
                                      max_prior_scale=config.max_prior_scale,
                                      progress=tiles.on(img), wrap=wraps[img.index])  # fmt: skip
            if gain is not None:
                hr = with_gain(hr, plain, gain, kind, config.detail_gain)
            del plain
            tiles.on(img)(1, 1)  # done, whether a prior ran on it or not
            init_encoded[img.index] = hr
            init[img.index] = encoded_to_param(torch.from_numpy(hr), kind)
            lr[img.index] = encoded_to_param(torch.from_numpy(px), kind)
    return init_encoded, init, lr


def _blend_map(bicubic, px, how, init_encoded, lr_pixels, s, kind, wrap, config, progress):
    """A data map whose channels blend its upscales (``how``, as :func:`blended_channels`
    gives it) over ``bicubic`` (this call's own array: the blended channels are written into
    it); the guide's HR map is in ``init_encoded``."""
    sources, weights, g = how
    priors = [p for p in sources if not isinstance(p, str)]
    used = [[c for c, w in enumerate(weights) if w[sources.index(p)]] for p in priors]
    ups = upscale_each(priors, px, kind, s, used, max_prior_scale=config.max_prior_scale,
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


def read_channels_only(picks: list, read: list[bool]) -> list:
    """``picks`` per channel with None (bicubic) for a channel no material reads (the R of a
    metallic-roughness image without occlusion): a data map's prior runs on the channels it
    is picked for only. Unchanged for a map of one entry."""
    if len(picks) != len(read):
        return picks
    return [p if r else None for p, r in zip(picks, read, strict=True)]


def prior_channels(img, config) -> list[bool]:
    """Which of an image's colour channels the preset lets the prior initialise: one entry
    for colour and normal maps (the image as a whole), one per channel for data maps (an ORM
    image's occlusion, roughness and metallic are separate maps, named in ``prior_maps``)."""
    from .optim.groups import map_groups

    n_colour = 3 if img.pixels.shape[2] >= 3 else 1
    if not img.roles & set(MAP_ROLES):  # KHR_materials_* maps only: as the core map of its kind
        kind = kind_of(img.roles)
        on = {"colour": "base_color", "normal": "normal", "data": "roughness"}[kind] in (
            config.prior_maps
        )
        if kind != "data":
            return [on]
        read = {c for r in img.roles for c in EXTENSION_CHANNELS.get(r, range(3))}
        return [on and (c in read or n_colour == 1 and bool(read)) for c in range(n_colour)]
    named = {
        c
        for g in map_groups(set(img.roles), n_colour, config)
        if g.name in config.prior_maps
        for c in g.channels
    }
    if kind_of(img.roles) != "data":
        return [bool(named)]
    if "roughness" in config.prior_maps:  # a KHR map in the same image: its channels too
        khr = {c for r in img.roles for c in EXTENSION_CHANNELS.get(r, ())}
        named |= {0} if n_colour == 1 and khr else khr
    return [c in named for c in range(n_colour)]
