"""`pbrsr bench upscale`: speed against error.

For each asset (two procedural ones, a brick box and a foliage cutout, and every asset of
``../shared/assets`` when that folder is present) the ground-truth maps are degraded by the paper's
protocol (``pbrsr degrade``), then upscaled by bicubic, the direct prior and each PBR-SR preset.
Each run is a subprocess, so its wall time and peak memory (max RSS) are its own. PBR-SR runs also
save their maps at intermediate iterations, so the plot shows render PSNR against wall time as
curves, with the baselines as lines. Metrics: PSNR per map over UV-covered texels, and render PSNR
over the paper's evaluation views under two environment maps.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from pbrsr_core.asset import load_asset, make_cutout_asset, make_demo_asset
from pbrsr_core.asset.images import jpeg_request
from pbrsr_core.asset.model import Asset
from pbrsr_core.degrade import check_kernels, degrade_asset
from pbrsr_core.metrics import RenderEvaluator, eval_cameras, map_metrics, stored_like
from pbrsr_core.options import DEFAULT_PRIOR
from pbrsr_core.render.light import EnvLight
from pbrsr_core.scene import procedural_light, rotated_procedural_light

from . import closest
from .machine import machine
from .shared import SHARED_ASSETS
from .targets import targets_table, worst_map
from .variants import BENCH_VARIANTS

DEFAULT_METHODS = ("bicubic", "direct", "fast", "balanced")
ENVMAPS = ("studio_small_03_1k.hdr", "venice_sunset_1k.hdr")
MAP_COLUMNS = ("albedo", "roughness", "metallic", "normal", "occlusion", "emissive")


def find_assets(shared: Path, names: list[str] | None) -> list[tuple[str, Path]]:
    """(name, main file) of each shared asset folder, optionally filtered by name."""
    out = []
    if not shared.is_dir():
        return out
    for d in sorted(p for p in shared.iterdir() if p.is_dir() and p.name != "envmaps"):
        files = sorted(d.glob("*.gltf")) + sorted(d.glob("*.glb"))
        if files and (not names or d.name in names):
            out.append((d.name, files[0]))
    return out


def bench_assets(
    work: Path,
    include_procedural: bool,
    procedural_size: int,
    shared: Path,
    names: list[str] | None,
    log,
    include_shared: bool = True,
    variants: bool = False,
) -> list[tuple[str, Path]]:
    """(name, ground-truth file) of the assets a benchmark runs on: the procedural demo asset
    and a procedural foliage cutout (alphaMode MASK; both written under ``work``) and, with
    ``include_shared``, the shared assets (all, or those ``names``), saying so when the shared
    folder is absent. With ``variants``, also each :data:`~pbrsr_bench.variants.BENCH_VARIANTS`
    entry whose source asset is there (all, or those ``names``), made under ``work``. A name
    with no folder there is a ValueError."""
    todo: list[tuple[str, Path]] = []
    if include_procedural:
        todo.append(
            ("procedural", make_demo_asset(work / "procedural" / "demo.glb", size=procedural_size))
        )
        cutout = make_cutout_asset(work / "procedural-cutout" / "cutout.glb", size=procedural_size)
        todo.append(("procedural-cutout", cutout))
    if include_shared and shared.is_dir():
        kinds = BENCH_VARIANTS if variants else {}
        chosen = {v: kinds[v] for v in kinds if not names or v in names}
        plain = [n for n in names or () if n not in kinds]
        sources = sorted({*plain, *(src for src, _ in chosen.values())}) if names else None
        found = dict(find_assets(shared, sources))
        missing = sorted(set(sources or ()) - set(found))
        if missing:
            raise ValueError(f"asset folder {', '.join(missing)} not found in {shared}")
        todo.extend((n, p) for n, p in found.items() if not names or n in plain)
        for name, (src, make) in chosen.items():
            if src in found:
                log(f"== {name}: made from {src}")
                todo.append((name, make(found[src], work / name / f"{found[src].stem}.glb")))
    elif include_shared:
        log(f"shared assets folder {shared} not present: procedural asset only")
    return todo


def cpu_evaluator(gt: Asset, eval_res: int, eval_views: int, lights: list) -> RenderEvaluator:
    """The benchmarks' render-PSNR evaluator of ``gt``: the paper's view sphere
    (``eval_views`` views of ``eval_res``²) under ``lights``, on the CPU."""
    import torch

    return RenderEvaluator(
        gt, cameras=eval_cameras(eval_res, eval_views), lights=lights, device=torch.device("cpu")
    )


def eval_lights(shared: Path) -> tuple[list[EnvLight], list[str]]:
    env_dir = shared / "envmaps"
    paths = [env_dir / n for n in ENVMAPS if (env_dir / n).is_file()]
    if len(paths) == 2:
        return [EnvLight.from_file(p) for p in paths], [p.stem for p in paths]
    return [procedural_light(), rotated_procedural_light(150.0)], [
        "procedural",
        "procedural-rotated",
    ]


OPTION_CHANGES = ("max_size", "lr_kernel", "maps", "other_maps")
"""``+key=value`` changes that are upscale options, which every method takes, not a preset's
numbers: ``direct+max_size=512``, ``direct+lr_kernel=area``, ``balanced+maps=base_color|normal``
(list items joined by ``|``, since a comma separates methods),
``balanced+maps=base_color|normal+other_maps=bicubic``."""


def parse_method(method: str) -> tuple[str, str | None, dict]:
    """``NAME[@PRIOR][+key=value...]`` -> (name, prior or None, changes: a preset's numbers or
    :data:`OPTION_CHANGES`). Values are JSON (numbers, true/false, null) or else strings:
    ``balanced+lambda_pix=0``, ``balanced@pbr-upconv7+pseudo_gt_prior=bicubic``,
    ``direct+max_size=512``."""
    head, *changes = method.split("+")
    name, _, prior = head.partition("@")
    config = {}
    for change in changes:
        key, eq, value = change.partition("=")
        if not eq or not key:
            raise ValueError(f"method {method!r}: '+{change}' is not key=value")
        try:
            config[key] = json.loads(value)
        except ValueError:
            config[key] = value
    return name, prior or None, config


def method_options(method: str, scale: int, prior: str) -> dict:
    """Upscale options of one benchmark method: ``bicubic``, ``direct`` or a PBR-SR preset,
    optionally with its own prior as ``METHOD@PRIOR`` (``direct@waifu2x-photo``), so one run
    compares priors."""
    name, own_prior, changes = parse_method(method)
    prior = own_prior or prior
    options = {k: v for k, v in changes.items() if k in OPTION_CHANGES}
    if isinstance(options.get("maps"), str):
        options["maps"] = options["maps"].split("|")
    if name in ("bicubic", "direct"):
        return {"method": name, "scale": scale, "prior": prior, **options}
    return {"method": "pbrsr", "preset": name, "scale": scale, "prior": prior, **options}


def preset_changes(method: str) -> dict:
    """The changes of ``method`` to its preset's numbers (``PbrsrConfig.with_``); a field
    that holds a tuple takes its items joined by ``|``: ``fast+prior_maps=base_color|normal``."""
    from pbrsr_core.optim.presets import PbrsrConfig

    defaults = PbrsrConfig()
    changes = {k: v for k, v in parse_method(method)[2].items() if k not in OPTION_CHANGES}
    for k, v in changes.items():
        if isinstance(v, str) and isinstance(getattr(defaults, k, None), tuple):
            changes[k] = tuple(v.split("|"))
    return changes


def check_methods(methods: tuple[str, ...], prior: str) -> None:
    """Raise ValueError naming the first method (its prior or a preset change) that is
    unknown, and any ``closest:`` method (pbrsr_bench/closest.py) that does not pick among
    methods listed before it."""
    from pydantic import ValidationError

    from pbrsr_core.errors import PbrsrError
    from pbrsr_core.optim.presets import PRESETS
    from pbrsr_core.options import UpscaleOptions
    from pbrsr_core.prior.registry import check_name

    closest.check(methods)
    for m in (m for m in methods if closest.parts(m) is None):
        name, own_prior, _ = parse_method(m)
        changes = preset_changes(m)
        if name not in ("bicubic", "direct") and name not in PRESETS:
            raise ValueError(
                f"unknown method {name!r}: use bicubic, direct or {', '.join(PRESETS)}"
            )
        if changes and name not in PRESETS:
            raise ValueError(
                f"method {m!r}: only a PBR-SR preset takes +key=value changes other than "
                + ", ".join(OPTION_CHANGES)
            )
        try:
            check_name(own_prior or prior)
            UpscaleOptions(**method_options(m, 4, prior))
            if changes:
                PRESETS[name].with_(**changes)
        except PbrsrError as exc:
            raise ValueError(f"method {m!r}: {exc.message}") from None
        except ValidationError as exc:
            e = exc.errors()[0]
            raise ValueError(f"method {m!r}: {'.'.join(map(str, e['loc']))}: {e['msg']}") from None
        except TypeError as exc:
            raise ValueError(f"method {m!r}: {exc}") from None


class Refused(RuntimeError):
    """The pipeline refused a run's options on its asset (the message says why)."""


