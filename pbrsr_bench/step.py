"""``pbrsr bench step``: the optimiser step's whole-map part against its memory-traffic floor.

Outside the renderer, every step touches every texel of every optimised map: the PBR
consistency and TV gradients are added and the gradient masked (``regularize_grads``), then
Adam updates the maps and its two moments and the maps are projected to valid ranges
(``MapAdam``). At 2048^2 and above this part, not the shading of a few hundred thousand
pixels, sets the step's time.

For each map size this times those passes on ``images`` maps of ``channels`` channels (the
renderer's gradient is stood in by a random one; the shading cost is ``pbrsr bench render``'s)
and compares them with the floor: the bytes a step cannot avoid moving (Adam reads the map,
its gradient and two moments and writes the map and moments; the gradient is written once:
8 float32 arrays) at the bandwidth of a large ``copy_`` measured on the same machine.

Writes ``step.json`` and ``step.png`` and prints a table.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from pbrsr_core.allocator import reuse_large_blocks
from pbrsr_core.optim.groups import map_groups
from pbrsr_core.optim.losses import ssim_target
from pbrsr_core.optim.presets import get_preset
from pbrsr_core.optim.schedule import channel_lr
from pbrsr_core.optim.step import regularize_grads
from pbrsr_core.optim.whole_map import MapAdam

from .results import pyplot, write_result

FLOOR_ARRAYS = 8  # float32 arrays per texel channel a step must move (see the docstring)
PASSES = ("regularize", "adam_project")


def copy_bandwidth(numel: int, repeats: int = 5) -> float:
    """Bytes per second of ``dst.copy_(src)`` on float32 arrays of ``numel`` (read + write)."""
    src = torch.rand(numel)
    dst = torch.empty_like(src)
    dst.copy_(src)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        dst.copy_(src)
        times.append(time.perf_counter() - t0)
    return 2 * 4 * numel / min(times)


def _time_passes(size: int, images: int, channels: int, scale: int, steps: int) -> dict:
    config = get_preset("balanced")
    roles = {"base_color"} if channels >= 3 else {"metallic_roughness"}
    gen = torch.Generator().manual_seed(0)
    params, lr, groups, masks = {}, {}, {}, {}
    for i in range(images):
        params[i] = torch.rand(size, size, channels, generator=gen).requires_grad_(True)
        lr[i] = torch.rand(size // scale, size // scale, channels, generator=gen)
        groups[i] = map_groups(roles, channels, config)
        masks[i] = (torch.ones(size, size, dtype=torch.bool), torch.ones(channels, dtype=bool))
    opt = MapAdam(
        params,
        {i: channel_lr(groups[i], channels, config) for i in params},
        dict.fromkeys(params, False),
        {i: masks[i][1] for i in params},
    )
    targets = {i: ssim_target(t) for i, t in lr.items()}  # once per run, as the optimiser
    times: dict[str, list[float]] = {k: [] for k in PASSES}
    for step in range(steps + 1):  # the first step warms up (kernels compiled, pages mapped)
        for p in params.values():
            p.grad = torch.randn(p.shape, generator=gen) * 1e-3  # the renderer's gradient
        t0 = time.perf_counter()
        regularize_grads(params, lr, targets, groups, masks, config)
        t1 = time.perf_counter()
        opt.step()
        t2 = time.perf_counter()
        if step:
            for k, dt in zip(PASSES, (t1 - t0, t2 - t1), strict=True):
                times[k].append(dt)
    return {k: statistics.median(v) for k, v in times.items()}


def run(
    *,
    out_dir: Path,
    sizes: tuple[int, ...] = (1024, 2048, 4096),
    images: int = 3,
    channels: int = 3,
    scale: int = 4,
    steps: int = 5,
    threads: int | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    if threads:
        torch.set_num_threads(threads)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    with reuse_large_blocks():
        for size in sizes:
            numel = size * size * channels * images
            log(f"step: {images} maps of {size}^2 x {channels}")
            bw = copy_bandwidth(numel)
            t = _time_passes(size, images, channels, scale, steps)
            total = sum(t.values())
            floor = FLOOR_ARRAYS * 4 * numel / bw
            rows.append(
                {
                    "size": size,
                    "values_m": round(numel / 1e6, 2),
                    **{f"{k}_ms": round(v * 1e3, 2) for k, v in t.items()},
                    "total_ms": round(total * 1e3, 2),
                    "floor_ms": round(floor * 1e3, 3),
                    "over_floor": round(total / floor, 2),
                    "copy_gb_s": float(f"{bw / 1e9:.3g}"),  # 3 digits at any rate
                }
            )
    result = {
        "images": images,
        "channels": channels,
        "scale": scale,
        "threads": torch.get_num_threads(),
        "rows": rows,
    }
    return write_result(result, out_dir, "step", plot)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()

    rows = result["rows"]
    labels = [f"{r['size']}²" for r in rows]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    bottom = [0.0] * len(rows)
    for k in PASSES:
        vals = [r[f"{k}_ms"] for r in rows]
        ax.bar(labels, vals, bottom=bottom, label=k)
        bottom = [b + v for b, v in zip(bottom, vals, strict=True)]
    ax.scatter(
        labels,
        [r["floor_ms"] for r in rows],
        color="k",
        marker="_",
        s=900,
        zorder=3,
        label="memory-traffic floor",
    )
    ax.set_ylabel("ms per step (whole-map part)")
    ax.set_yscale("log")
    ax.set_title(f"{result['images']} maps x {result['channels']} channels, x{result['scale']}")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    table = Table(title="optimiser step, whole-map part (median ms)")
    cols = [
        "size",
        "values_m",
        *[f"{k}_ms" for k in PASSES],
        "total_ms",
        "floor_ms",
        "over_floor",
        "copy_gb_s",
    ]
    for c in cols:
        table.add_column(c, justify="right")
    for r in result["rows"]:
        table.add_row(*[str(r[c]) for c in cols])
    Console().print(table)
