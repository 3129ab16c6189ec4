"""The quality targets of the texture priors and the optimiser (issue "Priors that know PBR
textures"), read off the rows of a ``pbrsr bench upscale`` run at x4.

- **prior**: direct with the run's prior at least 0.5 dB above direct with waifu2x-photo in
  mean render PSNR;
- **maps**: no map of direct below bicubic's on any asset (map PSNR over covered texels);
- **optimiser**: balanced at least 0.3 dB above direct in mean render PSNR, or at least 1 dB
  above it on the maps the renders constrain (normal, metallic, roughness) with its mean
  render no lower.

Each is measured over the assets every method it compares ran on (the bench leaves out the
procedural assets and the variants, as its summary does). The prior's third target, its
speed against waifu2x-photo, is ``pbrsr bench prior``'s."""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

PHOTO = "direct@waifu2x-photo"
CONSTRAINED = ("normal", "metallic", "roughness")
"""The maps the renders constrain, where the paper's optimiser gained most."""
PRIOR_LEAD_DB = 0.5
OPTIMISER_LEAD_DB = 0.3
CONSTRAINED_LEAD_DB = 1.0


def _by_asset(rows: list[dict], method: str, exclude: set[str]) -> dict[str, dict]:
    return {r["asset"]: r for r in rows if r["method"] == method and r["asset"] not in exclude}


def _lead(a: dict[str, dict], b: dict[str, dict]) -> tuple[float, int, list[str]]:
    """Mean render PSNR of ``a`` over ``b`` on the assets both have, how many ``a`` leads
    on, and those assets."""
    common = sorted(set(a) & set(b))
    diffs = [a[k]["render.psnr"] - b[k]["render.psnr"] for k in common]
    return float(np.mean(diffs)), sum(d > 0 for d in diffs), common


def worst_map(rows: list[dict], bic: dict[str, dict]) -> tuple[float, str]:
    """The lowest map PSNR difference of ``rows`` to their asset's bicubic row (``bic``, by
    asset) over every map both score, and where it is (``"asset map"``; empty, with inf,
    when they share none)."""
    worst, at = float("inf"), ""
    for r in rows:
        ref = bic[r["asset"]]
        for key in (k for k in r if k.startswith("maps.") and k.endswith(".psnr")):
            if key in ref and r[key] - ref[key] < worst:
                worst, at = r[key] - ref[key], f"{r['asset']} {key[5:-5]}"
    return worst, at


def targets(rows: list[dict], exclude: Collection[str] = ()) -> list[dict]:
    """Per target whose methods the rows hold (bicubic, direct, ``direct@waifu2x-photo``,
    balanced), over the assets but ``exclude``: ``{"target", "value_db", "met", "assets",
    "detail"}``. Values are rounded to the hundredth before they are compared, as the
    tables print them."""
    skip = set(exclude)
    bic, direct = _by_asset(rows, "bicubic", skip), _by_asset(rows, "direct", skip)
    photo, balanced = _by_asset(rows, PHOTO, skip), _by_asset(rows, "balanced", skip)
    out = []
    if set(direct) & set(photo):
        lead, ahead, common = _lead(direct, photo)
        out.append({
            "target": "prior",
            "value_db": round(lead, 2),
            "met": round(lead, 2) >= PRIOR_LEAD_DB,
            "assets": len(common),
            "detail": f"ahead on {ahead} of {len(common)} assets",
        })  # fmt: skip
    both = sorted(set(direct) & set(bic))
    worst, at = worst_map([direct[k] for k in both], bic)
    if at:  # a map both score
        out.append({
            "target": "maps",
            "value_db": round(worst, 2),
            "met": round(worst, 2) >= 0.0,
            "assets": len(both),
            "detail": at,
        })  # fmt: skip
    if set(balanced) & set(direct):
        lead, ahead, common = _lead(balanced, direct)
        maps = [
            balanced[k][f"maps.{m}.psnr"] - direct[k][f"maps.{m}.psnr"]
            for k in common
            for m in CONSTRAINED
            if f"maps.{m}.psnr" in balanced[k] and f"maps.{m}.psnr" in direct[k]
        ]
        on_maps = float(np.mean(maps)) if maps else 0.0
        met = round(lead, 2) >= OPTIMISER_LEAD_DB or (
            round(on_maps, 2) >= CONSTRAINED_LEAD_DB and round(lead, 2) >= 0.0
        )
        out.append({
            "target": "optimiser",
            "value_db": round(lead, 2),
            "met": met,
            "assets": len(common),
            "detail": f"ahead on {ahead} of {len(common)} assets; {on_maps:+.2f} dB on "
            f"their {len(maps)} normal, metallic and roughness maps",
        })  # fmt: skip
    return out


WORDING = {
    "prior": f"direct >= {PHOTO} + {PRIOR_LEAD_DB} dB (mean render PSNR)",
    "maps": "no map of direct below bicubic on any asset",
    "optimiser": f"balanced >= direct + {OPTIMISER_LEAD_DB} dB (mean render PSNR), or >= "
    f"+{CONSTRAINED_LEAD_DB:g} dB on the normal, metallic and roughness maps with renders no lower",
}


def targets_table(rows: list[dict], exclude: Collection[str] = ()) -> str:
    """:func:`targets` as markdown; empty when the rows hold none of them."""
    found = targets(rows, exclude)
    if not found:
        return ""
    lines = ["| target | measured | met |", "|---|---|---|"]
    for t in found:
        lines.append(
            f"| {WORDING[t['target']]} | {t['value_db']:+.2f} dB ({t['detail']}) "
            f"| {'yes' if t['met'] else 'no'} |"
        )
    return "\n".join(lines) + "\n"
