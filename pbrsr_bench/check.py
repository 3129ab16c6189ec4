"""``pbrsr bench check``: how often the prior's self-check decides right, on maps no network
trained on.

The self-check (``pbrsr_core/prior/selfcheck.py``) picks, per colour map and per channel of a
data map, the candidate of the prior that rebuilds the LR map best from one scale down, and
keeps bicubic where none beats it. Here that decision is scored at the real scale: crops of
the held-out materials of a texture folder (the split of ``pbrsr priors train``, so no
texture network has seen them) are degraded by the evaluation protocol, checked as the
pipeline checks them, and upscaled by every candidate and by bicubic. Per map (data: per
distinct channel) the table gives the PSNR gain over bicubic, against the HR crop, of the
check's choice, of each candidate used everywhere, and of the oracle (the best of the
candidates and bicubic, known only with the HR crop); how many of the check's choices fall
below bicubic and by how much at worst; and how many maps the check left to bicubic where a
candidate gains. The plot puts each map's margin one scale down against its gain at the real
scale. With ``jpeg`` the LR crops are stored as JPEG files of that quality would hold them
(4:4:4, as ``pbrsr degrade`` writes JPEG maps, or with ``subsampled`` 4:2:0, the chroma at
half resolution as many published maps store it), as real assets ship their maps, and checked
and upscaled as the presets do: deblocked with those tables, the check told the map as
stored (its flat floor counts the noise the deblocking took out); the gains are then over
bicubic of the deblocked crop, the presets' own bicubic (``deblock_jpeg=False``: the file's
pixels as they are, as with ``deblock_jpeg`` off). With ``storage`` as well the check models
that storage one scale down (``check_storage``: the crop it upscales compressed with the same
tables and deblocked as the LR crop was).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from pbrsr_core.asset.jpeg import compress, deblock, standard_quant, stored_as
from pbrsr_core.degrade import degrade_image
from pbrsr_core.metrics import psnr
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.direct import bicubic_map, upscale_map
from pbrsr_core.prior.selfcheck import prior_self_check
from pbrsr_core.prior.train.data import (
    load_materials,
    read_manifest,
    split_materials,
    texture_folder,
    validation_crops,
)

from .results import pyplot, write_result

KINDS = ("colour", "data")
MISSED_DB = 0.1
"""A map the check leaves to bicubic counts as missed when a candidate gains more than this."""


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR capped at 100 dB (the self-check's cap), so that identical maps stay finite."""
    return min(psnr(a, b), 100.0)


def low_res(
    hr: np.ndarray, scale: int, jpeg: int | None = None, subsampled: bool = False
) -> np.ndarray:
    """The LR map of an HR crop (H, W, 3): the protocol's degradation, then with ``jpeg`` a
    JPEG file's pixels at that quality (4:4:4, or 4:2:0 with ``subsampled``)."""
    lr = degrade_image(hr, scale)
    if jpeg is None:
        return lr
    t = torch.from_numpy(np.ascontiguousarray(lr)).permute(2, 0, 1)[None]
    return compress(t, standard_quant(jpeg, subsampled))[0].permute(1, 2, 0).numpy()


