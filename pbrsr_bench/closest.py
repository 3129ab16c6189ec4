"""``closest:A|B|...`` in ``pbrsr bench upscale --methods``: a bound, not a method.

Per map entry, as the self-check picks them (a colour or normal map whole, a data map channel
by channel), the maps of whichever listed method come closest to the ground truth over the
covered texels; the row is scored as a run is. It measures how much a perfect pick among
those methods' upscales would gain over each of them: the most any check choosing among them
one scale down can reach. It needs the ground truth, so no run can make it; its seconds and
memory are those of the runs it picks from (the sum, the largest)."""

from __future__ import annotations

import dataclasses

import numpy as np

from pbrsr_core.asset.model import Asset
from pbrsr_core.maps import kind_of
from pbrsr_core.uvmask import coverage_masks

PREFIX = "closest:"


def parts(method: str) -> tuple[str, ...] | None:
    """The methods ``closest:A|B`` picks from, or None for a method that runs."""
    if not method.startswith(PREFIX):
        return None
    return tuple(method[len(PREFIX) :].split("|"))


def check(methods: tuple[str, ...]) -> None:
    """Raise ValueError unless every ``closest:`` method names two or more methods listed
    before it (their outputs are what it picks from), none of them a ``closest:`` one."""
    for i, m in enumerate(methods):
        names = parts(m)
        if names is None:
            continue
        if len(names) < 2 or not all(names):
            raise ValueError(f"method {m!r}: name two or more methods: closest:A|B")
        missing = [n for n in names if n not in methods[:i] or parts(n) is not None]
        if missing:
            raise ValueError(
                f"method {m!r}: {', '.join(missing)} must be listed before it as a method "
                "that runs (closest: picks among their outputs)"
            )


def closest_maps(preds: dict[str, Asset], gt: Asset) -> tuple[Asset, dict[str, list[str]]]:
    """The asset whose every map entry is the closest of ``preds``' (method -> output, each
    at the ground truth's size) to ``gt`` by mean squared error over the covered texels, and
    per image the method each entry came from. Colour and normal maps are one entry (their
    first three channels decide; the winner's image is taken whole); data maps one entry per
    channel. Images no material samples keep the first output's. The picks are keyed
    ``INDEX:NAME`` (two images of an asset may share a name)."""
    masks = coverage_masks(gt)
    first = next(iter(preds.values()))
    pixels: dict[int, np.ndarray] = {}
    picks: dict[str, list[str]] = {}
    for ref in gt.images:
        if ref.index not in masks:
            continue
        truth = ref.pixels.astype(np.float64)
        mask = masks[ref.index] if masks[ref.index].any() else np.ones(truth.shape[:2], bool)
        candidates = {k: p.images[ref.index].pixels for k, p in preds.items()}
        channels = truth.shape[2]
        if kind_of(ref.roles) == "data":
            entries = [[c] for c in range(channels)]
        else:
            entries = [list(range(min(3, channels)))]
        chosen = []
        for entry in entries:
            err = {
                k: float(((p[..., entry].astype(np.float64) - truth[..., entry]) ** 2)[mask].mean())
                for k, p in candidates.items()
            }
            chosen.append(min(err, key=err.__getitem__))
        if len(entries) == 1:
            out = candidates[chosen[0]]
        else:
            taken = zip(chosen, entries, strict=True)
            out = np.stack([candidates[k][..., c] for k, (c,) in taken], axis=-1)
        pixels[ref.index] = out
        picks[f"{ref.index}:{ref.name}"] = chosen
    images = [
        dataclasses.replace(im, pixels=pixels[im.index]) if im.index in pixels else im
        for im in first.images
    ]
    return dataclasses.replace(first, images=images), picks


def row_of(method: str, made: dict[str, tuple[dict, Asset]], gt: Asset, score) -> dict | None:
    """The bench row of ``closest:`` ``method`` on one asset from ``made`` (method -> its row
    and its output at the ground truth's size), scored by ``score(asset)``; None where one
    of its methods has no row there (refused on the asset)."""
    names = parts(method) or ()
    if not all(n in made for n in names):
        return None
    asset, picks = closest_maps({n: made[n][1] for n in names}, gt)
    rows = [made[n][0] for n in names]
    return {
        "asset": rows[0]["asset"],
        "method": method,
        "wall_s": round(sum(r["wall_s"] for r in rows), 2),
        "run_s": round(sum(r["run_s"] for r in rows), 2),
        "peak_rss_mib": max(r["peak_rss_mib"] for r in rows),
        "timings": {},
        "lr_model": None,
        **{k: round(v, 3) for k, v in score(asset).items()},
        "curve": [],
        "picks": picks,
    }
