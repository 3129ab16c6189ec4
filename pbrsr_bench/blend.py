"""``pbrsr bench blend``: the presets' blend of data channels, rule by rule, on held-out
materials.

The CPU presets blend each data channel of a metallic-roughness map from its upscales
(``pbrsr_core/prior/blend.py``): weights fitted one scale down, a channel kept bicubic's unless
its blend beats bicubic by a margin there, and a candidate network run on the map only where it
adds a set number of dB to the map's channels. Here both rules are scored at the real scale on
what a glTF asset would hold: per held-out material of a texture folder (the split of ``pbrsr
priors train``, so no texture network has seen them) that has a colour map and a roughness,
metallic or occlusion map, each HR crop of ``size`` pixels on a grid over the material is
packed as an occlusion-roughness-metallic map (a map it lacks held constant, as an exporter
writes it), degraded by the evaluation protocol with its colour map, and run through the steps
of the pipeline: the colour map's self-check (its pick guides roughness and metallic), the data
map's self-check, the guided upscale, :func:`blend_check` and :func:`blend_plan` for every pair
of rules asked for. Per channel the result holds the gain over bicubic against the HR crop of
each rule's blend (and its gain one scale down), of direct's choice (the check's pick where it
beats bicubic), of each upscale alone (and its gain one scale down, as the check saw it) and of
the oracle; per rule, the networks it runs per map and their runs (a network's run on one
channel). The plot puts each rule's mean gain against its network runs per map. With ``jpeg``
both LR crops are stored as JPEG files of that quality hold them (4:4:4, as ``pbrsr degrade``
writes JPEG maps, or 4:2:0 with ``subsampled``) and checked and upscaled as the presets do
(``check.presets_low_res``).
"""

from __future__ import annotations

from itertools import product
from pathlib import Path

import numpy as np

from pbrsr_core.prior import load_prior
from pbrsr_core.prior.blend import blend, blend_check, blend_plan, check_picks
from pbrsr_core.prior.direct import bicubic_map, upscale_map
from pbrsr_core.prior.guided import CHANNELS as GUIDED_CHANNELS
from pbrsr_core.prior.guided import guided_check_upscale, guided_upscale
from pbrsr_core.prior.selfcheck import offered, prior_self_check
from pbrsr_core.prior.train.data import (
    Material,
    load_materials,
    read_manifest,
    split_materials,
    texture_folder,
)

from .check import _jpeg_note, _psnr, presets_low_res, storage_model
from .results import pyplot, write_result

PACKED = ("ao", "roughness", "metallic")
"""The scalar maps of a glTF metallic-roughness image, channel by channel (occlusion in R)."""
ABSENT = {"ao": 1.0, "roughness": 1.0, "metallic": 0.0}
"""The value a packed map holds where the material has no such map (glTF's defaults)."""


