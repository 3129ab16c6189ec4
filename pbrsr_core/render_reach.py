"""Which maps' errors reach the renders, measured on the LR asset before any prior runs.

A map the prior initialises costs a network run, and where the renders cannot show its error
the run buys nothing and risks a wrong acceptance of the self-check (docs/METHOD.md, "A wrong
acceptance"). So, one scale down on the asset itself: every map is degraded once more by
``REACH_SCALE`` (the run's LR model) and upscaled back by bicubic (its round trip), and the
LR asset is rendered from :func:`reach_cameras` under the two built-in lights (never the
benchmark's): with its own maps (the reference), with every map's round trip, and with one
map's round trip alone (an ORM image's occlusion, roughness and metallic one by one, as the
prior takes them). A map's ``margin_db`` is how far its own render error lies below that of
all of them together; at ``reach_db`` or more the map keeps bicubic's upscale (``made_by``:
"bicubic (unseen)"). The textures are sampled once per view for the reference and once for
the round trips; a map's renders take the material inputs it feeds from the second
(render/shade.py ``shade_inputs``), so each costs a shading pass, not a texture pass.

The band one scale down is not the band the upscale restores, so the margin is a proxy that
can err both ways, and what this renderer does not show under these lights a scene may show:
no preset turns it on (docs/METHOD.md, "Maps the renders do not show").
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .asset.model import Asset, ImageData
from .degrade import degrade_image, run_kernel
from .maps import encoded_to_param, image_cutout, image_wrap, kind_of, upscalable_images
from .optim.groups import map_groups
from .render import camera as cam
from .render import raster
from .render.shade import material_inputs, shade_inputs, tonemap, use_fused
from .scene import asset_textures, make_scene, procedural_light, rotated_procedural_light

REACH_SCALE = 2
REACH_RES = 96
REACH_ELEVATIONS = (-30.0, 30.0)
REACH_AZIMUTHS = 6
MIN_SIDE = 8
"""Texels a side a map needs one scale down to be measured (smaller: it is left to the
prior)."""


def reach_cameras() -> list[cam.Camera]:
    """The views the measurement renders: two rings of ``REACH_AZIMUTHS`` around the
    unit-size mesh, off the paper's evaluation elevations and azimuths."""
    return cam.orbit_cameras(
        len(REACH_ELEVATIONS),
        REACH_AZIMUTHS,
        cam.PAPER_DISTANCE,
        cam.PAPER_FOV_DEG,
        REACH_RES,
        REACH_ELEVATIONS,
        15.0,
    )


def round_trip(img: ImageData, asset: Asset) -> np.ndarray:
    """The map degraded by ``REACH_SCALE`` and upscaled back by bicubic, at its own size."""
    from .prior.direct import bicubic_map

    px, kind = img.pixels, kind_of(img.roles)
    low = degrade_image(px, REACH_SCALE, normal_map=kind == "normal", kernel=run_kernel())
    up = bicubic_map(
        low, kind, REACH_SCALE, image_wrap(asset, img.index), image_cutout(asset, img.index)
    )
    h, w = px.shape[:2]
    up = up[:h, :w]
    pad = ((0, h - up.shape[0]), (0, w - up.shape[1]), (0, 0))
    return np.pad(up, pad, mode="edge") if any(p[1] for p in pad) else up


