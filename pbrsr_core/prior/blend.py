"""A data channel as a blend of its upscales, weighted by a fit one scale down.

The self-check (prior/selfcheck.py) upscales each map from one scale down with every
candidate the prior offers, and a metallic-roughness map's roughness and metallic also with
the colour map as guide (prior/guided.py). Picking the closest of them throws away what the
others know: they err in different places (a network sharpens edges the guided fit follows
only where the paint does). Per channel of a data map, :func:`blend_weights` fits the convex
weights of the upscales and bicubic that come closest to the LR channel one scale down (least
squares, weights clipped to [0, 1] and summing to at most 1, bicubic taking the rest), and
the run applies the same weights to the upscales at the real scale. Three or four weights fit
on thousands of texels: the fit barely overfits the scale it is made at.

A channel is blended where its blend beats bicubic one scale down by the preset's
``blend_margin`` (and, with ``blend_pick_db`` set, the self-check's pick by that much where
the pick beats bicubic; otherwise the channel takes the pick), and a candidate network runs
on a map where it adds ``blend_network_db`` to the map's blends, is a kept pick or (with
``blend_pick_floor``) holds a channel's blend at its pick one scale down; with
``blend_channel_db`` only on the channels whose blends it adds that much to. ``pbrsr
bench blend`` scores the rules at the real scale on the held-out CC0 materials' maps packed
as occlusion-roughness-metallic images (x4, pbr-srmd, 38 channels): the presets' margin 0,
0.1 dB networks, no pick rule +0.958 dB over bicubic, no channel below it, 0.62 networks per
map (docs/METHOD.md, "Data channels blended").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

MIN_WEIGHT = 0.05
"""An upscale weighted less than this is dropped and the rest refitted: a run does not call a
network for a sliver of a channel."""
RIDGE = 1e-6
"""Regularisation of the normal equations (upscales that agree everywhere)."""
Fit = tuple[list[str], list[float], float]
"""One channel's blend: the upscales' names, their weights, its dB over bicubic."""


def _fit(d: np.ndarray, t: np.ndarray) -> np.ndarray:
    a = d.T @ d
    w = np.linalg.solve(a + RIDGE * (np.trace(a) / len(a) + 1.0) * np.eye(len(a)), d.T @ t)
    w = np.clip(np.nan_to_num(w), 0.0, 1.0)
    return w / max(1.0, float(w.sum()))


def blend_weights(
    ups: Sequence[np.ndarray], bicubic: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None
) -> list[float]:
    """Weights of ``ups`` (each the shape of ``ref``; bicubic takes 1 - their sum) whose
    blend comes closest to ``ref`` over the texels ``mask`` marks (all when None): least
    squares, clipped to [0, 1], at most 1 in all, refitted without the upscales weighted
    under :data:`MIN_WEIGHT`."""
    if not ups:
        return []
    sel = slice(None) if mask is None else mask.reshape(-1)
    base = np.asarray(bicubic, np.float64).reshape(-1)[sel]
    t = np.asarray(ref, np.float64).reshape(-1)[sel] - base
    d = np.stack([np.asarray(u, np.float64).reshape(-1)[sel] - base for u in ups], -1)
    active = list(range(len(ups)))
    weights = np.zeros(len(ups))
    while active:
        w = _fit(d[:, active], t)
        keep = [k for k, wk in zip(active, w, strict=True) if wk >= MIN_WEIGHT]
        if keep == active:
            weights[active] = w
            break
        active = keep
    return [round(float(w), 4) for w in weights]


def blend(ups: Sequence[np.ndarray], bicubic: np.ndarray, weights: Sequence[float]) -> np.ndarray:
    """``bicubic`` + the ``weights`` of each upscale's difference from it (float32, [0, 1])."""
    out = np.asarray(bicubic, np.float32).copy()
    for u, w in zip(ups, weights, strict=True):
        if w:
            out += np.float32(w) * (np.asarray(u, np.float32) - bicubic)
    return np.clip(np.nan_to_num(out), 0.0, 1.0)