def packed_crops(mat: Material, size: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, colour crop, packed crop), each (size, size, 3) float32 in [0, 1], on a grid
    of non-overlapping ``size`` windows over the material; none when it has no colour map or
    no packed map, or is smaller than ``size``."""
    have = [m for m in PACKED if m in mat.maps]
    if "basecolor" not in mat.maps or not have:
        return []
    h, w = mat.maps["basecolor"].shape[:2]
    if any(mat.maps[m].shape[:2] != (h, w) for m in have):
        return []
    out = []
    for y, x in product(range(0, h - size + 1, size), range(0, w - size + 1, size)):
        win = (slice(y, y + size), slice(x, x + size))
        colour = mat.maps["basecolor"][win].astype(np.float32) / 255.0
        packed = np.stack(
            [
                mat.maps[m][win][..., 0].astype(np.float32) / 255.0
                if m in mat.maps
                else np.full((size, size), ABSENT[m], np.float32)
                for m in PACKED
            ],
            -1,
        )
        out.append((f"{mat.name}@{y},{x}", colour, packed))
    return out


def score_crop(
    prior,
    colour: np.ndarray,
    packed: np.ndarray,
    present: list[int],
    scale: int,
    rules: list[tuple[float, float, float | None, bool, float | None]],
    max_prior_scale: int | None = None,
    jpeg: int | None = None,
    subsampled: bool = False,
    storage: bool = False,
) -> tuple[list[dict], dict[str, int], dict[str, int]]:
    """One material crop: per channel of ``present`` that its check does not find flat, the
    gains over bicubic at the real scale (rows); per rule the networks the blend runs, and
    their runs (one per network and channel)."""
    kw = {"max_prior_scale": max_prior_scale}
    store = storage_model(jpeg, subsampled, True, storage)
    (lr_c, stored_c), (lr_d, stored_d) = (
        presets_low_res(colour, scale, jpeg, subsampled=subsampled),
        presets_low_res(packed, scale, jpeg, subsampled=subsampled),
    )
    c_check = prior_self_check(prior, lr_c, scale, "colour", stored=stored_c, store=store, **kw)
    colour_candidates = offered(prior, "colour", scale, max_prior_scale)
    by_name = {p.name: p for p in colour_candidates}
    src = None
    if c_check is None or c_check["channels"][0]:
        src = by_name[c_check["priors"][0]] if c_check else colour_candidates[0]

    def upscale_guide(px: np.ndarray, f: int) -> np.ndarray:
        if src is None:
            return bicubic_map(px, "colour", f)
        return upscale_map(src, px, "colour", f, **kw)

    kept: dict = {}
    check = prior_self_check(
        prior, lr_d, scale, "data", keep=kept, stored=stored_d, store=store, **kw
    )
    if check is None:
        return [], {}, {}
    todo = [c for c in present if not check["flat"][c]]
    gc = [c for c in GUIDED_CHANNELS if c in todo]
    guided_small = {}
    if gc:
        up = guided_check_upscale(kept, lr_d.shape[:2], lr_c, upscale_guide, gc)
        guided_small = {c: up[..., m] for m, c in enumerate(gc)}
    # the real scale: every upscale a rule may weigh
    candidates = offered(prior, "data", scale, max_prior_scale)
    real = {p.name: upscale_map(p, lr_d, "data", scale, **kw) for p in candidates}
    bic = bicubic_map(lr_d, "data", scale)
    if gc:
        g = guided_upscale(lr_d[..., gc], lr_c, upscale_guide(lr_c, scale), scale)
        real["guided"] = bic.copy()
        for m, c in enumerate(gc):
            real["guided"][..., c] = g[..., m]
    inner = (slice(scale, -scale), slice(scale, -scale))

    def gain(up: np.ndarray, c: int) -> float:
        """Channel ``c`` of ``up`` (or ``up`` itself, one channel) over bicubic's."""
        ref = packed[inner][..., c]
        got = up[inner] if up.ndim == 2 else up[inner][..., c]
        return _psnr(got, ref) - _psnr(bic[inner][..., c], ref)

    def check_gain(c: int) -> dict[str, float]:
        """Each upscale's gain over bicubic one scale down, on the check's covered texels."""
        db, ref, bic_small = kept["db"], kept["crop"][..., c], kept["bicubic"][..., c]
        ups = {n: u[..., c] for n, u in kept["ups"].items()}
        if c in guided_small:
            ups["guided"] = guided_small[c]
        return {n: db(u, ref) - db(bic_small, ref) for n, u in ups.items()}

    rows = [
        {
            "channel": PACKED[c],
            "margin_db": check["margins"][c],
            "gain": {n: gain(u, c) for n, u in real.items() if n != "guided" or c in gc},
            "check_gain": check_gain(c),
            "direct": (gain(real[check["priors"][c]], c) if check["channels"][c] else 0.0),
            "rules": {},
            "fit_db": {},
        }
        for c in todo
    ]
    for r in rows:
        r["oracle"] = max(0.0, *r["gain"].values())
    networks, runs = {}, {}
    names = list(kept["ups"]) + (["guided"] if gc else [])
    picks = check_picks(check, todo)
    for margin, network_db, pick_db, floor, channel_db in rules:
        key = rule_name(margin, network_db, pick_db, floor, channel_db)
        fits = blend_check(kept, todo, guided_small, network_db=network_db, margin=margin,
                           picks=picks if floor else None, channel_db=channel_db)  # fmt: skip
        used, weights, use = blend_plan(fits, names, packed.shape[2], margin, picks, pick_db)
        networks[key] = sum(n != "guided" for n in used)
        runs[key] = sum(bool(w[m]) for w in weights for m, n in enumerate(used) if n != "guided")
        for r, c in zip(rows, todo, strict=True):
            r["fit_db"][key] = fits[c][2]
            if use[c]:
                out = blend([real[n][..., c] for n in used], bic[..., c], weights[c])
                r["rules"][key] = gain(out, c)
            else:
                r["rules"][key] = 0.0
    direct_nets = {check["priors"][c] for c in todo if check["channels"][c]}
    networks["direct"] = len(direct_nets)
    runs["direct"] = sum(bool(check["channels"][c]) for c in todo)
    return rows, networks, runs


