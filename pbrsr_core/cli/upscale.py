"""`pbrsr upscale`, `pbrsr eval` and `pbrsr demo`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from ..map_table import map_rows
from ..options import DEFAULT_PRIOR, UpscaleOptions
from .progressbar import progress_bar

console = Console()


def _size(wh: list[int]) -> str:
    return f"{wh[0]}²" if wh[0] == wh[1] else f"{wh[0]}x{wh[1]}"


def _print_report(report: dict, out_dir: Path) -> None:
    maps = Table(title="maps")
    for col in ("map", "role", "size", "made from", "consistency dB"):
        maps.add_column(
            col, justify="right" if col == "consistency dB" else "left", overflow="fold"
        )
    for row in map_rows(report):
        lr, hr, f = row["lr_size"], row["size"], row["scale"]
        maps.add_row(  # Text: names such as "pbr-srmd[data]" are not rich markup
            Text(row["name"]),
            Text(row["label"] or ""),
            f"{_size(lr)} x{f} = {_size(hr)}" if f > 1 else f"{_size(lr)} kept",
            Text(row["made_from"]),
            " ".join(f"{db:.1f}" for db in row["consistency_db"].values()),
        )
    console.print(maps)
    t = Table(title="stage timings (s)")
    t.add_column("stage")
    t.add_column("seconds", justify="right")
    for k, v in report["timings"].items():
        t.add_row(k, f"{v:.2f}")
    console.print(t)
    console.print(f"result:  {out_dir / report['input']}")
    console.print(f"maps:    {out_dir / 'maps'}")
    console.print(f"report:  {out_dir / 'report.json'}")
    console.print(f"preview: {out_dir / 'preview.png'}")


def register(app: typer.Typer) -> None:
    @app.command()
    def upscale(
        input: Annotated[Path, typer.Argument(help=".glb, .gltf or .zip holding one .gltf")],
        out: Annotated[Path, typer.Option("-o", "--out", help="output folder")],
        scale: Annotated[int, typer.Option(help="2, 4 or 8")] = 4,
        max_size: Annotated[
            int | None,
            typer.Option(
                help="largest output texture side (px): a map scale would make larger gets "
                "scale/2 or scale/4, or is kept"
            ),
        ] = None,
        maps: Annotated[
            str | None,
            typer.Option(
                help="comma-separated material roles to upscale (base_color, "
                "metallic_roughness, normal, occlusion, emissive, clearcoat, ...); the other "
                "maps keep their files (or, with --other-maps bicubic, get bicubic's). "
                "Default: every map"
            ),
        ] = None,
        other_maps: Annotated[
            str,
            typer.Option(
                help="with --maps, what the other maps get: keep (their files) or bicubic "
                "(a bicubic upscale, no prior or optimiser)"
            ),
        ] = "keep",
        method: Annotated[str, typer.Option(help="pbrsr, direct or bicubic")] = "pbrsr",
        preset: Annotated[str, typer.Option(help="fast, balanced, quality, paper")] = "balanced",
        iterations: Annotated[
            int | None,
            typer.Option(help="optimiser steps over the preset's views (default: the preset's)"),
        ] = None,
        prior: Annotated[
            str,
            typer.Option(
                help="pbr-upconv7, pbr-upconv7-fast, pbr-srmd, waifu2x-photo, rrdn-thick, bicubic, "
                "texture:<folder>, spandrel:<path>, diffusion:<dir> (pbrsr priors list)"
            ),
        ] = DEFAULT_PRIOR,
        envmap: Annotated[str | None, typer.Option(help=".hdr/.exr environment")] = None,
        seed: Annotated[int, typer.Option()] = 0,
        image_format: Annotated[
            str,
            typer.Option(
                "--texture-format",
                "--format",
                help="same, png, png16, exr, jpeg, ktx2, webp, avif",
            ),
        ] = "same",
        lr_kernel: Annotated[
            str,
            typer.Option(
                help="how the input's maps were made smaller, the LR model the prior's "
                "back-projection inverts: gaussian (pbrsr degrade's protocol), area "
                "(mipmaps), bicubic or lanczos (image editors), auto (estimated from the maps: "
                "pbrsr kernel estimate)"
            ),
        ] = "gaussian",
        device: Annotated[str, typer.Option(help="auto, cpu, cuda, cuda:N")] = "auto",
        memory_mb: Annotated[
            int,
            typer.Option(
                min=0,
                help="memory the run may use (MiB); a run estimated above it is refused before "
                "it starts. 0: what the machine has free",
            ),
        ] = 0,
        overwrite: Annotated[bool, typer.Option(help="replace an existing output folder")] = False,
        quiet: Annotated[bool, typer.Option("-q", "--quiet")] = False,
    ) -> None:
        """Upscale every PBR texture of an asset."""
        from pydantic import ValidationError

        from ..errors import InvalidOptions
        from ..footprint import memory_budget
        from ..pipeline import upscale_asset

        if not input.is_file():
            raise InvalidOptions(f"input file '{input}' does not exist")
        try:
            options = UpscaleOptions(
                scale=scale,
                max_size=max_size,
                maps=None if maps is None else [m.strip() for m in maps.split(",") if m.strip()],
                other_maps=other_maps,
                method=method,
                preset=preset,
                iterations=iterations,
                prior=prior,
                envmap=envmap,
                seed=seed,
                image_format=image_format,
                lr_kernel=lr_kernel,
                device=device,
            )
        except ValidationError as exc:
            msgs = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
            raise InvalidOptions(msgs) from None
        if overwrite and out.exists():
            shutil.rmtree(out)
        with progress_bar(not quiet) as cb:
            report = upscale_asset(
                input, out, options, progress=cb, memory_budget=memory_budget(memory_mb)
            )
        if not quiet:
            _print_report(report, out)

    @app.command(name="eval")
    def eval_cmd(
        pred: Annotated[Path, typer.Argument(help="upscaled asset")],
        gt: Annotated[Path, typer.Argument(help="ground-truth asset (same structure)")],
        resolution: Annotated[int, typer.Option(help="render size of evaluation views")] = 256,
        views: Annotated[int, typer.Option(help="evaluation views (paper: 240)")] = 240,
        envmap: Annotated[list[Path] | None, typer.Option(help="environment maps")] = None,
        json_out: Annotated[Path | None, typer.Option("--json", help="write JSON here")] = None,
        store_like_gt: Annotated[
            bool,
            typer.Option(
                "--store-like-gt",
                help="score each map of PRED whose ground truth is a JPEG file as stored with "
                "that file's tables and chroma sampling",
            ),
        ] = False,
    ) -> None:
        """Per-map PSNR/SSIM and render PSNR of PRED against GT."""
        from ..metrics import evaluate

        res = evaluate(
            pred,
            gt,
            resolution=resolution,
            envmaps=envmap,
            num_views=views,
            store_like_gt=store_like_gt,
        )
        t = Table(title=f"{pred.name} vs {gt.name}")
        t.add_column("metric")
        t.add_column("value", justify="right")
        for k, v in res.items():
            t.add_row(k, f"{v:.3f}" if k.endswith("psnr") else f"{v:.4f}")
        console.print(t)
        if json_out:
            json_out.write_text(json.dumps(res, indent=2))

    @app.command()
    def demo(
        out: Annotated[Path, typer.Option("-o", "--out", help="output folder")] = Path("out/demo"),
        preset: Annotated[str, typer.Option(help="fast, balanced, quality")] = "balanced",
        method: Annotated[str, typer.Option(help="pbrsr, direct or bicubic")] = "pbrsr",
        size: Annotated[int, typer.Option(help="LR texture size of the demo asset")] = 128,
    ) -> None:
        """Make the built-in procedural demo asset and upscale it x4 in-process."""
        from ..asset import make_demo_asset
        from ..pipeline import upscale_asset

        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        src = make_demo_asset(out / "input" / "demo.glb", size=size)
        console.print(
            f"demo asset: {src} ({size}x{size} textures), method {method}, preset {preset}"
        )
        options = UpscaleOptions(method=method, preset=preset)
        with progress_bar() as cb:
            report = upscale_asset(src, out / "result", options, progress=cb)
        _print_report(report, out / "result")
