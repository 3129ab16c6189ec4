"""``pbrsr bench render``: renderer speed per stage.

For a procedural UV sphere of ~100k triangles (three 1024^2 maps: baseColor, ORM, normal)
and for each asset of ``the shared assets folder`` (when that folder exists), at each render
resolution, over a few orbit views:

* G-buffer time per view, split into the coverage kernel (z-buffer) and attribute
  interpolation, for the default CPU backend (and the torch reference once, at the first
  resolution, for comparison);
* shading forward and backward time per view w.r.t. every texture, with the per-view texel
  taps already cached (the optimiser's steady state), and the throughput in covered
  Mpixel/s of forward + backward, for the default path (the fused numba kernels on the
  CPU) and, when those are in use, for the torch reference path as well (``ref_*``);
* peak resident memory above the starting level while shading (sampled every 5 ms);
* once, a ``torch.profiler`` breakdown of the shading step: the top operators by self time.

Writes ``render.json`` and ``render.png`` to the output directory and prints a rich table.
"""

from __future__ import annotations

import os
import statistics
import threading
import time
from collections.abc import Callable
from pathlib import Path

import torch

from pbrsr_core.asset.model import Material, Mesh, TextureRef
from pbrsr_core.render import camera as cam
from pbrsr_core.render import light as light_mod
from pbrsr_core.render import raster, shade, shapes

from .results import pyplot, write_result
from .shared import SHARED_ASSETS

TARGET_GBUFFER_S = 0.5  # 100k triangles at 1024^2
TARGET_MPIX_S = 2.0  # shading forward + backward


class PeakRss:
    """Peak resident set size above the level at entry, in bytes (sampled every 5 ms)."""

    def __init__(self):
        self.peak = 0
        self._stop = threading.Event()

    @staticmethod
    def rss() -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def _watch(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.rss() - self.base)
            time.sleep(0.005)

    def __enter__(self):
        self.base = self.rss()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self.rss() - self.base)


def procedural_case(n: int = 224, tex_size: int = 1024):
    """A UV sphere with 2 n (n - 1) triangles (~100k for n = 224), one textured material."""
    mesh = shapes.uv_sphere(n, n, radius=0.5)
    g = torch.Generator().manual_seed(0)
    textures = {
        0: torch.rand(tex_size, tex_size, 4, generator=g),
        1: torch.rand(tex_size, tex_size, 3, generator=g),
        2: torch.rand(tex_size, tex_size, 3, generator=g) * 0.4 + torch.tensor([0.3, 0.3, 0.6]),
    }
    mat = Material(
        index=0,
        base_color=TextureRef(0),
        metallic_roughness=TextureRef(1),
        occlusion=TextureRef(1),
        normal=TextureRef(2),
    )
    return f"sphere-{mesh.num_triangles // 1000}k-{tex_size}px", mesh, [mat], textures


def asset_cases(log: Callable[[str], None]):
    """(name, normalised mesh, materials, textures) of each shared asset that loads."""
    if not SHARED_ASSETS.is_dir():
        log(f"{SHARED_ASSETS} not found: procedural mesh only")
        return []
    try:
        from pbrsr_core.asset import load_asset
        from pbrsr_core.scene import asset_textures, make_scene
    except ImportError as exc:  # the asset module is not there yet
        log(f"asset loading unavailable ({exc}): procedural mesh only")
        return []
    cases = []
    for d in sorted(p for p in SHARED_ASSETS.iterdir() if p.is_dir() and p.name != "envmaps"):
        files = sorted(d.glob("*.gltf")) + sorted(d.glob("*.glb"))
        if not files:
            continue
        try:
            asset = load_asset(files[0])
            scene = make_scene(asset, torch.device("cpu"))
            cases.append((d.name, scene.mesh, scene.materials, asset_textures(asset, "cpu")))
        except Exception as exc:  # a benchmark reports, it does not stop on one asset
            log(f"skipped {d.name}: {exc}")
    return cases


def _views(res: int, n_views: int) -> list[cam.Camera]:
    return cam.orbit_cameras(1, n_views, 2.2, 30.0, res, (20.0, 20.0), 15.0)


