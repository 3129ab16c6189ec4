"""``pbrsr bench prior``: speed, memory and quality of every installed prior.

For each prior and scale: parameters; seconds per 256x256 input and per 1024x1024 input
(tiled with the prior's default tile size); peak memory above the baseline (CUDA: allocator
peak; CPU: resident-set peak sampled every 5 ms); PSNR against the HR image and the gain over
bicubic on natural photos shipped inside scikit-image (``skimage.data``) and on albedo crops
of ``the shared assets folder`` (baseColor/diffuse images), both degraded by the paper's protocol
(:func:`pbrsr_core.degrade.degrade_image`: Gaussian blur, bicubic down). PSNR is measured on
sRGB values in [0, 1] with ``s`` pixels shaved off each border (the usual SR protocol).
Writes ``prior.json`` and ``prior.png`` to the output directory and prints a table.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from pbrsr_core.degrade import degrade_image
from pbrsr_core.device import resolve_device
from pbrsr_core.prior import load_prior
from pbrsr_core.prior.base import Prior
from pbrsr_core.prior.tiling import count_tiles
from pbrsr_core.runtime import configured

from .machine import machine
from .results import pyplot
from .shared import SHARED_ASSETS

NATURAL = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry")
ALBEDO_HINTS = ("basecolor", "base_color", "albedo", "_diff_", "diffuse")


@dataclass
class PriorRow:
    prior: str
    scale: int
    parameters: int
    precision: str = "fp32"
    s_per_256: float | None = None
    s_per_1024: float | None = None
    tiles_1024: int | None = None
    peak_mb: float | None = None
    psnr_natural: float | None = None
    gain_natural: float | None = None
    psnr_texture: float | None = None
    gain_texture: float | None = None
    per_image: dict[str, float] = field(default_factory=dict)


class PeakMemory:
    """Peak memory above the starting level during a ``with`` block, in bytes."""

    def __init__(self, device: torch.device):
        self.device, self.peak = device, 0
        self._stop = threading.Event()

    @staticmethod
    def _rss() -> int:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def _sample(self, base: int) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss() - base)
            time.sleep(0.005)

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)
        else:
            self._thread = threading.Thread(target=self._sample, args=(self._rss(),), daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device) - self._base
        else:
            self._stop.set()
            self._thread.join()


def natural_images(crop: int) -> dict[str, np.ndarray]:
    """Centre crops (crop, crop, 3) float32 of photos that ship inside scikit-image."""
    from skimage import data

    out = {}
    for name in NATURAL:
        img = getattr(data, name)()[..., :3]
        out[name] = _centre_crop(img.astype(np.float32) / 255.0, crop)
    return out


def texture_crops(
    crop: int, root: Path = SHARED_ASSETS, per_image: int = 2
) -> dict[str, np.ndarray]:
    """Albedo crops (crop, crop, 3) float32 from the shared assets' baseColor/diffuse images:
    the centre and, if ``per_image`` > 1, the top-left quarter's centre. Empty if absent."""
    import OpenImageIO as oiio

    out: dict[str, np.ndarray] = {}
    if not root.is_dir():
        return out
    files = sorted(
        p
        for p in root.rglob("*")
        if p.suffix.lower() in (".png", ".jpg", ".jpeg")
        and any(h in p.name.lower() for h in ALBEDO_HINTS)
    )
    for path in files:
        buf = oiio.ImageBuf(str(path))
        px = buf.get_pixels(oiio.FLOAT)
        if px is None or px.ndim != 3 or min(px.shape[:2]) < crop:
            continue
        rgb = px[..., :3] if px.shape[2] >= 3 else np.repeat(px[..., :1], 3, axis=2)
        key = path.relative_to(root).as_posix()
        out[key] = _centre_crop(rgb, crop)
        h, w = rgb.shape[:2]
        if per_image > 1 and min(h, w) >= 2 * crop:
            out[f"{key}@q"] = _centre_crop(rgb[: h // 2, : w // 2], crop)
    return out


def _centre_crop(img: np.ndarray, crop: int) -> np.ndarray:
    h, w = img.shape[:2]
    c = min(crop, h, w)
    y, x = (h - c) // 2, (w - c) // 2
    return np.ascontiguousarray(img[y : y + c, x : x + c], dtype=np.float32)


def psnr(a: np.ndarray, b: np.ndarray, shave: int) -> float:
    """PSNR (dB, peak 1) of (H, W, C) images with ``shave`` pixels dropped at each border."""
    if shave:
        a, b = a[shave:-shave, shave:-shave], b[shave:-shave, shave:-shave]
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


def _to_t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]


def _sr(prior: Prior, hr: np.ndarray, scale: int) -> np.ndarray:
    lr = degrade_image(hr, scale)
    out = prior.upscale(_to_t(lr), scale)[0].permute(1, 2, 0).cpu().numpy()
    return out[: hr.shape[0], : hr.shape[1]]


def _quality(prior: Prior, images: dict[str, np.ndarray], scale: int) -> dict[str, float]:
    return {name: psnr(_sr(prior, hr, scale), hr, scale) for name, hr in images.items()}


def _timed(prior: Prior, side: int, scale: int, device: torch.device) -> tuple[float, int]:
    """Seconds for one (1, 3, side, side) input (natural content), and peak memory bytes."""
    from skimage import data

    base = torch.from_numpy(data.astronaut().astype(np.float32) / 255.0).permute(2, 0, 1)[None]
    x = torch.nn.functional.interpolate(base, size=(side, side), mode="bilinear").clamp(0, 1)
    prior.upscale(x[:, :, :32, :32].to(device), scale)  # warm-up: load weights, kernels
    with PeakMemory(device) as mem:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        prior.upscale(x.to(device), scale)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        dt = time.perf_counter() - t0
    return dt, mem.peak


def default_priors() -> list[str]:
    from pbrsr_core.prior import rrdn, waifu2x

    installed = [(rrdn.NAME, rrdn.is_installed()), (waifu2x.NAME, waifu2x.is_installed())]
    return ["bicubic"] + [name for name, ok in installed if ok]


def run(
    out_dir: Path = Path("bench-out/prior"),
    priors: list[str] | None = None,
    scales: tuple[int, ...] = (2, 4, 8),
    large_scales: tuple[int, ...] | None = None,
    device: str = "auto",
    crop: int = 256,
    threads: int | None = None,
    precisions: tuple[str, ...] = ("auto",),
    assets_root: Path = SHARED_ASSETS,
    log=print,
) -> dict:
    """Run the benchmark; returns the JSON-able result (also written to ``out_dir``).

    ``large_scales``: scales timed on a 1024x1024 input (default: all ``scales``; an empty
    tuple skips them). ``threads`` sets torch's intra-op threads for the run. Each prior runs
    at each of ``precisions`` (auto, fp32, bf16, int8) that gives it a precision of its own
    (a prior with no int8 network runs once for ``fp32`` and ``int8``)."""
    if threads:
        torch.set_num_threads(threads)
    host = machine()  # before any prior runs, on the threads they run on
    dev = resolve_device(device)
    names = priors or default_priors()
    large = tuple(scales) if large_scales is None else tuple(large_scales)
    natural = natural_images(crop)
    textures = texture_crops(crop, assets_root)
    if not textures:
        log(f"note: {assets_root} not found or has no albedo images: texture column skipped")
    bicubic = load_prior("bicubic", dev)
    rows: list[PriorRow] = []
    runs = []  # (name, prior, precision asked for): once per precision a prior takes
    for name in names:
        prior = load_prior(name, dev)
        seen = set()
        for choice in precisions:
            with configured(prior_precision=choice):
                taken = prior.precision_in_use()
            if taken not in seen:
                seen.add(taken)
                runs.append((name, prior, choice))
    for name, prior, choice in runs:
        with configured(prior_precision=choice):  # the cached prior is left as it was
            for s in [s for s in scales if s in prior.scales]:
                log(f"{name} ({prior.precision_in_use()}) x{s} ...")
                row = PriorRow(
                    prior=name,
                    scale=s,
                    parameters=prior.num_parameters(),
                    precision=prior.precision_in_use(),
                )
                row.s_per_256, peak = _timed(prior, 256, s, dev)
                if s in large:
                    row.s_per_1024, peak = _timed(prior, 1024, s, dev)
                    tile = prior.effective_tile(s)
                    overlap = (
                        prior.default_overlap if prior.tile_overlap is None else prior.tile_overlap
                    )
                    row.tiles_1024 = count_tiles(1024, 1024, tile, min(overlap, tile // 2))
                row.peak_mb = peak / 2**20
                for label, images in (("natural", natural), ("texture", textures)):
                    if not images:
                        continue
                    q = _quality(prior, images, s)
                    ref = _quality(bicubic, images, s) if name != "bicubic" else q
                    mean, gain = (
                        float(np.mean(list(q.values()))),
                        float(np.mean([q[k] - ref[k] for k in q])),
                    )
                    setattr(row, f"psnr_{label}", mean)
                    setattr(row, f"gain_{label}", gain)
                    row.per_image.update({f"{label}:{k}": v for k, v in q.items()})
                rows.append(row)
    result = {
        "device": str(dev),
        "torch_threads": torch.get_num_threads(),
        "machine": host,
        "crop": crop,
        "natural_images": list(natural),
        "texture_crops": list(textures),
        "assets_root_found": bool(textures),
        "degradation": "pbrsr_core.degrade.degrade_image (Gaussian blur sigma=0.375*s, bicubic)",
        "rows": [asdict(r) for r in rows],
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "prior.json").write_text(json.dumps(result, indent=2), encoding="utf-8")
    _plot(rows, out_dir / "prior.png")
    return result


def _plot(rows: list[PriorRow], path: Path) -> None:
    plt = pyplot()

    labels = [f"{r.prior}\n{r.precision} x{r.scale}" for r in rows]
    xs = np.arange(len(rows))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(max(8, 1.6 * len(rows)), 4.5))
    for off, key, lab in ((-0.2, "gain_natural", "natural"), (0.2, "gain_texture", "texture")):
        vals = [getattr(r, key) or 0.0 for r in rows]
        ax1.bar(xs + off, vals, width=0.4, label=lab)
    ax1.axhline(0, color="k", lw=0.8)
    ax1.set_xticks(xs, labels, fontsize=8)
    ax1.set_ylabel("PSNR gain over bicubic (dB)")
    ax1.legend()
    ax2.bar(xs - 0.2, [r.s_per_256 or 0 for r in rows], width=0.4, label="256x256")
    ax2.bar(xs + 0.2, [r.s_per_1024 or 0 for r in rows], width=0.4, label="1024x1024 (tiled)")
    ax2.set_yscale("log")
    ax2.set_xticks(xs, labels, fontsize=8)
    ax2.set_ylabel("seconds per input")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    where = result.get("machine") or f"{result['torch_threads']} threads"
    t = Table(title=f"pbrsr bench prior ({result['device']}; {where})")
    cols = (
        "prior",
        "precision",
        "scale",
        "params",
        "s/256²",
        "s/1024² (tiles)",
        "peak MB",
        "PSNR nat",
        "gain nat",
        "PSNR tex",
        "gain tex",
    )
    for c in cols:
        t.add_column(c, justify="right" if c not in ("prior", "precision") else "left")

    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    for r in result["rows"]:
        big = "-" if r["s_per_1024"] is None else f"{r['s_per_1024']:.1f} ({r['tiles_1024']})"
        t.add_row(
            r["prior"],
            r.get("precision", "fp32"),
            f"x{r['scale']}",
            f"{r['parameters']:,}",
            f(r["s_per_256"], ".2f"),
            big,
            f(r["peak_mb"], ".0f"),
            f(r["psnr_natural"], ".2f"),
            f(r["gain_natural"], "+.2f"),
            f(r["psnr_texture"], ".2f"),
            f(r["gain_texture"], "+.2f"),
        )
    Console(width=160).print(t)
