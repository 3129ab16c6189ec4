"""`pbrsr bench oracle`: where the render error of an upscaled asset lives, map by map.

For each asset (as in ``pbrsr bench upscale``: the procedural one and every shared asset, LR
made by ``pbrsr degrade``) the LR maps are upscaled by bicubic interpolation, and the render
PSNR is measured again with one map's channels (albedo, roughness, metallic, normal,
occlusion, emissive) replaced by the ground truth's. The gain of each replacement is an
upper bound on what any upscaler of that map alone can add to render PSNR over bicubic, so
the table says which maps a method has to get right to move render PSNR, and how far a
target such as "+1.5 dB over bicubic" is from what each map can give.

Replacing several maps does not add up the single gains (the error terms interact); with
every map replaced the render equals the ground truth's (reported as ``all``: infinite PSNR).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from pbrsr_core.asset import load_asset
from pbrsr_core.asset.model import Asset
from pbrsr_core.degrade import degrade_asset
from pbrsr_core.metrics import MAP_CHANNELS, RenderEvaluator, images_for
from pbrsr_core.options import UpscaleOptions
from pbrsr_core.pipeline import upscale_asset

from .results import pyplot
from .shared import SHARED_ASSETS
from .upscale import bench_assets, cpu_evaluator, eval_lights


def with_gt_maps(pred: Asset, gt: Asset, names: list[str]) -> Asset:
    """``pred`` with the channels of the maps ``names`` (keys of ``MAP_CHANNELS``) taken from
    ``gt`` (same document structure and image sizes)."""
    pixels = {im.index: im.pixels for im in pred.images}
    for name in names:
        role, ch = MAP_CHANNELS[name]
        for i in images_for(gt, role):
            g = gt.images[i].pixels
            if g.shape[2] <= ch.start:
                continue
            p = pixels[i]
            if p.shape != g.shape:
                raise ValueError(
                    f"image {i}: prediction {p.shape} and ground truth {g.shape} differ in shape"
                )
            p = p.astype(np.float32, copy=True)
            p[..., ch] = g[..., ch]
            pixels[i] = p
    images = [dataclasses.replace(im, pixels=pixels[im.index]) for im in pred.images]
    return dataclasses.replace(pred, images=images)


def oracle_gains(gt: Asset, bicubic: Asset, evaluator: RenderEvaluator) -> dict:
    """Render PSNR of ``bicubic``, and of it with each map the asset has (then every map)
    replaced by the ground truth's."""
    present = [n for n, (role, _) in MAP_CHANNELS.items() if images_for(gt, role)]
    row = {"bicubic": evaluator(bicubic)["render.psnr"], "maps": {}}
    for name in present:
        row["maps"][name] = evaluator(with_gt_maps(bicubic, gt, [name]))["render.psnr"]
    row["all"] = evaluator(with_gt_maps(bicubic, gt, present))["render.psnr"]
    return row


def run(
    *,
    out_dir: Path = Path("bench-out/oracle"),
    assets: list[str] | None = None,
    scale: int = 4,
    eval_res: int = 256,
    eval_views: int = 240,
    procedural_size: int = 512,
    include_procedural: bool = True,
    shared: Path = SHARED_ASSETS,
    log=print,
) -> list[dict]:
    """Run the benchmark; write ``oracle.json`` and ``oracle.png``; return the rows."""

    out_dir.mkdir(parents=True, exist_ok=True)
    lights, light_names = eval_lights(shared)
    work = Path(tempfile.mkdtemp(prefix="pbrsr-oracle-"))
    rows: list[dict] = []
    try:
        todo = bench_assets(work, include_procedural, procedural_size, shared, assets, log)
        for name, gt_path in todo:
            log(f"== {name}")
            lr = degrade_asset(gt_path, work / name / "lr" / gt_path.name, scale)[0]
            upscale_asset(
                lr,
                work / name / "out",
                UpscaleOptions(method="bicubic", scale=scale),
                work_dir=work / name / "work",
            )
            gt = load_asset(gt_path)
            evaluator = cpu_evaluator(gt, eval_res, eval_views, lights)
            row = {
                "asset": name,
                **oracle_gains(gt, load_asset(work / name / "out" / lr.name), evaluator),
            }
            rows.append(row)
            log("   " + _row_text(row))
        meta = {
            "scale": scale,
            "eval_res": eval_res,
            "eval_views": eval_views,
            "lights": light_names,
        }
        (out_dir / "oracle.json").write_text(json.dumps({**meta, "rows": rows}, indent=2))
        plot(rows, out_dir / "oracle.png")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return rows


def _row_text(row: dict) -> str:
    gains = " ".join(f"{k}={v - row['bicubic']:+.2f}" for k, v in row["maps"].items())
    return f"bicubic={row['bicubic']:.2f} dB; with the GT map: {gains}"


def markdown_table(rows: list[dict]) -> str:
    """Bicubic render PSNR and the gain with each map from the ground truth ('-': no such
    map), plus the mean over the shared assets (the procedural one left out)."""
    names = list(MAP_CHANNELS)
    lines = [
        "| asset | bicubic render PSNR | " + " | ".join(f"GT {n}" for n in names) + " |",
        "|" + "---|" * (2 + len(names)),
    ]

    def cell(row: dict, n: str) -> str:
        v = row["maps"].get(n)
        return "-" if v is None else f"{v - row['bicubic']:+.2f}"

    for r in rows:
        lines.append(
            f"| {r['asset']} | {r['bicubic']:.2f} | " + " | ".join(cell(r, n) for n in names) + " |"
        )
    shared = [r for r in rows if r["asset"] != "procedural"]
    if shared:
        means = []
        for n in names:
            gains = [r["maps"][n] - r["bicubic"] for r in shared if n in r["maps"]]
            means.append(f"{np.mean(gains):+.2f} ({len(gains)})" if gains else "-")
        lines.append(
            f"| mean of {len(shared)} shared assets (assets with the map) | | "
            + " | ".join(means)
            + " |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    plt = pyplot()

    names = list(MAP_CHANNELS)
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(rows)), 4))
    width = 0.8 / len(names)
    for k, n in enumerate(names):
        xs = [i + k * width for i, r in enumerate(rows) if n in r["maps"]]
        ys = [r["maps"][n] - r["bicubic"] for r in rows if n in r["maps"]]
        ax.bar(xs, ys, width, label=f"GT {n}")
    ax.set_xticks([i + 0.4 - width / 2 for i in range(len(rows))])
    ax.set_xticklabels([r["asset"] for r in rows], rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("render PSNR over bicubic (dB)")
    ax.set_title("render PSNR with one map from the ground truth, others bicubic")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