def run_subprocess(spec: dict, work: Path) -> dict:
    """Run one upscale in a child process; return its result JSON plus peak RSS. Raises
    :class:`Refused` where the pipeline refused the options on the asset."""
    spec_path = work / "spec.json"
    spec_path.write_text(json.dumps(spec))
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "pbrsr_bench.isolated_run", str(spec_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"run {spec['label']} failed:\n{err[-3000:]}")
    result = json.loads((work / "result.json").read_text())
    if "refused" in result:
        raise Refused(result["refused"])
    result["wall_s"] = wall
    return result


def _with_pixels(asset: Asset, pixels: dict[int, np.ndarray]) -> Asset:
    images = [
        dataclasses.replace(im, pixels=pixels[im.index]) if im.index in pixels else im
        for im in asset.images
    ]
    return dataclasses.replace(asset, images=images)


def _score(
    pred: Asset, gt: Asset, evaluator: RenderEvaluator, store_like_gt: bool = False
) -> dict[str, float]:
    """Map PSNR/SSIM and render PSNR of ``pred``. The renders take its maps as they are; a
    map made smaller than the ground truth's (``max_size``) is compared as a bicubic upscale
    of it to the ground truth's size, as a renderer magnifying it would see it.
    ``store_like_gt``: each map whose ground truth is a JPEG file scored as stored with that
    file's tables and chroma sampling (metrics.stored_like)."""
    if store_like_gt:
        pred = stored_like(pred, gt)
    return {**map_metrics(at_gt_size(pred, gt), gt), **evaluator(pred)}