def blend_check(
    kept: dict,
    channels: Sequence[int],
    guided: dict[int, np.ndarray] | None = None,
    *,
    network_db: float,
    margin: float,
    picks: dict[int, tuple[str, float]] | None = None,
    channel_db: float | None = None,
) -> dict[int, Fit]:
    """Per channel of ``channels`` of a data map: (the upscales' names, their weights, the
    blend's dB over bicubic), one scale down, from what its self-check compared (``kept``,
    :func:`~.selfcheck.prior_self_check`): each candidate's upscale, and ``guided[c]`` where
    given (named ``"guided"``). A candidate is left out of every channel while that costs the
    map's channels less than ``network_db`` in all (counting only channels that gain more
    than ``margin``): its network then does not run on the map. With ``picks`` (per channel,
    the self-check's pick and its dB over bicubic one scale down, :func:`check_picks`) a
    candidate stays wherever leaving it out would put a channel's blend below its pick (or
    below the blend's own gain, where that is lower): the pick alone is a blend too. With
    ``channel_db``, a network left in is then also left out of each channel where it adds
    less than that to the channel's blend (one network run fewer per channel)."""
    db, ref, bic = kept["db"], kept["crop"], kept["bicubic"]
    guided = guided or {}

    def fit_channel(c: int, nets: list[str]) -> Fit:
        names = nets + (["guided"] if c in guided else [])
        ups = [kept["ups"][n][..., c] for n in nets] + ([guided[c]] if c in guided else [])
        w = blend_weights(ups, bic[..., c], ref[..., c], kept["mask"])
        gain = db(blend(ups, bic[..., c], w), ref[..., c]) - db(bic[..., c], ref[..., c])
        return names, w, round(gain, 3)

    def fit(nets: list[str]) -> dict[int, Fit]:
        return {c: fit_channel(c, nets) for c in channels}

    def worth(fits: dict) -> float:
        return sum(g for _, _, g in fits.values() if g > margin)

    def keeps_picks(now: dict, then: dict) -> bool:  # gains are rounded to 0.001 dB
        return all(
            then[c][2] >= min(now[c][2], db_pick) - 1e-3
            for c, (_, db_pick) in (picks or {}).items()
            if c in now
        )

    nets = list(kept["ups"])
    fits = fit(nets)
    while nets:
        weighted = [n for n in nets if any(w[ns.index(n)] for ns, w, _ in fits.values())]
        if weighted != nets:  # a network no channel weighs: refitted without it
            nets, fits = weighted, fit(weighted)
            continue
        dropped = {n: fit([m for m in nets if m != n]) for n in nets}
        can = [n for n in nets if keeps_picks(fits, dropped[n])]
        if not can:
            break
        n = min(can, key=lambda m: worth(fits) - worth(dropped[m]))
        if worth(fits) - worth(dropped[n]) >= network_db:
            break
        nets, fits = [m for m in nets if m != n], dropped[n]
    if channel_db is not None:
        for c in fits:
            fits[c] = _pruned_channel(c, fits[c], fit_channel, channel_db, keeps_picks)
    return fits


def _pruned_channel(
    c: int,
    fitted: Fit,
    fit_channel: Callable[[int, list[str]], Fit],
    channel_db: float,
    keeps_picks: Callable[[dict, dict], bool],
) -> Fit:
    """One channel's fit with its networks left out, the cheapest first, while each costs
    the channel's blend less than ``channel_db`` one scale down (and ``keeps_picks``)."""
    while True:
        nets = [n for n, w in zip(fitted[0], fitted[1], strict=True) if n != "guided" and w]
        trials = {n: fit_channel(c, [m for m in nets if m != n]) for n in nets}
        can = [n for n in nets if keeps_picks({c: fitted}, {c: trials[n]})]
        if not can:
            return fitted
        n = min(can, key=lambda m: fitted[2] - trials[m][2])
        if fitted[2] - trials[n][2] >= channel_db:
            return fitted
        fitted = trials[n]


def check_picks(check: dict, channels: Sequence[int]) -> dict[int, tuple[str, float]]:
    """The ``picks`` of :func:`blend_plan` from a data map's self-check report: per channel of
    ``channels`` whose pick beats bicubic, (the pick's name, its dB over bicubic one scale
    down)."""
    return {c: (check["priors"][c], check["margins"][c]) for c in channels if check["channels"][c]}


def blend_plan(
    fits: dict[int, tuple[list[str], list[float], float]],
    names: list[str],
    n: int,
    margin: float,
    picks: dict[int, tuple[str, float]] | None = None,
    pick_db: float | None = None,
) -> tuple[list[str], list[list[float]], list[bool]]:
    """What a run blends from :func:`blend_check`'s ``fits`` for a map of ``n`` channels
    whose upscales are ``names`` (every candidate, then ``"guided"`` where offered): the
    sources some channel weighs, per channel their weights (all 0: bicubic's), and per
    channel whether it is blended (its blend beats bicubic by more than ``margin`` one
    scale down). ``picks``: per channel whose self-check pick beats bicubic, (the pick's
    name, its dB over bicubic one scale down); with ``pick_db`` such a channel takes its
    pick alone (weight 1) unless its blend beats the pick by more than ``pick_db`` there,
    and the pick's network runs whether or not a blend weighs it."""
    weights = [[0.0] * len(names) for _ in range(n)]
    use = [False] * n
    picks = picks or {}
    for c, (fit_names, w, gain) in fits.items():
        pick = picks.get(c)
        if pick_db is not None and pick is not None and gain <= pick[1] + pick_db:
            use[c] = True
            weights[c][names.index(pick[0])] = 1.0
        elif gain > margin:
            use[c] = True
            for name, wk in zip(fit_names, w, strict=True):
                weights[c][names.index(name)] = wk
    kept_at = [m for m in range(len(names)) if any(w[m] for w in weights)]
    return [names[m] for m in kept_at], [[w[m] for m in kept_at] for w in weights], use