def rule_name(
    margin: float,
    network_db: float,
    pick_db: float | None = None,
    floor: bool = False,
    channel_db: float | None = None,
) -> str:
    pick = "" if pick_db is None else f", over the pick {pick_db:g}"
    per = "" if channel_db is None else f", per channel {channel_db:g}"
    return (
        f"margin {margin:g}, networks {network_db:g}{pick}"
        + (", pick floor" if floor else "")
        + per
    )


def summarise(result: dict) -> list[dict]:
    """Per rule (and direct's choice): mean and worst gain over the channels, mean networks
    run per map and their runs (one per network and channel), channels below bicubic."""
    rows, crops = result["rows"], result["crops"]
    out = []
    for key in [*result["rules"], "direct"]:
        gains = [r["direct"] if key == "direct" else r["rules"][key] for r in rows]
        out.append(
            {
                "rule": key,
                "channels": len(gains),
                "mean": float(np.mean(gains)) if gains else 0.0,
                "worst": float(min(gains, default=0.0)),
                "below": sum(g < 0 for g in gains),
                "networks": float(np.mean([c["networks"][key] for c in crops])) if crops else 0.0,
                "runs": float(np.mean([c["runs"][key] for c in crops])) if crops else 0.0,
            }
        )
    return out


def run(
    log,
    out_dir: Path,
    textures: Path | None,
    prior: str,
    scale: int = 4,
    size: int = 512,
    margins: tuple[float, ...] = (0.0, 0.1),
    network_dbs: tuple[float, ...] = (0.0, 0.1),
    pick_dbs: tuple[float | None, ...] = (None,),
    pick_floors: tuple[bool, ...] = (False,),
    max_prior_scale: int | None = None,
    jpeg: int | None = None,
    channel_dbs: tuple[float | None, ...] = (None,),
    subsampled: bool = False,
    storage: bool = False,
) -> dict:
    """Score the blend of ``prior``'s data upscales at ``scale`` for every rule of
    ``margins``, ``network_dbs``, ``pick_dbs`` (None: no pick rule), ``pick_floors``
    (``blend_pick_floor``: networks kept where a channel needs them to reach its pick) and
    ``channel_dbs`` (``blend_channel_db``; None: off) on
    packed crops of ``size`` HR pixels of the held-out materials, the LR crops stored as JPEG
    of quality ``jpeg`` when given (4:2:0 with ``subsampled``; with ``storage`` the checks
    model that storage one scale down)."""
    if scale not in (2, 4, 8):
        raise ValueError(f"scale must be 2, 4 or 8, not {scale}")
    if size < 16 * scale:
        raise ValueError(f"the crop size must be at least {16 * scale} px at x{scale}")
    picked = [v for v in (*pick_dbs, *channel_dbs) if v is not None]
    if any(v < 0 for v in (*margins, *network_dbs, *picked)) or not (
        margins and network_dbs and pick_dbs and pick_floors and channel_dbs
    ):
        raise ValueError(
            "margins, network dBs, pick dBs, pick floors and channel dBs must be given, the dBs "
            "not negative"
        )
    root = texture_folder(textures)
    manifest = read_manifest(root)
    held = split_materials(manifest)[1]
    p = load_prior(prior)
    rules = list(product(margins, network_dbs, pick_dbs, pick_floors, channel_dbs))
    rows: list[dict] = []
    crops: list[dict] = []
    for mat in load_materials(root, held, manifest):
        present = [c for c, m in enumerate(PACKED) if m in mat.maps]
        for name, colour, packed in packed_crops(mat, size):
            log(f"{name}: {', '.join(PACKED[c] for c in present)}")
            crop_rows, networks, runs = score_crop(p, colour, packed, present, scale, rules,
                                             max_prior_scale, jpeg, subsampled,
                                             storage)  # fmt: skip
            if not crop_rows:
                continue
            rows += [{"map": f"{name}[{r['channel']}]", **r} for r in crop_rows]
            crops.append({"crop": name, "networks": networks, "runs": runs})
    if not crops:
        raise ValueError(
            f"no held-out material in {root} has a colour map and an occlusion, roughness or "
            f"metallic map of {size} px with a signal"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {
        "prior": p.name,
        "scale": scale,
        "size": size,
        "max_prior_scale": max_prior_scale,
        "jpeg": jpeg,
        "subsampled": subsampled,
        "storage": storage and jpeg is not None,
        "materials": held,
        "rules": [rule_name(*r) for r in rules],
        "rule_values": rules,
        "rows": rows,
        "crops": crops,
    }
    result["summary"] = summarise(result)
    return write_result(result, out_dir, "blend", plot)


def markdown_table(result: dict) -> str:
    rows = result["rows"]
    each = {n: float(np.mean([r["gain"][n] for r in rows if n in r["gain"]]))
            for n in dict.fromkeys(n for r in rows for n in r["gain"])}  # fmt: skip
    lines = [
        f"x{result['scale']}, prior {result['prior']}, {len(result['crops'])} packed crops of "
        f"{result['size']}² from the held-out materials"
        + _jpeg_note(result)
        + "; mean PSNR gain over bicubic per "
        "channel at the real scale (dB); each upscale alone: "
        + ", ".join(f"{n} {v:+.3f}" for n, v in each.items())
        + f"; oracle {np.mean([r['oracle'] for r in rows]):+.3f}; "
        + _ranking_note(rows),
        "",
        "| rule | channels | mean gain | worst | below bicubic | networks per map | network "
        "runs per map |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in result["summary"]:
        lines.append(
            f"| {s['rule']} | {s['channels']} | {s['mean']:+.3f} | {s['worst']:+.2f} | "
            f"{s['below']} | {s['networks']:.2f} | {s['runs']:.2f} |"
        )
    return "\n".join(lines)


def _ranking_note(rows: list[dict]) -> str:
    """How often the upscale (or bicubic) that gains most one scale down gains most at the
    real scale too, per channel."""

    def best(gains: dict[str, float]) -> str:
        return max({"bicubic": 0.0, **gains}.items(), key=lambda kv: kv[1])[0]

    same = sum(best(r["check_gain"]) == best(r["gain"]) for r in rows)
    return f"the best upscale one scale down is the real scale's best in {same} of {len(rows)}"


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    rules = dict(zip(result["rules"], result["rule_values"], strict=True))
    by_rule = {s["rule"]: s for s in result["summary"]}
    for margin, pick, floor, per in dict.fromkeys((m, p, f, c) for m, _, p, f, c in rules.values()):
        pts = sorted((by_rule[k]["runs"], by_rule[k]["mean"], n)
                     for k, (m, n, p, f, c) in rules.items()
                     if (m, p, f, c) == (margin, pick, floor, per))  # fmt: skip
        label = (f"margin {margin:g} dB" + ("" if pick is None else f", over the pick {pick:g}")
                 + (", pick floor" if floor else "")
                 + ("" if per is None else f", per channel {per:g}"))  # fmt: skip
        ax.plot([x for x, _, _ in pts], [y for _, y, _ in pts], "o-", label=label)
        for x, y, n in pts:
            ax.annotate(f"{n:g}", (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    d = by_rule["direct"]
    ax.plot([d["runs"]], [d["mean"]], "k*", ms=10, label="direct's choice")
    ax.set(
        xlabel="network runs per map, one per network and channel (labels: dB a network must "
        "add to the map)",
        ylabel="mean gain over bicubic, real scale (dB)",
        title=f"data-channel blend of {result['prior']} at x{result['scale']}",
    )
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
