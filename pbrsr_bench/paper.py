"""``pbrsr bench paper``: what the ``paper`` preset costs on this machine.

The paper preset renders 750 views (15 x 50 at FoV 10), makes a 1024² pseudo-GT for each and
runs 2000 Adam steps of 4 views at 1024²: hours on a CPU. This benchmark runs that preset for
real on a sample, in its own process (``isolated_run``): a ``elev`` x ``azim`` grid over the same
view sphere, ``iterations`` steps, and the G-buffer cache cut by the same fraction as the views
(so a step re-rasterises as often as in the full run). Each stage is then extrapolated by its
unit of work: G-buffers and pseudo-GT per view, the optimisation per step; every other stage
(loading, the prior's init, the export) does not depend on the view or step counts. The
sample's loss history is in its report; its maps are not scored (a few steps log nothing of
2000).

Writes ``paper.json`` and ``paper.png`` and prints a table.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

from pbrsr_core.degrade import degrade_asset
from pbrsr_core.optim.presets import PAPER
from pbrsr_core.options import DEFAULT_PRIOR

from .results import pyplot, write_result
from .shared import SHARED_ASSETS
from .upscale import bench_assets, run_subprocess

PER_VIEW = ("gbuffers", "pseudo_gt")
PER_STEP = ("optimize",)


def extrapolate(timings: dict[str, float], view_factor: float, step_factor: float) -> dict:
    """Seconds per stage of the full run from the sample's: per-view stages times
    ``view_factor``, per-step stages times ``step_factor``, the rest as measured."""
    out = {}
    for stage, sec in timings.items():
        f = view_factor if stage in PER_VIEW else step_factor if stage in PER_STEP else 1.0
        out[stage] = sec * f
    return out


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else 0


def run(
    *,
    out_dir: Path = Path("bench-out/paper"),
    asset: str = "procedural",
    elev: int = 3,
    azim: int = 10,
    iterations: int = 20,
    scale: int = 4,
    prior: str = DEFAULT_PRIOR,
    procedural_size: int = 512,
    shared: Path = SHARED_ASSETS,
    log=print,
) -> dict:
    """Run the sample; return (and write to ``paper.json``) its measurements and the
    extrapolated full run."""
    if elev < 1 or azim < 1 or iterations < 1:
        raise ValueError("elev, azim and iterations must be >= 1")
    full_views = PAPER.n_elev * PAPER.n_azim
    views = elev * azim
    if views > full_views or iterations > PAPER.iterations:
        raise ValueError(f"a sample is at most {full_views} views and {PAPER.iterations} steps")
    out_dir.mkdir(parents=True, exist_ok=True)
    work_root = Path(tempfile.mkdtemp(prefix="pbrsr-bench-paper-"))
    try:
        names = None if asset == "procedural" else [asset]
        todo = dict(
            bench_assets(work_root, asset == "procedural", procedural_size, shared, names, log)
        )
        if asset not in todo:
            raise ValueError(f"asset {asset!r} not found (procedural, or a folder of {shared})")
        gt_path = todo[asset]
        log(f"== {asset}: degrade x{scale}")
        lr_path = degrade_asset(gt_path, work_root / "lr" / gt_path.name, scale)[0]
        cache_mb = max(1, round(PAPER.gbuffer_cache_mb * views / full_views))
        changes = {
            "n_elev": elev,
            "n_azim": azim,
            "iterations": iterations,
            "gbuffer_cache_mb": cache_mb,
        }
        work = work_root / "run"
        work.mkdir()
        spec = {
            "label": f"{asset}/paper-sample",
            "input": str(lr_path),
            "out": str(work / "out"),
            "work": str(work),
            "options": {"method": "pbrsr", "preset": "paper", "scale": scale, "prior": prior},
            "config": changes,
            "snapshots": False,
        }
        log(f"   paper preset, {elev} x {azim} views, {iterations} steps ...")
        res = run_subprocess(spec, work)
        report = json.loads((work / "out" / "report.json").read_text())
        pseudo_gt_bytes = _dir_bytes(work / "job" / "pseudo_gt")
    finally:
        shutil.rmtree(work_root, ignore_errors=True)

    view_factor = full_views / views
    step_factor = PAPER.iterations / iterations
    sample = {k: float(v) for k, v in res["timings"].items()}
    full = extrapolate(sample, view_factor, step_factor)
    result = {
        "asset": asset,
        "scale": scale,
        "prior": prior,
        "sample": {
            "views": views,
            "views_seeing_mesh": res["num_views"],
            "iterations": iterations,
            "gbuffer_cache_mb": cache_mb,
            "run_s": res["run_s"],
            "peak_rss_mib": res["peak_rss_mib"],
            "pseudo_gt_bytes": pseudo_gt_bytes,
            "timings": sample,
            "history": report.get("history", []),
        },
        "full": {
            "views": full_views,
            "iterations": PAPER.iterations,
            "gbuffer_cache_mb": PAPER.gbuffer_cache_mb,
            "timings": full,
            # what no stage holds (writing the bundle, the process) is counted as measured
            "run_s": res["run_s"] + sum(full.values()) - sum(sample.values()),
            "pseudo_gt_bytes": round(pseudo_gt_bytes * view_factor),
        },
        "per_view_s": {k: sample.get(k, 0.0) / views for k in PER_VIEW},
        "per_step_s": {k: sample.get(k, 0.0) / iterations for k in PER_STEP},
    }
    return write_result(result, out_dir, "paper", plot)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()

    full = result["full"]["timings"]
    stages = sorted(full, key=full.get)
    fig, ax = plt.subplots(figsize=(6.5, 0.35 * len(stages) + 1.2))
    ax.barh(stages, [full[s] / 3600 for s in stages])
    ax.set_xlabel("hours (extrapolated from the sample)")
    s = result["sample"]
    ax.set_title(
        f"paper preset on {result['asset']} x{result['scale']}: "
        f"{result['full']['run_s'] / 3600:.1f} h "
        f"(sample: {s['views']} views, {s['iterations']} steps, {s['run_s']:.0f} s)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    s, f = result["sample"], result["full"]
    table = Table(title=f"paper preset, {result['asset']} x{result['scale']} ({result['prior']})")
    table.add_column("stage")
    table.add_column(f"sample s ({s['views']} views, {s['iterations']} steps)", justify="right")
    table.add_column("unit")
    table.add_column(f"full s ({f['views']} views, {f['iterations']} steps)", justify="right")
    for stage, sec in s["timings"].items():
        unit = "view" if stage in PER_VIEW else "step" if stage in PER_STEP else "-"
        table.add_row(stage, f"{sec:.2f}", unit, f"{f['timings'][stage]:.0f}")
    table.add_row("run", f"{s['run_s']:.1f}", "", f"{f['run_s']:.0f} ({f['run_s'] / 3600:.2f} h)")
    Console().print(table)
    Console().print(
        f"sample peak RSS {s['peak_rss_mib']:.0f} MiB (G-buffer cache {s['gbuffer_cache_mb']} MiB;"
        f" the full run's is {f['gbuffer_cache_mb']} MiB); pseudo-GT on disk: sample "
        f"{s['pseudo_gt_bytes'] / 2**20:.0f} MiB, full run {f['pseudo_gt_bytes'] / 2**30:.2f} GiB"
    )