def bench_case(name, mesh: Mesh, materials, textures, res: int, n_views: int, env, reference):
    """One (mesh, resolution) row."""
    cams = _views(res, n_views)
    t_cov, t_int, gbs = [], [], []
    for c in cams:
        t0 = time.perf_counter()
        tri, bary, backend = raster.coverage(mesh, c)
        t1 = time.perf_counter()
        pix = torch.nonzero(tri >= 0).squeeze(1)
        gbs.append(raster.build_gbuffer(mesh, c, pix, tri[pix], bary[pix]))
        t_int.append(time.perf_counter() - t1)
        t_cov.append(t1 - t0)
    row = {
        "case": name,
        "triangles": mesh.num_triangles,
        "resolution": res,
        "backend": backend,
        "views": n_views,
        "coverage_s": statistics.median(t_cov),
        "interpolate_s": statistics.median(t_int),
    }
    row["gbuffer_s"] = row["coverage_s"] + row["interpolate_s"]
    if reference:
        t0 = time.perf_counter()
        raster.rasterize(mesh, cams[0], backend="torch")
        row["gbuffer_torch_s"] = time.perf_counter() - t0
    params = {k: v.detach().clone().requires_grad_(True) for k, v in textures.items()}
    for gb in gbs:  # warm the per-view caches (texel taps), as the optimiser's loop does
        shade.shade(gb, materials, params, env)
    for ref in (True, False):  # and every kernel of both paths, backward included (numba
        # compiles, or loads from its disk cache, on first use)
        shade.shade(gbs[0], materials, params, env, reference=ref)[:, :3].sum().backward()
    fused = shade.use_fused(gbs[0], params, env)
    for path in ("reference", "default") if fused else ("default",):
        fwd, bwd, pixels = [], [], []
        with PeakRss() as mem:
            for gb in gbs:
                t0 = time.perf_counter()
                out = shade.shade(gb, materials, params, env, reference=path == "reference")
                t1 = time.perf_counter()
                out[:, :3].sum().backward()
                t2 = time.perf_counter()
                fwd.append(t1 - t0)
                bwd.append(t2 - t1)
                pixels.append(gb.num_pixels)
        mpix = sum(pixels) / (sum(fwd) + sum(bwd)) / 1e6
        if path == "reference":  # the torch path, for comparison with the fused kernels
            row.update(ref_fwd_s=statistics.median(fwd), ref_bwd_s=statistics.median(bwd))
            row.update(ref_mpix_per_s=mpix, ref_peak_mb=mem.peak / 2**20)
            continue
        row.update(
            shading="fused" if fused else "torch",
            pixels=int(statistics.median(pixels)),
            shade_fwd_s=statistics.median(fwd),
            shade_bwd_s=statistics.median(bwd),
            mpix_per_s=mpix,
            peak_mb=mem.peak / 2**20,
        )
    return row, gbs[0], params


def profile_shading(gb, materials, params, env, top: int = 10) -> list[dict]:
    """Top operators (self CPU time) of one shading forward + backward."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        shade.shade(gb, materials, params, env)[:, :3].sum().backward()
    rows = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in rows) or 1.0
    return [
        {
            "op": e.key,
            "calls": e.count,
            "self_ms": e.self_cpu_time_total / 1e3,
            "share": e.self_cpu_time_total / total,
        }
        for e in rows[:top]
    ]


def run(
    out_dir: Path = Path("bench-out/render"),
    resolutions: tuple[int, ...] = (512, 1024),
    n_views: int = 3,
    shared: bool = True,
    threads: int | None = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Run the benchmark; returns (and writes) the result dict."""
    if threads:
        import numba

        # numba's OpenMP layer resets the (shared) OpenMP thread count on every launch:
        # set both, or a 1-thread run silently shades on NUMBA_NUM_THREADS threads
        torch.set_num_threads(threads)
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    env = light_mod.EnvLight.procedural()
    env_s = time.perf_counter() - t0
    light_mod.brdf_lut()
    cases = [procedural_case()]
    if shared:
        cases += asset_cases(log)
    rows, profile_rows = [], []
    # warm the numba kernels (compiled once, cached on disk)
    raster.rasterize(shapes.quad(), cam.look_at((0, 0, 2), resolution=(16, 16)))
    for ci, (name, mesh, mats, texs) in enumerate(cases):
        for ri, res in enumerate(resolutions):
            log(f"{name}: {mesh.num_triangles} triangles at {res}x{res}")
            row, gb, params = bench_case(
                name, mesh, mats, texs, res, n_views, env, reference=(ri == 0 and ci == 0)
            )
            rows.append(row)
            if ci == 0 and res == max(resolutions):
                profile_rows = profile_shading(gb, mats, params, env)
    result = {
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": list(os.getloadavg()),
        "env_prefilter_s": env_s,
        "targets": {"gbuffer_s_100k_1024": TARGET_GBUFFER_S, "mpix_per_s": TARGET_MPIX_S},
        "rows": rows,
        "shading_profile": profile_rows,
    }
    return write_result(result, out_dir, "render", plot)