def at_gt_size(pred: Asset, gt: Asset) -> Asset:
    """``pred`` with each map smaller than the ground truth's by a whole factor upscaled to
    its size by bicubic interpolation (as the pipeline's bicubic method upscales it)."""
    from pbrsr_core.maps import kind_of
    from pbrsr_core.prior.direct import bicubic_map

    resized = {}
    for img, ref in zip(pred.images, gt.images, strict=False):
        h, w = img.pixels.shape[:2]
        H, W = ref.pixels.shape[:2]
        if h < H and H % h == 0 and W * h == H * w:  # smaller by a whole factor
            resized[img.index] = bicubic_map(img.pixels, kind_of(ref.roles), H // h)
    return _with_pixels(pred, resized) if resized else pred


def run(
    *,
    out_dir: Path = Path("bench-out/upscale"),
    assets: list[str] | None = None,
    methods: tuple[str, ...] = DEFAULT_METHODS,
    scale: int = 4,
    prior: str = DEFAULT_PRIOR,
    eval_res: int = 256,
    eval_views: int = 240,
    procedural_size: int = 512,
    include_procedural: bool = True,
    include_shared: bool = True,
    lr_format: str = "same",
    kernel: str = "gaussian",
    shared: Path = SHARED_ASSETS,
    assets_dir: Path | None = None,
    store_like_gt: bool = False,
    log=print,
) -> list[dict]:
    """Run the benchmark; write ``results.json``, ``results.md`` and ``speed_vs_error.png``.

    ``assets_dir``: a folder laid out as the shared one (a folder per asset, a glTF or GLB in
    each) whose assets run instead of the shared ones (no variants); the shared HDRs still
    light the evaluation. ``store_like_gt``: every method's maps are scored as stored the way
    the ground truth's JPEG files are (:func:`_score`)."""

    check_methods(methods, prior)
    check_kernels((kernel,))
    jpeg_request(lr_format)
    if assets_dir is not None and not assets_dir.is_dir():
        raise ValueError(f"--assets-dir {assets_dir} is not a folder")
    if assets_dir is not None and not find_assets(assets_dir, None):
        raise ValueError(f"{assets_dir} holds no folder with a .gltf or .glb in it")
    out_dir.mkdir(parents=True, exist_ok=True)
    lights, light_names = eval_lights(shared)
    work_root = Path(tempfile.mkdtemp(prefix="pbrsr-bench-"))
    rows: list[dict] = []
    meta = {
        "scale": scale,
        "prior": prior,
        "eval_res": eval_res,
        "eval_views": eval_views,
        "lights": light_names,
        "lr_format": lr_format,
        "kernel": kernel,
        "machine": machine(),
        **({"assets_dir": str(assets_dir)} if assets_dir is not None else {}),
        **({"store_like_gt": True} if store_like_gt else {}),
    }
    try:
        todo = bench_assets(
            work_root,
            include_procedural,
            procedural_size,
            shared if assets_dir is None else assets_dir,
            assets,
            log,
            include_shared,
            variants=assets_dir is None,
        )
        for name, gt_path in todo:
            log(f"== {name}: degrade x{scale} ({kernel})")
            lr_path = degrade_asset(
                gt_path,
                work_root / name / "lr" / gt_path.name,
                scale,
                image_format=lr_format,
                kernel=kernel,
            )[0]
            gt = load_asset(gt_path)
            evaluator = cpu_evaluator(gt, eval_res, eval_views, lights)
            made: dict[str, tuple[dict, Asset]] = {}  # what closest: methods pick from
            for method in methods:
                if closest.parts(method) is not None:
                    score = functools.partial(
                        _score, gt=gt, evaluator=evaluator, store_like_gt=store_like_gt
                    )
                    row = closest.row_of(method, made, gt, score)
                    if row is None:
                        log(f"   {method}: a method it picks from has no run here")
                    else:
                        rows.append(row)
                        log("   " + _row_text(row))
                        _write_results(out_dir, rows, meta)
                    continue
                work = work_root / name / method
                work.mkdir(parents=True)
                spec = {
                    "label": f"{name}/{method}",
                    "input": str(lr_path),
                    "out": str(work / "out"),
                    "work": str(work),
                    "options": method_options(method, scale, prior),
                    "config": preset_changes(method),
                }
                log(f"   {method} ...")
                try:
                    res = run_subprocess(spec, work)
                except Refused as exc:  # no row: nothing of this method ran on the asset
                    log(f"   {method}: refused: {exc}")
                    continue
                pred = load_asset(work / "out" / lr_path.name)
                scores = _score(pred, gt, evaluator, store_like_gt)
                curve = []
                for snap in res.get("snapshots", []):
                    px = dict(np.load(work / snap["file"]))
                    # a snapshot holds the maps being optimised; the rest are the output's
                    snap_asset = _with_pixels(pred, {int(k): v for k, v in px.items()})
                    s = _score(snap_asset, gt, evaluator, store_like_gt)
                    curve.append({"it": snap["it"], "seconds": snap["seconds"], **s})
                row = {
                    "asset": name,
                    "method": method,
                    "wall_s": round(res["wall_s"], 2),
                    "run_s": round(res["run_s"], 2),
                    "peak_rss_mib": round(res["peak_rss_mib"], 1),
                    "timings": res["timings"],
                    "lr_model": res.get("lr_model"),
                    **{k: round(v, 3) for k, v in scores.items()},
                    "curve": curve,
                }
                rows.append(row)
                if any(method in (closest.parts(m) or ()) for m in methods):
                    made[method] = (row, at_gt_size(pred, gt))
                log("   " + _row_text(row))
                _write_results(out_dir, rows, meta)
    finally:
        shutil.rmtree(work_root, ignore_errors=True)
    return rows


def _write_results(out_dir: Path, rows: list[dict], meta: dict) -> None:
    """Written after every run, so an interrupted benchmark keeps what it measured."""
    (out_dir / "results.json").write_text(json.dumps({**meta, "rows": rows}, indent=2))
    (out_dir / "results.md").write_text(results_text(rows, meta["scale"]))
    plot(rows, out_dir / "speed_vs_error.png")


def _map_cell(row: dict, m: str) -> str:
    v = row.get(f"maps.{m}.psnr")
    return "-" if v is None else f"{v:.2f}"


def _method_cell(row: dict) -> str:
    """The method, and for a run that estimated its LR kernel (``lr_kernel=auto``) the kernel
    it picked from the maps."""
    lr = row.get("lr_model") or {}
    return f"{row['method']} ({lr['kernel']})" if lr.get("estimated") else row["method"]


def _md(text: str) -> str:
    """``text`` as a markdown table cell: a list change's ``|`` (``+maps=a|b``) escaped."""
    return text.replace("|", "\\|")


def _row_text(row: dict) -> str:
    maps = " ".join(f"{m}={_map_cell(row, m)}" for m in MAP_COLUMNS if f"maps.{m}.psnr" in row)
    return (
        f"{_method_cell(row):<9} {row['run_s']:8.1f}s {row['peak_rss_mib']:7.0f}MiB "
        f"render={row.get('render.psnr', float('nan')):.2f} {maps}"
    )


def markdown_table(rows: list[dict]) -> str:
    head = (
        "| asset | method | wall s | peak MiB | render PSNR | " + " | ".join(MAP_COLUMNS) + " |\n"
    )
    head += "|" + "---|" * (5 + len(MAP_COLUMNS)) + "\n"
    lines = []
    for r in rows:
        cells = [
            r["asset"],
            _md(_method_cell(r)),
            f"{r['run_s']:.1f}",
            f"{r['peak_rss_mib']:.0f}",
            f"{r.get('render.psnr', float('nan')):.2f}",
        ]
        cells += [_map_cell(r, m) for m in MAP_COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


PROCEDURAL_ASSETS = ("procedural", "procedural-cutout")
"""The assets the benchmarks make themselves (:func:`bench_assets`); summaries over real
assets leave them out."""


def summary(
    rows: list[dict], exclude: tuple[str, ...] = (*PROCEDURAL_ASSETS, *BENCH_VARIANTS)
) -> list[dict]:
    """Per method, over the assets that also have a bicubic row (``exclude`` left out: the
    procedural assets, and the variants, which repeat their source's maps): mean
    render PSNR gain over bicubic, the worst map PSNR difference to bicubic (any asset, any
    map the two rows both score, occlusion and emissive included), mean run seconds and the
    largest peak memory; the targets are stated on these. ``render_gain_db_by_light``: the
    mean gain under each light, where every row and its bicubic row have it.
    ``estimated_kernels``: for runs that read their LR kernel off the maps, how many assets
    got each kernel."""
    bic = {r["asset"]: r for r in rows if r["method"] == "bicubic" and r["asset"] not in exclude}
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method and r["asset"] in bic]
        if method == "bicubic" or not mine:
            continue
        gains = [r["render.psnr"] - bic[r["asset"]]["render.psnr"] for r in mine]
        worst, worst_at = worst_map(mine, bic)
        picked = [
            r["lr_model"]["kernel"] for r in mine if (r.get("lr_model") or {}).get("estimated")
        ]
        by_light = {
            key[len("render.") : -len(".psnr")]: round(
                float(np.mean([r[key] - bic[r["asset"]][key] for r in mine])), 3
            )
            for key in _common_light_keys(mine, bic)
        }
        out.append(
            {
                "method": method,
                "assets": len(mine),
                "estimated_kernels": dict(Counter(picked).most_common()),
                "render_gain_db": round(float(np.mean(gains)), 3),
                "render_gain_db_by_light": by_light,
                "worst_map_db": round(worst, 3),
                "worst_map_at": worst_at,
                "mean_run_s": round(float(np.mean([r["run_s"] for r in mine])), 1),
                "max_peak_mib": round(max(r["peak_rss_mib"] for r in mine)),
            }
        )
    return out


def _common_light_keys(rows: list[dict], bic: dict[str, dict]) -> list[str]:
    """The ``render.<light>.psnr`` keys every row and its asset's bicubic row have, in the
    order of the first row."""
    keys = [k for k in rows[0] if k.startswith("render.") and k.endswith(".psnr")]
    keys = [k for k in keys if k != "render.psnr"]
    return [k for k in keys if all(k in r and k in bic[r["asset"]] for r in rows)]


def summary_table(rows: list[dict]) -> str:
    """:func:`summary` as markdown, with fast's share of balanced's gain and time."""
    s = summary(rows)
    if not s:
        return ""
    lines = [
        "| method | assets | render PSNR gain over bicubic (mean) | worst map vs bicubic "
        "| mean run s | max peak MiB |",
        "|---|---|---|---|---|---|",
    ]
    for r in s:
        lines.append(
            f"| {_md(r['method'])} | {r['assets']} | {r['render_gain_db']:+.2f} dB "
            f"| {r['worst_map_db']:+.2f} dB ({r['worst_map_at']}) | {r['mean_run_s']:.1f} "
            f"| {r['max_peak_mib']} |"
        )
    lights = list(s[0]["render_gain_db_by_light"])
    if lights and all(list(r["render_gain_db_by_light"]) == lights for r in s):
        each = ", ".join(
            f"{r['method']} "
            + " / ".join(f"{r['render_gain_db_by_light'][k]:+.2f}" for k in lights)
            for r in s
        )
        lines += ["", f"Mean render PSNR gain per light ({' / '.join(lights)}): {each} dB."]
    for r in s:
        if r["estimated_kernels"]:
            n = sum(r["estimated_kernels"].values())
            picks = ", ".join(f"{k} on {c}" for k, c in r["estimated_kernels"].items())
            lines += [
                "",
                f"{r['method']} estimated the LR kernel of {n} of its {r['assets']} assets: "
                f"{picks}.",
            ]
    by = {r["method"]: r for r in s}
    if "fast" in by and "balanced" in by and by["balanced"]["render_gain_db"] > 0:
        share = by["fast"]["render_gain_db"] / by["balanced"]["render_gain_db"]
        time_share = by["fast"]["mean_run_s"] / by["balanced"]["mean_run_s"]
        lines.append("")
        lines.append(
            f"fast keeps {100 * share:.0f} % of balanced's mean render-PSNR gain in "
            f"{100 * time_share:.0f} % of its mean run time."
        )
    return "\n".join(lines) + "\n"


def results_text(rows: list[dict], scale: int) -> str:
    """``results.md`` as a run at ``scale`` writes it and the command prints it: the table of
    every row, the summary and, at x4, the targets."""
    return markdown_table(rows) + "\n" + summary_table(rows) + targets_text(rows, scale)


def targets_text(rows: list[dict], scale: int) -> str:
    """The targets of pbrsr_bench/targets.py the rows hold, as a paragraph and a table: at
    x4, where they are set; empty at another scale or without their methods."""
    table = targets_table(rows, (*PROCEDURAL_ASSETS, *BENCH_VARIANTS)) if scale == 4 else ""
    if not table:
        return ""
    return "\nThe targets of the texture priors and the optimiser at x4:\n\n" + table


def published_summary(out_dir: Path) -> str:
    """The summary of ``out_dir/results.json`` as a documentation section: what was measured,
    where and by which command, then :func:`summary_table` and :func:`targets_text`."""
    data = json.loads((Path(out_dir) / "results.json").read_text())
    rows = data["rows"]
    methods = ",".join(dict.fromkeys(r["method"] for r in rows))
    quoted = f'"{methods}"' if "|" in methods else methods  # a list change's | for the shell
    command = f"pbrsr bench upscale --methods {quoted} --eval-views {data['eval_views']}"
    if data["scale"] != 4:
        command += f" --scale {data['scale']}"
    if data["prior"] != DEFAULT_PRIOR:
        command += f" --prior {data['prior']}"
    kernel = data.get("kernel", "gaussian")
    lr = "" if kernel == "gaussian" else f", LR by the {kernel} kernel (`pbrsr degrade --kernel`)"
    if kernel != "gaussian":
        command += f" --kernel {kernel}"
    lr_format = data.get("lr_format", "same")
    if lr_format != "same":
        lr += f", LR maps stored as `{lr_format}` (`pbrsr degrade --format`)"
        command += f" --lr-format {lr_format}"
    if data.get("store_like_gt"):
        lr += (
            ", each map whose ground truth is a JPEG file scored as stored with that file's "
            "tables and chroma sampling"
        )
        command += " --store-like-gt"
    real = sorted({r["asset"] for r in rows} - {*PROCEDURAL_ASSETS, *BENCH_VARIANTS})
    where = "shared assets"
    if data.get("assets_dir"):
        where = f"assets of `{data['assets_dir']}`"
        command += f" --assets-dir {data['assets_dir']}"
    return (
        f"x{data['scale']}{lr}, prior `{data['prior']}`, render PSNR over "
        f"{data['eval_views']} views at {data['eval_res']}² under "
        f"{' and '.join(data['lights'])}, mean over "
        f"{len(real)} {where} ({', '.join(real)}); run time is the method's own "
        f"(load to save), on {data.get('machine') or machine()}. Measured by `{command}`.\n\n"
        + summary_table(rows)
        + targets_text(rows, data["scale"])
    )


def plot(rows: list[dict], path: Path, columns: int = 4) -> None:
    """A grid: first the summary (per method, mean render-PSNR gain over bicubic against
    mean run time, over the real assets), then one panel per asset (render PSNR against
    wall seconds: curves over iterations where a method has them, a point where not, bicubic
    as a dashed line). A method keeps its colour in every panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    assets = list(dict.fromkeys(r["asset"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colour = {m: f"C{i % 10}" for i, m in enumerate(methods)}
    panels = 1 + len(assets)
    ncols = min(columns, panels)
    nrows = -(-panels // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(4.6 * ncols, 3.8 * nrows), squeeze=False)
    flat = list(axes.flat)
    _plot_summary(flat[0], summary(rows), colour)
    for ax, a in zip(flat[1:], assets, strict=False):
        for r in (r for r in rows if r["asset"] == a):
            m = r["method"]
            if r["curve"]:
                xs = [c["seconds"] for c in r["curve"]] + [r["run_s"]]
                ys = [c["render.psnr"] for c in r["curve"]] + [r["render.psnr"]]
                ax.plot(xs, ys, marker="o", markersize=3, label=m, color=colour[m])
            elif m == "bicubic":
                ax.axhline(r["render.psnr"], linestyle="--", label=m, color="gray")
            else:
                ax.plot([r["run_s"]], [r["render.psnr"]], "s", label=m, color=colour[m])
        ax.set_title(a, fontsize=10)
        ax.set_xlabel("wall seconds")
        ax.set_ylabel("render PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in flat[panels:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_summary(ax, rows: list[dict], colour: dict[str, str]) -> None:
    if not rows:
        ax.text(0.5, 0.5, "no real asset with a bicubic row", ha="center", va="center")
        ax.axis("off")
        return
    most = max(r["assets"] for r in rows)
    for r in rows:  # a method that ran on fewer assets (refused on some) says on how many
        label = r["method"] + (f" ({r['assets']} assets)" if r["assets"] < most else "")
        ax.plot(r["mean_run_s"], r["render_gain_db"], "o", color=colour[r["method"]])
        ax.annotate(label, (r["mean_run_s"], r["render_gain_db"]), fontsize=8,
                    xytext=(4, 4), textcoords="offset points")  # fmt: skip
    ax.axhline(0.0, color="gray", linestyle="--", linewidth=0.8)
    ax.set_xscale("log")
    ax.set_title(f"mean over {most} real assets", fontsize=10)
    ax.set_xlabel("mean run seconds (log)")
    ax.set_ylabel("render PSNR gain over bicubic (dB)")
    ax.grid(alpha=0.3)