def presets_low_res(
    hr: np.ndarray,
    scale: int,
    jpeg: int | None = None,
    deblock_jpeg: bool = True,
    subsampled: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """(the LR map as the presets check and upscale it, the map as stored where that differs):
    with ``jpeg`` (and ``deblock_jpeg``) the file's pixels deblocked with its tables, and those
    pixels; ``subsampled``: the file's chroma at half resolution (4:2:0)."""
    lr = low_res(hr, scale, jpeg, subsampled)
    if jpeg is None or not deblock_jpeg:
        return lr, None
    return deblock(lr, standard_quant(jpeg, subsampled)), lr


def storage_model(
    jpeg: int | None, subsampled: bool, deblock_jpeg: bool, storage: bool
) -> Callable[[np.ndarray], np.ndarray] | None:
    """The self-check's ``store`` for LR crops stored as JPEG of quality ``jpeg`` (4:2:0 with
    ``subsampled``, deblocked with ``deblock_jpeg``) when ``storage`` asks for it, else None."""
    if not storage or jpeg is None:
        return None
    return partial(stored_as, quant=standard_quant(jpeg, subsampled), deblocked=deblock_jpeg)


def score_map(
    prior,
    hr: np.ndarray,
    kind: str,
    scale: int,
    name: str,
    jpeg: int | None = None,
    deblock_jpeg: bool = True,
    subsampled: bool = False,
    storage: bool = False,
) -> list[dict]:
    """One HR crop (H, W, 3) in [0, 1]: the check's decision and every option's PSNR at the
    real scale, per part (the whole map for colour, each distinct channel for data)."""
    lr, stored = presets_low_res(hr, scale, jpeg, deblock_jpeg, subsampled)
    store = storage_model(jpeg, subsampled, deblock_jpeg, storage)
    check = prior_self_check(prior, lr, scale, kind, stored=stored, store=store)
    candidates = prior.candidates(kind, scale)
    ups = {c.name: upscale_map(c, lr, kind, scale) for c in candidates}
    bic = bicubic_map(lr, kind, scale)
    shave = scale  # the SR protocol's border
    inner = (slice(shave, -shave), slice(shave, -shave))
    parts = [0]
    if kind == "data":  # a scalar map packed twice is scored once
        same = [[np.array_equal(hr[..., c], hr[..., d]) for d in range(c)] for c in range(3)]
        parts = [c for c in range(3) if not any(same[c])]
    rows = []
    for entry in parts:
        sl = slice(entry, entry + 1) if kind == "data" else slice(0, 3)
        ref = hr[inner][..., sl]
        real = {n: _psnr(u[inner][..., sl], ref) for n, u in ups.items()}
        real_bic = _psnr(bic[inner][..., sl], ref)
        # too small to check: the pipeline uses the first candidate
        pick = candidates[0].name if check is None else check["priors"][entry]
        choice = pick if check is None or check["channels"][entry] else "bicubic"
        rows.append(
            {
                "map": name if kind == "colour" else f"{name}[{'RGB'[entry]}]",
                "kind": kind,
                "size": int(hr.shape[0]),
                "pick": pick,
                "choice": choice,
                "margin_db": None if check is None else check["margins"][entry],
                "gain": {n: v - real_bic for n, v in real.items()},
                "choice_gain": 0.0 if choice == "bicubic" else real[choice] - real_bic,
                "oracle_gain": max(0.0, *(v - real_bic for v in real.values())),
            }
        )
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Per kind and crop size: mean gains over bicubic and the check's wrong decisions."""
    out = []
    for kind in KINDS:
        for size in sorted({r["size"] for r in rows if r["kind"] == kind}, reverse=True):
            sel = [r for r in rows if r["kind"] == kind and r["size"] == size]
            names = list(sel[0]["gain"])
            below = [r["choice_gain"] for r in sel if r["choice_gain"] < 0]
            out.append(
                {
                    "kind": kind,
                    "size": size,
                    "maps": len(sel),
                    "check": float(np.mean([r["choice_gain"] for r in sel])),
                    "each": {n: float(np.mean([r["gain"][n] for r in sel])) for n in names},
                    "each_median": {
                        n: float(np.median([r["gain"][n] for r in sel])) for n in names
                    },
                    "oracle": float(np.mean([r["oracle_gain"] for r in sel])),
                    "below": len(below),
                    "worst": min(below, default=0.0),
                    "missed": sum(
                        r["choice"] == "bicubic" and r["oracle_gain"] > MISSED_DB for r in sel
                    ),
                }
            )
    return out


def run(
    log,
    out_dir: Path,
    textures: Path | None,
    prior: str,
    scale: int = 4,
    sizes: tuple[int, ...] = (1024, 512),
    jpeg: int | None = None,
    deblock_jpeg: bool = True,
    subsampled: bool = False,
    storage: bool = False,
) -> dict:
    """Score the self-check of ``prior`` at ``scale`` on centre-placed crops of ``sizes`` HR
    pixels (one per held-out material and kind; a material smaller than a size is skipped),
    the LR crops stored as JPEG of quality ``jpeg`` when given (4:2:0 with ``subsampled``;
    deblocked unless ``deblock_jpeg`` is off; with ``storage`` the check models that)."""
    if scale not in (2, 4, 8):
        raise ValueError(f"scale must be 2, 4 or 8, not {scale}")
    if not sizes or min(sizes) < 16 * scale:
        raise ValueError(f"crop sizes must be at least {16 * scale} px at x{scale}")
    root = texture_folder(textures)
    manifest = read_manifest(root)
    held = split_materials(manifest)[1]
    materials = load_materials(root, held, manifest)
    p = load_prior(prior)
    rows: list[dict] = []
    for size in sizes:
        for kind in KINDS:
            crops = validation_crops(materials, kind, size, per_material=1)
            for name, crop in crops:
                log(f"{kind} {size}: {name}")
                hr = crop.astype(np.float32) / 255.0
                rows += score_map(p, hr, kind, scale, name.split("#")[0], jpeg, deblock_jpeg,
                                  subsampled, storage)  # fmt: skip
    if not rows:
        raise ValueError(f"no held-out material in {textures} has maps of {min(sizes)} px")
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {
        "prior": p.name,
        "scale": scale,
        "jpeg": jpeg,
        "subsampled": subsampled,
        "deblock": deblock_jpeg,
        "storage": storage and jpeg is not None,
        "materials": held,
        "rows": rows,
        "summary": summarise(rows),
    }
    return write_result(result, out_dir, "check", plot)


def _jpeg_note(result: dict) -> str:
    if not result.get("jpeg"):
        return ""
    done = "deblocked" if result.get("deblock", True) else "not deblocked"
    chroma = "4:2:0" if result.get("subsampled") else "4:4:4"
    modelled = ", that storage modelled in the check" if result.get("storage") else ""
    return f", LR stored as JPEG quality {result['jpeg']} {chroma}, {done}{modelled}"


def markdown_table(result: dict) -> str:
    lines = [
        f"x{result['scale']}, prior {result['prior']}, held-out materials"
        + _jpeg_note(result)
        + "; mean PSNR gain over "
        "bicubic at the real scale (dB; a near-flat map, scored at 50-60 dB, moves a mean by "
        "dB that no render shows: the medians say what is typical)",
        "",
        "| kind | crop | maps | check's choice | each candidate alone | oracle | below bicubic "
        "(worst) | left to bicubic, a candidate gains |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in result["summary"]:
        each = ", ".join(
            f"{n} {v:+.3f} (median {s['each_median'][n]:+.2f})" for n, v in s["each"].items()
        )
        lines.append(
            f"| {s['kind']} | {s['size']}² | {s['maps']} | {s['check']:+.3f} | {each} | "
            f"{s['oracle']:+.3f} | {s['below']} ({s['worst']:+.2f}) | {s['missed']} |"
        )
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 5))
    for kind, marker in zip(KINDS, "os", strict=True):
        pts = [
            (r["margin_db"], r["gain"][r["pick"]])
            for r in result["rows"]
            if r["kind"] == kind and r["margin_db"] is not None
        ]
        if pts:
            x, y = zip(*pts, strict=True)
            ax.scatter(x, y, marker=marker, s=18, alpha=0.7, label=kind)
    ax.axhline(0, color="k", lw=0.6)
    ax.axvline(0, color="k", lw=0.6)
    ax.set(
        xlabel="check: its pick over bicubic, one scale down (dB)",
        ylabel="the same pick over bicubic, real scale (dB)",
        title=f"self-check of {result['prior']} at x{result['scale']}",
    )
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