def plot(result: dict, path: Path) -> None:
    plt = pyplot()

    rows = result["rows"]
    labels = [f"{r['case'][:18]}\n{r['resolution']}" for r in rows]
    x = range(len(rows))
    fig, axes = plt.subplots(1, 2, figsize=(max(8, 1.3 * len(rows) + 4), 4.5))
    ax = axes[0]
    cov = [r["coverage_s"] * 1e3 for r in rows]
    itp = [r["interpolate_s"] * 1e3 for r in rows]
    ax.bar(x, cov, label="coverage (z-buffer)")
    ax.bar(x, itp, bottom=cov, label="interpolation")
    ax.axhline(TARGET_GBUFFER_S * 1e3, color="r", ls="--", lw=1, label="target (100k tris, 1024²)")
    ax.set_ylabel("ms per view")
    ax.set_title("G-buffer")
    ax.set_xticks(list(x), labels, rotation=60, fontsize=7)
    ax.legend(fontsize=7)
    ax = axes[1]
    ax.bar(x, [r["mpix_per_s"] for r in rows], color="tab:green")
    ax.axhline(TARGET_MPIX_S, color="r", ls="--", lw=1, label="target")
    ax.set_ylabel("covered Mpixel/s (forward + backward)")
    ax.set_title(f"Shading ({result['threads']} threads)")
    ax.set_xticks(list(x), labels, rotation=60, fontsize=7)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"pbrsr bench render ({result['threads']} threads)")
    for col in (
        "case",
        "tris",
        "res",
        "pixels",
        "cover ms",
        "interp ms",
        "G-buf ms",
        "fwd ms",
        "bwd ms",
        "Mpix/s",
        "ref fwd ms",
        "ref bwd ms",
        "ref Mpix/s",
        "peak MB",
    ):
        t.add_column(col, justify="left" if col == "case" else "right")
    for r in result["rows"]:
        t.add_row(
            r["case"],
            f"{r['triangles']:,}",
            str(r["resolution"]),
            f"{r['pixels']:,}",
            f"{r['coverage_s'] * 1e3:.1f}",
            f"{r['interpolate_s'] * 1e3:.1f}",
            f"{r['gbuffer_s'] * 1e3:.1f}",
            f"{r['shade_fwd_s'] * 1e3:.0f}",
            f"{r['shade_bwd_s'] * 1e3:.0f}",
            f"{r['mpix_per_s']:.2f}",
            f"{r['ref_fwd_s'] * 1e3:.0f}" if "ref_fwd_s" in r else "-",
            f"{r['ref_bwd_s'] * 1e3:.0f}" if "ref_bwd_s" in r else "-",
            f"{r['ref_mpix_per_s']:.2f}" if "ref_mpix_per_s" in r else "-",
            f"{r['peak_mb']:.0f}",
        )
    console = Console(width=max(Console().width, 150))
    console.print(t)
    if result["shading_profile"]:
        p = Table(title="shading forward + backward: top operators (largest case)")
        for col in ("op", "calls", "self ms", "share"):
            p.add_column(col, justify="left" if col == "op" else "right")
        for e in result["shading_profile"]:
            p.add_row(e["op"], str(e["calls"]), f"{e['self_ms']:.1f}", f"{e['share']:.0%}")
        console.print(p)
    ref = [r for r in result["rows"] if "gbuffer_torch_s" in r]
    for r in ref:
        console.print(
            f"G-buffer reference (torch backend) at {r['resolution']}: "
            f"{r['gbuffer_torch_s'] * 1e3:.0f} ms vs {r['backend']} {r['gbuffer_s'] * 1e3:.0f} ms"
        )
    console.print(
        f"environment prefilter: {result['env_prefilter_s']:.2f} s; "
        f"load average {result['load_average'][0]:.1f} on {result['cpu_count']} CPUs"
    )
