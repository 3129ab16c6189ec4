"""Does the prior help on this map? A check on each of the asset's own maps, one scale down.

A photo-trained prior can make textures worse than bicubic interpolation: on the Avocado at
x4 rrdn-thick's albedo was 0.9 dB below bicubic's (``pbrsr bench upscale``). Before a PBR-SR
run spends prior calls on the init and the pseudo-GT, each LR map the preset lets the prior
initialise (a centre crop of at most ``CROP`` texels a side) is degraded once more by the
scale (``degrade.degrade_image``, the declared LR model), upscaled back by the prior and by
bicubic, and both are compared with the LR map itself: the prior initialises a map only if
it wins on that map (self-similarity across scales, as in zero-shot SR). A prior that offers
several candidates for a map kind (a texture set: its own network and the photo prior it
falls back on) has each upscale the map, and the one closest to the LR map is kept. The cost
is one call per candidate on at most ``(CROP / s)^2`` pixels per map.

A map too small for its scale is checked at a smaller factor (:func:`check_factor`): one
scale down, the crop must keep at least ``MIN_SIDE`` texels a side. At x8 the tea set's
128² ORM map shrank to 16² and the check left its occlusion and metallic channels to bicubic,
4.1 and 3.9 dB below the prior at the real scale; checked at x4 (32²) it chose the prior for
both and waifu2x-photo for roughness, the best choice for each channel (the ToyCar's 128²
clearcoat map: waifu2x-photo at x8, the texture network at x4, 4.0 dB better).

The comparison counts only the texels the mesh's UVs cover (when the caller passes them, as
the pipeline does): the rest of an atlas is never seen, and it can decide the check the wrong
way. The Avocado's roughness (x4, prior x2 as the fast preset runs it): +0.38 dB for the
prior over the whole map one scale down, -0.40 over its covered texels, and -0.51 dB at the
real scale against the ground truth (covered texels). On the other colour and data maps of
the shared assets no decision changed with the prior's x4; with its x2 one did, the
ToyCar's roughness: +0.34 / -0.04 one scale down, +3.8 dB at the real scale.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from ..degrade import degrade_image, run_kernel
from .base import Prior
from .direct import bicubic_map, upscale_map

CROP = 512
MIN_SIDE = 32
"""Texels a side the crop keeps one scale down (fewer: the check runs at a smaller factor)."""
FLAT_STD = 1 / 255
"""Standard deviation (encoded values) below which a map entry's compared texels are flat:
their variation is an 8-bit level's quantisation, nothing for a network to sharpen, and the
init keeps bicubic's upscale there without running a network. On the Avocado's roughness
(0.73 levels) the data network's x4 was 0.12 dB ahead of bicubic one scale down and 0.53 dB
behind at the real scale (covered texels; waifu2x-photo 0.12 behind); on the 11 of the CC0
texture set's 74 roughness, metallic and occlusion maps under a level (centre crops of 512²,
x4) it gained 0.00 to +0.24 dB. The least varied map of either set with a signal above
that: 1.15 levels (a CC0 metal's sparse metallic mask, +0.84 dB).

A JPEG map's floor is higher by the noise its deblocking took out (``stored`` of
:func:`prior_self_check`: the RMS per channel of the stored pixels less the deblocked ones):
variation of that size is the file's, which a network sharpens and bicubic averages away.
On the held-out CC0 materials' packed maps stored as JPEG and deblocked (``pbrsr bench
blend --jpeg 95`` / ``--jpeg 85``, x4, pbr-srmd) direct's choices gain +0.251 / +0.098 dB over
bicubic with it against +0.240 / +0.091 without, 3 / 3 channels below bicubic against 8 / 10
(near-flat metals' roughness and metallic); the wooden table's metallic (x4), 1.9 levels RMS
after deblocking and 1.0 taken out, scores 0.14 dB above bicubic in direct with the floor and
0.21 below without. A map stored without loss keeps the 8-bit floor."""
FLAT_PEAK = 32 / 255
"""Deviation from the median (encoded values) that no entry under :data:`FLAT_STD`'s floor
reaches by noise: one texel that far off is a feature (an LED, a sparse mask), and the entry
is checked as any other. The flat entries of the CC0 set's roughness, metallic and occlusion
maps (centre crops of 512², x4) deviate by at most 2.8 levels; those of the seven shared
assets and the twelve WebXR controllers at x2, x4 and x8 by at most 23 (the HP controller's
metallic at x2; the wooden table's JPEG metallic by 15, at 2 levels of floor). Sparse
features deviate by more: a CC0 metal's metallic mask by 68 levels, magicleap-two's LEDs
(x8, 3 of 65 536 texels above 0.1, 0.81 levels RMS) by 112; checked, that map is
waifu2x-photo's in direct, 8.22 dB closer to the ground truth than bicubic's."""


GAIN_RANGE = (0.5, 1.5)
"""The range a map entry's detail gain (:func:`detail_gain`) is kept in."""
GAIN_KINDS = ("colour", "data")
"""Map kinds whose upscale takes the gain (:func:`with_gain`). Not normal maps: on the seven
shared assets (x4, direct, 40 evaluation views) the fitted gain brought their normal maps
0.14 dB closer to the ground truth and cost the renders 0.06 dB on average (the cabinet's
0.37, docs/METHOD.md, "The network's detail scaled by a gain fitted one scale down")."""


def offered(prior: Prior, kind: str, scale: int, max_prior_scale: int | None = None) -> list[Prior]:
    """``prior``'s candidates for a map of ``kind`` upscaled by ``scale`` with the prior
    capped at ``max_prior_scale`` (:func:`~.direct.upscale_map`): those it offers at the
    factor it may run at."""
    return prior.candidates(kind, min(scale, max_prior_scale or scale))


def check_factor(side: int, scale: int, priors: Sequence[Prior] = ()) -> int:
    """The factor a map of ``side`` texels (its shorter side, at most ``CROP``) is checked
    at: ``scale``, halved while the crop one scale down would hold fewer than ``MIN_SIDE``
    texels a side and every prior in ``priors`` upscales by the half (never below 2)."""
    f = scale
    while side < MIN_SIDE * f and f % 4 == 0 and all(f // 2 in p.scales for p in priors):
        f //= 2
    return f


def _centre(a: np.ndarray, size: int) -> np.ndarray:
    h, w = a.shape[:2]
    y, x = max(0, (h - size) // 2), max(0, (w - size) // 2)
    return a[y : y + size, x : x + size]


def scorer(
    crop: np.ndarray, shape: tuple[int, ...], covered: np.ndarray | None, scale: int
) -> tuple[Callable[[np.ndarray, np.ndarray], float], np.ndarray]:
    """(``db(up, ref)``, the texels it compares as a mask): ``db`` is the PSNR of an upscale
    of ``shape`` against ``ref`` (channels of the map's centre ``crop``) over the texels both
    cover (the mask's shape), of those only the ones ``covered`` (H, W, the whole map's mask)
    marks, or all of them when that leaves fewer than ``(4 scale)²``."""
    h, w = min(crop.shape[0], shape[0]), min(crop.shape[1], shape[1])
    mask = np.ones((h, w), dtype=bool)
    if covered is not None:
        m = _centre(covered, CROP)[:h, :w]
        if int(m.sum()) >= (4 * scale) ** 2:
            mask = m

    def db(up: np.ndarray, ref: np.ndarray) -> float:
        diff = (up[:h, :w].astype(np.float64) - ref[:h, :w])[mask]
        se = float((diff**2).sum())
        return 100.0 if se <= 0 else 10.0 * math.log10(diff.size / se)

    return db, mask


def channel_entries(kind: str, channels: int) -> list[slice]:
    """The channel entries of a map of ``kind`` with ``channels`` channels (alpha included),
    as the check decides them: each colour channel of a data map on its own (occlusion,
    roughness and metallic packed in one image are unrelated images), a colour or normal map
    as a whole."""
    n_colour = 3 if channels >= 3 else 1
    return [slice(c, c + 1) for c in range(n_colour)] if kind == "data" else [slice(0, n_colour)]


def detail_gain(up: np.ndarray, bicubic: np.ndarray, ref: np.ndarray) -> float:
    """The ``k`` (within :data:`GAIN_RANGE`) for which ``bicubic + k (up - bicubic)`` is
    closest to ``ref`` in least squares, the three given over the same texels: how much of
    an upscale's departure from bicubic's the map bears out. 1 where the upscale is
    bicubic's."""
    d = (up.astype(np.float64) - bicubic).ravel()
    dd = float(d @ d)
    if dd <= 1e-12:
        return 1.0
    k = float(d @ (ref.astype(np.float64) - bicubic).ravel()) / dd
    return float(np.clip(k, *GAIN_RANGE))


def with_gain(hr: np.ndarray, bicubic: np.ndarray, gains: Sequence[float], kind: str,
              share: float) -> np.ndarray:  # fmt: skip
    """``hr`` (sH, sW, C, an upscale of a map of ``kind``) with its departure from
    ``bicubic`` (the same map's bicubic upscale) scaled per channel entry by
    ``1 + share (k - 1)``, ``k`` the entry's fitted gain (``gains``, a
    :func:`prior_self_check` report's); clamped to [0, 1], alpha kept. Texels where ``hr`` is
    bicubic's stay bicubic's. Unchanged when ``share`` is 0 or ``kind`` is not in
    :data:`GAIN_KINDS`."""
    if not share or kind not in GAIN_KINDS:
        return hr
    parts = channel_entries(kind, hr.shape[2])
    if len(gains) != len(parts):
        raise ValueError(f"{len(gains)} gains for a {kind} map of {len(parts)} channel entries")
    out = hr.copy()
    for part, k in zip(parts, gains, strict=True):
        g = 1.0 + share * (float(k) - 1.0)
        if g != 1.0:
            b = bicubic[..., part]
            out[..., part] = np.clip(b + g * (hr[..., part] - b), 0.0, 1.0)
    return out


def prior_self_check(
    prior: Prior,
    lr_map: np.ndarray,
    scale: int,
    kind: str = "colour",
    *,
    max_prior_scale: int | None = None,
    covered: np.ndarray | None = None,
    cutout: float | None = None,
    keep: dict | None = None,
    stored: np.ndarray | None = None,
    store: Callable[[np.ndarray], np.ndarray] | None = None,
    pick_only: bool = False,
) -> dict | None:
    """``{"priors", "prior_db", "bicubic_db", "candidates", "texels", "use_prior",
    "channels", "margins", "gains", "flat", "spread", "scale"}`` for one map (H, W, C) as
    stored, or None when it is not at least ``4 * scale`` texels a side (nothing to check
    on: the prior is used, as the paper does). The report's ``scale`` is the factor the map
    was checked at: ``scale``, or less for a small map (:func:`check_factor`).

    Each of the prior's candidates (:func:`offered`) upscales the map from one scale down;
    ``candidates`` gives each one's PSNR by name, ``prior_db`` the best of them. ``kind`` is
    the map's (prior/direct.py): colour and normal maps are decided as a whole; the channels
    of a data map (occlusion, roughness, metallic packed in one image) are unrelated images,
    so each is decided on its own: per colour channel (one entry for colour and normal maps),
    ``priors`` names the candidate that reconstructs it best and ``channels`` says whether
    that one beats bicubic (the prior initialises it), ``margins`` by how many dB (negative:
    bicubic is closer), ``gains`` its :func:`detail_gain` (the scale of that candidate's
    departure from bicubic that fits the map best one scale down); ``use_prior`` is whether
    any does. ``flat`` per entry: its compared
    texels vary less than :data:`FLAT_STD` in every channel and none departs from the median
    by more than :data:`FLAT_PEAK`; such an entry keeps bicubic whatever its margin.
    ``spread`` per entry: those numbers in 8-bit levels (:func:`spread`).
    ``max_prior_scale`` as in :func:`~.direct.upscale_map`: the check scores the upscaling
    the init will use.
    ``covered`` (H, W) bool: the texels the mesh's UVs cover; only those are compared (all of
    the crop when it covers fewer than ``4 * scale`` squared of them). ``cutout``: upscale as
    a cutout's colour (:func:`~.direct.with_cutout`), as the init will. ``keep``: filled
    with what the check compared (``crop``, ``small``, ``factor``, ``mask``, the scorer
    ``db``, the candidates' upscales ``ups`` by name, ``bicubic``; each cut to the mask's
    shape), for a decision made from the same upscales (prior/blend.py). ``stored`` (the
    map's shape): the map as stored where ``lr_map`` is it deblocked; what the deblocking
    took out, its RMS per channel over the compared texels, raises the flat floor
    (:data:`FLAT_STD`). ``store``: the map's storage (an image -> as its file would hold it
    and the run reads it; asset/jpeg.py ``stored_as``), applied to the crop one scale down
    before the candidates upscale it, as it was to the map itself. ``pick_only``: the check
    picks among the candidates alone: every entry takes its closest candidate (``channels``
    all true), whatever its margin over bicubic and whether it is flat."""
    a = np.asarray(lr_map, dtype=np.float32)
    n_colour = 3 if a.shape[2] >= 3 else 1
    crop = _centre(a, CROP)
    if min(crop.shape[:2]) < 4 * scale:
        return None
    candidates = offered(prior, kind, scale, max_prior_scale)
    scale = check_factor(min(crop.shape[:2]), scale, candidates)
    if covered is not None and covered.shape != a.shape[:2]:
        raise ValueError(f"coverage mask {covered.shape} does not match the map {a.shape[:2]}")
    small = degrade_image(crop, scale, normal_map=kind == "normal", kernel=run_kernel())
    if store is not None:
        small = store(small)
    ups = [
        upscale_map(c, small, kind, scale, max_prior_scale=max_prior_scale, cutout=cutout)
        for c in candidates
    ]
    up_b = bicubic_map(small, kind, scale, cutout=cutout)
    score, mask = scorer(crop, up_b.shape, covered, scale)
    if keep is not None:
        h, w = mask.shape
        keep.update(crop=crop[:h, :w], small=small, factor=scale, mask=mask, db=score,
                    ups={c.name: up[:h, :w] for c, up in zip(candidates, ups, strict=True)},
                    bicubic=up_b[:h, :w])  # fmt: skip

    def db(up: np.ndarray, c: slice) -> float:
        return score(up[..., c], crop[..., c])

    whole = slice(0, n_colour)
    b = db(up_b, whole)
    parts = channel_entries(kind, a.shape[2])
    h, w = mask.shape
    seen = crop[:h, :w][mask]
    floor = np.full(a.shape[2], FLAT_STD)
    if stored is not None:  # the stored file's noise the deblocking took out, per channel
        floor = floor + (_centre(np.asarray(stored, np.float32), CROP)[:h, :w][mask] - seen).std(0)
    best, channels, margins, gains, flat, spreads = [], [], [], [], [], []
    for part in parts:
        scores = [db(up, part) for up in ups]
        i = max(range(len(ups)), key=lambda k: (scores[k], -k))  # ties: the earlier one
        best.append(candidates[i].name)
        margin = scores[i] - db(up_b, part)
        margins.append(round(margin, 3))
        gains.append(round(detail_gain(ups[i][:h, :w][mask][:, part], up_b[:h, :w][mask][:, part],
                                       seen[:, part]), 3))  # fmt: skip
        is_flat, levels = spread(seen[:, part], floor[part])
        flat.append(is_flat)
        spreads.append(levels)
        channels.append(pick_only or (margin > 0 and not is_flat))
    each = {c.name: round(db(up, whole), 3) for c, up in zip(candidates, ups, strict=True)}
    return {
        "priors": best,
        "prior_db": max(each.values()),
        "bicubic_db": round(b, 3),
        "candidates": each,
        "texels": int(mask.sum()),
        "use_prior": any(channels),
        "channels": channels,
        "margins": margins,
        "gains": gains,
        "flat": flat,
        "spread": spreads,
        "scale": scale,
    }


def spread(texels: np.ndarray, floor: np.ndarray) -> tuple[bool, dict]:
    """(whether the entry is flat, how it varies in 8-bit levels) for ``texels`` (N, C, one
    entry's compared texels) held to ``floor`` (C): flat when under the floor in every
    channel and no texel is more than :data:`FLAT_PEAK` from its channel's median; the
    levels are the ``rms`` and ``floor`` per channel and that ``peak`` deviation."""
    rms = texels.std(axis=0)
    peak = float(np.abs(texels - np.median(texels, axis=0)).max())
    levels = {
        "rms": [round(float(v) * 255, 2) for v in rms],
        "floor": [round(float(v) * 255, 2) for v in floor],
        "peak": round(peak * 255, 1),
    }
    return bool((rms < floor).all() and peak <= FLAT_PEAK), levels


def chosen(
    prior: Prior,
    kind: str,
    check: dict | None,
    n: int,
    scale: int,
    max_prior_scale: int | None = None,
) -> list[Prior]:
    """Per entry of a map's ``channels`` (``n`` of them), the candidate of ``prior`` that
    ``check`` (a :func:`prior_self_check` report of the map at ``scale`` with the prior
    capped at ``max_prior_scale``) chose; the first candidate without one."""
    candidates = offered(prior, kind, scale, max_prior_scale)
    names = (check or {}).get("priors") or [candidates[0].name] * n
    by_name = {c.name: c for c in candidates}
    return [by_name.get(name, candidates[0]) for name in names]


def merge_channels(prior_map: np.ndarray, bicubic: np.ndarray, channels: list[bool]) -> np.ndarray:
    """The prior's upscaled map where ``channels`` says so, bicubic's elsewhere (alpha, past
    the colour channels, is the same in both)."""
    if len(channels) == 1:
        return prior_map if channels[0] else bicubic
    out = bicubic.copy()
    for c, use in enumerate(channels):
        if use:
            out[..., c] = prior_map[..., c]
    return out


def upscale_each(
    priors: Sequence[Prior],
    pixels: np.ndarray,
    kind: str,
    scale: int,
    channels: Sequence[Sequence[int] | None] | None = None,
    **kw,
) -> list[np.ndarray]:
    """The map upscaled by each of ``priors`` (:func:`~.direct.upscale_map` with ``kw``; a data
    map on the ``channels`` given for that prior, all when None); a ``progress`` callback in
    ``kw`` sees the runs as one: ``(tiles done, tiles)`` over all of them."""
    progress = kw.pop("progress", None)
    n, out = len(priors), []
    for k, p in enumerate(priors):
        if progress is not None:
            kw["progress"] = lambda done, total, k=k: progress(k * total + done, n * total)
        only = None if channels is None else channels[k]
        out.append(upscale_map(p, pixels, kind, scale, channels=only, **kw))
    return out


def upscale_channels(
    sources: Sequence[Prior | None],
    pixels: np.ndarray,
    kind: str,
    scale: int,
    base: np.ndarray | None = None,
    **kw,
) -> np.ndarray:
    """A map upscaled channel entry by channel entry (as ``channels`` counts them): each
    entry of ``sources`` names the prior for it (:func:`upscale_each` with ``kw``: each prior
    runs once, on a data map's channels it is named for), None keeps ``base``'s (bicubic;
    without ``base``, the channels no prior is named for come out as bicubic's)."""
    out = base
    priors = list(dict.fromkeys(q for q in sources if q is not None))
    each = len(sources) > 1 and kind == "data"
    only = [[c for c, q in enumerate(sources) if q is p] for p in priors] if each else None
    ups = upscale_each(priors, pixels, kind, scale, only, **kw)
    for p, up in zip(priors, ups, strict=True):
        out = up if out is None else merge_channels(up, out, [q is p for q in sources])
    if out is None:
        raise ValueError("no prior and no base map to upscale with")
    return out