def render_reach(asset: Asset, channels: dict[int, list[bool]], config, device) -> list[dict]:
    """Per map the prior would initialise (``channels``: {image: per entry, as
    ``initial_maps.prior_channels`` counts them, whether the prior would}), ``{"image",
    "index", "map", "channels", "margin_db", "unseen"}``: its render error one scale down, in
    dB below that of every map of the asset together (None: it has none), and whether that
    is at least ``config.reach_db``. Empty when ``reach_db`` is None, or when the asset's
    maps do not change the renders at all (nothing to compare with: the prior runs as
    without the measurement). A map's margin is the asset's, whichever maps a run
    upscales."""
    if config.reach_db is None:
        return []
    every, entries = [], []  # (image, map name, its channels)
    for img in upscalable_images(asset):
        if min(img.pixels.shape[:2]) < MIN_SIDE * REACH_SCALE:
            continue
        use = channels.get(img.index, [])
        for g in map_groups(set(img.roles), 3 if img.pixels.shape[2] >= 3 else 1, config):
            every.append((img, g.name, list(g.channels)))
            if any(use[c] for c in (g.channels if len(use) > 1 else [0]) if c < len(use)):
                entries.append(every[-1])
    if not entries:
        return []
    trips = {
        img.index: encoded_to_param(torch.from_numpy(round_trip(img, asset)), kind_of(img.roles))
        for img in {img.index: img for img, _, _ in every}.values()
    }
    scene = make_scene(asset, device)
    lights = [procedural_light().to(device), rotated_procedural_light(150.0).to(device)]
    own = asset_textures(asset, device)
    tripped = {i: t.clone() if i in trips else t for i, t in own.items()}
    for img, _, chans in every:
        tripped[img.index][..., chans] = trips[img.index][..., chans].to(tripped[img.index])
    views = []  # per view: its G-buffer, the material inputs of its own maps and of the trips
    for c in reach_cameras():
        gb = raster.rasterize(scene.mesh, c).to(device)
        if gb.num_pixels == 0:
            continue
        fused = all(use_fused(gb, own, light) for light in lights)
        mine, trip = (
            material_inputs(gb, scene.materials, t, fused_decode=fused) for t in (own, tripped)
        )
        views.append((gb, fused, mine, trip))

    def render(gb, fused, m) -> list[torch.Tensor]:
        return [tonemap(shade_inputs(gb, m, light, fused=fused)) for light in lights]

    refs = [render(gb, fused, mine) for gb, fused, mine, _ in views]

    def error(swap: dict[int, list[int]]) -> float:
        """Squared render error, over every view and light, of the own maps with the channels
        ``swap`` names ({image: channels}) from their round trips."""
        total = 0.0
        for (gb, fused, mine, trip), ref in zip(views, refs, strict=True):
            m = dict(mine)
            for field, rows in _swapped(asset, gb, swap):
                m[field] = m[field].index_copy(0, rows, trip[field][rows])
            for a, b in zip(render(gb, fused, m), ref, strict=True):
                total += float(((a - b) ** 2).double().sum())
        return total

    swaps: dict[int, list[int]] = {}
    for img, _, chans in every:
        swaps.setdefault(img.index, []).extend(chans)
    total = error(swaps)
    if not total > 0:
        return []
    out = []
    for img, name, chans in entries:
        e = error({img.index: chans})
        margin = 10.0 * math.log10(total / e) if e > 0 else None
        out.append(
            {
                "image": img.name,
                "index": img.index,
                "map": name,
                "channels": chans,
                "margin_db": None if margin is None else round(margin, 2),
                "unseen": margin is None or margin >= config.reach_db,
            }
        )
    return out


ROLE_FIELDS: dict[str, tuple[tuple[str, tuple[int, ...]], ...]] = {
    "base_color": (("base", (0, 1, 2)),),
    "emissive": (("emissive", (0, 1, 2)),),
    "normal": (("normal_ts", (0, 1, 2)),),
    "occlusion": (("ao", (0,)),),
    "metallic_roughness": (("rough", (1,)), ("metal", (2,))),
}
"""Per material role, the material inputs (render/shade.py) it makes and the image channels
each reads."""


def _swapped(asset: Asset, gb, swap: dict[int, list[int]]) -> list[tuple[str, torch.Tensor]]:
    """(material input, pixel rows of ``gb``) that the channels ``swap`` names ({image:
    channels}) feed: the rows of each material reading one of them (the per-view rows
    ``material_inputs`` cached on ``gb``)."""
    rows_of = dict(gb.derived()["material_rows"])
    out = []
    for m in asset.materials:
        if m.index not in rows_of:
            continue
        rows = rows_of[m.index]
        if rows is None:  # the view shows this material only
            rows = torch.arange(gb.num_pixels, device=gb.device)
        for role, fields in ROLE_FIELDS.items():
            ref = m.texture(role)  # type: ignore[arg-type]
            if ref is not None and ref.image in swap:
                out += [(f, rows) for f, used in fields if set(used) & set(swap[ref.image])]
    return out


def unseen_entries(reach: list[dict], channels: dict[int, list[bool]]) -> dict[int, set[int]]:
    """Per image, the entries of ``channels`` (its per-entry list) that unseen maps hold."""
    out: dict[int, set[int]] = {}
    for r in reach:
        if r["unseen"]:
            n = len(channels[r["index"]])  # 1: a colour or normal map, one entry
            out.setdefault(r["index"], set()).update(r["channels"] if n > 1 else [0])
    return out
