"""``pbrsr bench <name>``: benchmarks (implemented in ``pbrsr_bench/<name>.py``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

import typer

from pbrsr_core.cli.extras import require_extra
from pbrsr_core.errors import InvalidOptions
from pbrsr_core.options import DEFAULT_PRIOR

bench_app = typer.Typer(help="Benchmarks: print a table, write JSON and plots to bench-out/.")


def _bad_input(exc: Exception) -> NoReturn:
    """A benchmark refused its input (an unknown asset, an impossible size): say why, exit 2."""
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(2) from None


def _log(message: str) -> None:
    typer.echo(message, err=True)


def _report(
    run: Callable[..., Any],
    show: Callable[[Any], None],
    written: list[Path],
    failed: Callable[[Any], bool] | None = None,
    **options: Any,
) -> None:
    """Every bench command: run with ``options`` and progress on stderr (a refused input exits
    2), print the table with ``show``, name the files written, exit 1 when ``failed``."""
    try:
        result = run(log=_log, **options)
    except (ValueError, InvalidOptions) as exc:
        _bad_input(exc)
    show(result)
    typer.echo("wrote " + ", ".join(str(p) for p in written))
    if failed is not None and failed(result):
        raise typer.Exit(1)


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(v) for v in text.split(",") if v.strip())


@bench_app.command("prior")
def prior_cmd(
    out: Path = typer.Option(Path("bench-out/prior"), "--out", "-o", help="Output directory."),
    prior: list[str] = typer.Option(  # noqa: B006
        [], "--prior", "-p", help="Prior to include (repeatable); default: every installed one."
    ),
    scales: str = typer.Option("2,4,8", help="Scales, comma-separated."),
    large_scales: str = typer.Option(
        None, help="Scales timed on a 1024x1024 input (default: all; '' for none)."
    ),
    device: str = typer.Option("auto", help="auto, cpu, cuda or cuda:N."),
    crop: int = typer.Option(256, help="HR crop side for the PSNR images."),
    threads: int = typer.Option(0, help="torch intra-op threads (0: torch's default)."),
    precision: list[str] = typer.Option(  # noqa: B006
        ["auto"],
        help="Prior precision (repeatable): auto, fp32, bf16, int8; each prior runs once per "
        "precision it actually takes.",
    ),
) -> None:
    """Prior speed (256² and tiled 1024² inputs), peak memory and PSNR gain over bicubic on
    skimage photos and on albedo crops of the shared assets (when present)."""
    require_extra("bench prior", "bench", ("skimage",))
    from pbrsr_bench.prior import print_table, run

    _report(
        run,
        print_table,
        [out / "prior.json", out / "prior.png"],
        out_dir=out,
        priors=prior or None,
        scales=_ints(scales),
        large_scales=None if large_scales is None else _ints(large_scales),
        device=device,
        crop=crop,
        threads=threads or None,
        precisions=tuple(precision),
    )


@bench_app.command("check")
def check_cmd(
    out: Path = typer.Option(Path("bench-out/check"), "--out", "-o", help="Output directory."),
    textures: Path | None = typer.Option(
        None, help="Texture folder with manifest.json ($PBRSR_TEXTURES)."
    ),
    prior: str = typer.Option(DEFAULT_PRIOR, help="Prior whose self-check is scored."),
    scale: int = typer.Option(4, help="Upscaling factor: 2, 4 or 8."),
    sizes: str = typer.Option("1024,512", help="HR crop sides, comma-separated."),
    jpeg: int | None = typer.Option(
        None,
        min=1,
        max=100,
        help="Store the LR crops as JPEG at this quality (4:4:4, as pbrsr degrade writes JPEG).",
    ),
    deblock: bool = typer.Option(
        True, help="Deblock the JPEG crops with their tables before the check, as the presets do."
    ),
    chroma: str = typer.Option(
        "4:4:4", help="With --jpeg: the crops' chroma at full (4:4:4) or half resolution (4:2:0)."
    ),
    storage: bool = typer.Option(
        False,
        help="With --jpeg: the self-check models that storage one scale down (check_storage).",
    ),
) -> None:
    """The prior's self-check against the real scale on held-out texture materials: the gain
    over bicubic of the check's choices, of each candidate alone and of the oracle, and the
    choices that fall below bicubic."""
    from pbrsr_bench.check import markdown_table, run

    _report(
        run,
        lambda result: typer.echo(markdown_table(result)),
        [out / "check.json", out / "check.png"],
        out_dir=out,
        textures=textures,
        prior=prior,
        scale=scale,
        sizes=_ints(sizes),
        jpeg=jpeg,
        deblock_jpeg=deblock,
        subsampled=_subsampled(chroma, jpeg, storage),
        storage=storage,
    )


def _subsampled(chroma: str, jpeg: int | None, storage: bool = False) -> bool:
    """--chroma: 4:2:0 (True) or 4:4:4 (False), of the --jpeg files; anything else, or 4:2:0
    or --storage without --jpeg, is refused."""
    if storage and jpeg is None:
        _bad_input(ValueError("--storage models the --jpeg files in the check: give --jpeg Q"))
    if chroma not in ("4:4:4", "4:2:0"):
        _bad_input(ValueError(f"--chroma takes 4:4:4 or 4:2:0, not {chroma!r}"))
    if chroma == "4:2:0" and jpeg is None:
        _bad_input(ValueError("--chroma 4:2:0 is the chroma of the --jpeg files: give --jpeg Q"))
    return chroma == "4:2:0"


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(",") if v.strip())


@bench_app.command("blend")
def blend_cmd(
    out: Path = typer.Option(Path("bench-out/blend"), "--out", "-o", help="Output directory."),
    textures: Path | None = typer.Option(
        None, help="Texture folder with manifest.json ($PBRSR_TEXTURES)."
    ),
    prior: str = typer.Option(DEFAULT_PRIOR, help="Prior whose data upscales are blended."),
    scale: int = typer.Option(4, help="Upscaling factor: 2, 4 or 8."),
    size: int = typer.Option(512, help="HR crop side (crops on a grid over each material)."),
    margins: str = typer.Option(
        "0,0.1", help="dB a channel's blend must beat bicubic by one scale down, comma-separated."
    ),
    network_db: str = typer.Option(
        "0,0.1", help="dB a network must add to a map's blends to run, comma-separated."
    ),
    pick_db: str = typer.Option(
        "off",
        help="dB a channel's blend must beat the check's pick by one scale down to replace "
        "it (off: weighed against bicubic only, as the presets), comma-separated.",
    ),
    pick_floor: str = typer.Option(
        "off",
        help="off, on or off,on: keep a network wherever leaving it out would put a "
        "channel's blend below the check's pick one scale down (blend_pick_floor).",
    ),
    channel_db: str = typer.Option(
        "off",
        help="dB a network must add to a channel's blend to run on that channel "
        "(blend_channel_db; off: on every channel its fit weighs; the presets take 0.1), "
        "comma-separated.",
    ),
    max_prior_scale: int | None = typer.Option(
        None, help="Largest factor the prior runs at (fast: 2; default: the prior's own)."
    ),
    jpeg: int | None = typer.Option(
        None,
        min=1,
        max=100,
        help="Store the LR crops as JPEG at this quality and deblock them, as the presets do.",
    ),
    chroma: str = typer.Option(
        "4:4:4", help="With --jpeg: the crops' chroma at full (4:4:4) or half resolution (4:2:0)."
    ),
    storage: bool = typer.Option(
        False,
        help="With --jpeg: the self-check models that storage one scale down (check_storage).",
    ),
) -> None:
    """The presets' blend of data channels on held-out texture materials, rule by rule: the
    gain over bicubic per channel and the networks run per map (and their runs, one per
    network and channel), with direct's choice."""
    from pbrsr_bench.blend import markdown_table, run

    try:
        margin_values, network_values = _floats(margins), _floats(network_db)
        pick_values, channel_values = (
            tuple(None if v.strip() == "off" else float(v) for v in text.split(",") if v.strip())
            for text in (pick_db, channel_db)
        )
        floors = tuple({"off": False, "on": True}[v.strip()] for v in pick_floor.split(","))
    except (ValueError, KeyError):
        _bad_input(
            ValueError(
                "--margins, --network-db, --pick-db and --channel-db take comma-separated "
                "numbers, --pick-floor off, on or both"
            )
        )
    _report(
        run,
        lambda result: typer.echo(markdown_table(result)),
        [out / "blend.json", out / "blend.png"],
        out_dir=out,
        textures=textures,
        prior=prior,
        scale=scale,
        size=size,
        margins=margin_values,
        network_dbs=network_values,
        pick_dbs=pick_values,
        pick_floors=floors,
        max_prior_scale=max_prior_scale,
        jpeg=jpeg,
        channel_dbs=channel_values,
        subsampled=_subsampled(chroma, jpeg, storage),
        storage=storage,
    )


@bench_app.command("fuzz")
def fuzz_cmd(
    cases: int = typer.Option(3000, "--cases", "-n", help="Number of mutated assets."),
    seed: int = typer.Option(0, "--seed", "-s", help="Seed: case i of seed s is reproducible."),
    start: int = typer.Option(
        0, "--start", min=0, help="First case index (--start I --cases 1 replays case I)."
    ),
    out: Path = typer.Option(Path("bench-out/fuzz"), "--out", "-o", help="Output directory."),
    shared: bool = typer.Option(
        False, help="Also mutate the .glb files (< 2 MB) of the shared assets, if present."
    ),
    memory_cap: int | None = typer.Option(
        None, "--memory-cap", min=0, help="Address-space cap of the case process, MiB [2048]."
    ),
    case_timeout: float | None = typer.Option(
        None, "--case-timeout", min=1.0, help="Seconds one case may take [60]."
    ),
) -> None:
    """Fuzz the GLB/glTF reader, writer and zip extraction with mutated valid assets in a
    memory-capped child process; any exception that is not a pbrsr error, a crash, a hang or
    an allocation past the cap is an escape, saved under OUT/findings/."""
    from pbrsr_bench.fuzz import print_table, run

    limits = {"memory_cap_mib": memory_cap, "case_timeout_s": case_timeout}
    _report(
        run,
        print_table,
        [out / "fuzz.json", out / "fuzz.png"],
        lambda result: bool(result["escapes"]),
        cases=cases,
        seed=seed,
        start=start,
        out_dir=out,
        shared=shared,
        **{k: v for k, v in limits.items() if v is not None},
    )


@bench_app.command("render")
def render_cmd(
    out: Path = typer.Option(Path("bench-out/render"), "--out", "-o", help="Output directory."),
    resolutions: str = typer.Option("512,1024", help="Render resolutions, comma-separated."),
    views: int = typer.Option(3, help="Orbit views per case (medians are reported)."),
    shared: bool = typer.Option(True, help="Include the shared assets when present."),
    threads: int = typer.Option(0, help="torch intra-op threads (0: torch's default)."),
) -> None:
    """Renderer speed: G-buffer time per view (coverage + interpolation), shading forward +
    backward throughput (Mpixel/s) and peak memory, on a ~100k-triangle procedural mesh and
    the shared assets; plus a per-operator profile of shading."""
    from pbrsr_bench.render import print_table, run

    _report(
        run,
        print_table,
        [out / "render.json", out / "render.png"],
        out_dir=out,
        resolutions=_ints(resolutions),
        n_views=views,
        shared=shared,
        threads=threads or None,
    )


@bench_app.command("step")
def step_cmd(
    out: Path = typer.Option(Path("bench-out/step"), "--out", "-o", help="Output directory."),
    sizes: str = typer.Option("1024,2048,4096", help="HR map sides, comma-separated."),
    images: int = typer.Option(3, help="Optimised maps (images)."),
    channels: int = typer.Option(3, help="Channels per map."),
    steps: int = typer.Option(5, help="Timed steps per size (medians are reported)."),
    threads: int = typer.Option(0, help="torch intra-op threads (0: torch's default)."),
) -> None:
    """The optimiser step's whole-map part (consistency + TV gradient and masking, Adam,
    projection) against its memory-traffic floor, per map size."""
    from pbrsr_bench.step import print_table, run

    _report(
        run,
        print_table,
        [out / "step.json", out / "step.png"],
        out_dir=out,
        sizes=_ints(sizes),
        images=images,
        channels=channels,
        steps=steps,
        threads=threads or None,
    )


_SECTION = typer.Option(
    "upscale",
    help="The docs' section to write: between <!-- bench:SECTION --> and <!-- /bench:SECTION -->.",
)


@bench_app.command("upscale")
def upscale_cmd(
    out: Path = typer.Option(Path("bench-out/upscale"), "--out", "-o", help="Output directory."),
    asset: list[str] = typer.Option(  # noqa: B006
        [],
        "--asset",
        "-a",
        help="Shared asset folder name, or a variant made from one (WaterBottle-draco: its "
        "geometry Draco-compressed) (repeatable); default: all, variants too.",
    ),
    methods: str = typer.Option(
        "bicubic,direct,fast,balanced",
        help="bicubic, direct and preset names, comma-separated; each as NAME[@PRIOR]"
        "[+key=value...]: a preset's numbers, or max_size for any method (its maps scored "
        "as bicubic upscales to the ground truth's size). closest:A|B (after A and B): "
        "per map entry the one of their outputs closest to the ground truth, a bound on "
        "any check choosing among them.",
    ),
    scale: int = typer.Option(4, help="Upscaling factor (the LR input is degraded by it)."),
    prior: str = typer.Option(DEFAULT_PRIOR, help="Image prior for direct and PBR-SR."),
    eval_res: int = typer.Option(256, help="Render size of the evaluation views."),
    eval_views: int = typer.Option(240, help="Evaluation views (the paper's 240)."),
    procedural: bool = typer.Option(True, help="Include the procedural demo asset."),
    shared: bool = typer.Option(
        True, help="Include the shared assets (their HDRs light the evaluation either way)."
    ),
    procedural_size: int = typer.Option(512, help="HR texture size of the procedural asset."),
    assets_dir: Path | None = typer.Option(
        None,
        "--assets-dir",
        help="A folder laid out as the shared assets (a folder per asset, a .gltf or .glb in "
        "each) whose assets run instead of the shared ones; the shared HDRs light them.",
    ),
    lr_format: str = typer.Option(
        "same",
        help="LR image format (pbrsr degrade --format): same, png, png16, exr, jpeg, jpeg:Q, "
        "jpeg:Q:420 (JPEG of quality Q, chroma at half resolution).",
    ),
    kernel: str = typer.Option(
        "gaussian",
        help="How the LR input is made (pbrsr degrade --kernel): gaussian (the protocol), "
        "area, bicubic, lanczos.",
    ),
    store_like_gt: bool = typer.Option(
        False,
        "--store-like-gt",
        help="Score each map whose ground truth is a JPEG file as stored with that file's "
        "tables and chroma sampling (what the ground truth's files can hold).",
    ),
    docs: list[Path] = typer.Option(  # noqa: B006
        [], "--docs", help="Markdown file whose --section gets the summary (repeatable)."
    ),
    section: str = _SECTION,
) -> None:
    """Speed against error: bicubic, direct prior and each PBR-SR preset on degraded assets;
    wall time, peak memory, PSNR per map and render PSNR, with curves over iterations."""
    from pbrsr_bench.docs import markers, section_span
    from pbrsr_bench.upscale import results_text, run

    try:  # before hours of benchmark, not after
        markers(section)
        for path in docs:
            section_span(path, section)
    except (OSError, ValueError) as exc:
        _bad_input(ValueError(str(exc)))
    _report(
        run,
        lambda rows: typer.echo(results_text(rows, scale)),
        [out / "results.json", out / "results.md", out / "speed_vs_error.png"],
        out_dir=out,
        assets=asset or None,
        methods=tuple(m.strip() for m in methods.split(",") if m.strip()),
        scale=scale,
        prior=prior,
        eval_res=eval_res,
        eval_views=eval_views,
        include_procedural=procedural,
        include_shared=shared,
        procedural_size=procedural_size,
        lr_format=lr_format,
        kernel=kernel,
        assets_dir=assets_dir,
        store_like_gt=store_like_gt,
    )
    _publish(out, docs, section)


def _publish(out: Path, docs: list[Path], section: str) -> None:
    from pbrsr_bench.docs import write_section
    from pbrsr_bench.upscale import published_summary

    if not docs:
        return
    text = published_summary(out)
    for path in docs:
        try:
            write_section(path, section, text)
        except (OSError, ValueError) as exc:
            _bad_input(ValueError(str(exc)))
        typer.echo(f"wrote the summary into {path}, section {section}")


@bench_app.command("publish")
def publish_cmd(
    out: Path = typer.Argument(..., help="Output directory of a `pbrsr bench upscale` run."),
    docs: list[Path] = typer.Option(  # noqa: B006
        ..., "--docs", help="Markdown file with the --section's markers (repeatable)."
    ),
    section: str = _SECTION,
) -> None:
    """Write the summary of a finished `pbrsr bench upscale` run into documentation files,
    between their <!-- bench:SECTION --> and <!-- /bench:SECTION --> markers (a file may hold
    one section per run it quotes)."""
    if not (out / "results.json").is_file():
        _bad_input(ValueError(f"{out} holds no results.json of pbrsr bench upscale"))
    _publish(out, docs, section)


def _load_report(out: Path, **options: Any) -> None:
    require_extra("bench", "bench", ("httpx", "redis"))
    from pbrsr_bench.load import print_table, run

    written = [out / "load.json", out / "load.png"]
    _report(run, print_table, written, lambda result: not result["ok"], out_dir=out, **options)


@bench_app.command("load")
def load_cmd(
    duration: float = typer.Option(60.0, help="Seconds of the mixed polling + upload phase."),
    baseline: float = typer.Option(10.0, help="Seconds of polling alone first (0: skip)."),
    pollers: int = typer.Option(50, help="Concurrent clients polling job status and lists."),
    uploaders: int = typer.Option(10, help="Concurrent uploaders (mixed and big-upload phases)."),
    upload_mb: float = typer.Option(20.0, help="Size of each big upload (MB); a valid GLB."),
    big_uploads: int = typer.Option(None, help="Number of big uploads (default: --uploaders)."),
    jobs: int = typer.Option(100, help="Small bicubic jobs drained by the workers (0: skip)."),
    workers: int = typer.Option(2, help="Worker processes for the drain phase."),
    drain_timeout: float = typer.Option(900.0, help="Most seconds the drain may take."),
    redis_url: str = typer.Option(
        None, help="Redis to use (default: a private redis-server on a free loopback port)."
    ),
    out: Path = typer.Option(Path("bench-out/load"), "--out", "-o", help="Output directory."),
) -> None:
    """The job service under load, on loopback only: one API process, a private Redis and
    temporary storage; polling + uploads for --duration s, concurrent big uploads, then
    --jobs small jobs drained by --workers workers. Fails (exit 1) on any error or lost job."""
    _load_report(
        out,
        duration=duration,
        baseline=baseline,
        pollers=pollers,
        uploaders=uploaders,
        upload_mb=upload_mb,
        big_uploads=big_uploads,
        jobs=jobs,
        workers=workers,
        drain_timeout=drain_timeout,
        redis_url=redis_url,
    )


@bench_app.command("service")
def service_cmd(
    asset: str = typer.Option(
        "procedural", "--asset", "-a", help="procedural, or a shared asset folder name."
    ),
    preset: str = typer.Option("fast", help="fast, balanced, quality or paper."),
    method: str = typer.Option("pbrsr", help="pbrsr, direct or bicubic."),
    scale: int = typer.Option(4, help="Upscaling factor (the input is degraded by it first)."),
    workers: int = typer.Option(2, min=1, help="Workers of the parallel batch."),
    jobs: int = typer.Option(0, min=0, help="Jobs in each batch (0: as many as --workers)."),
    procedural_size: int = typer.Option(1536, help="HR texture size of the procedural asset."),
    duration: float = typer.Option(
        15.0, min=0.0, help="Seconds of polling alone, then with uploads (0: skip the API)."
    ),
    pollers: int = typer.Option(50, help="Concurrent clients polling job status and lists."),
    uploaders: int = typer.Option(10, help="Concurrent 20 MB uploads."),
    upload_mb: float = typer.Option(20.0, help="Size of each big upload (MB); a valid GLB."),
    out: Path = typer.Option(Path("bench-out/service"), "--out", "-o", help="Output directory."),
) -> None:
    """The job service on loopback with real workers: one job through the service (upload to
    succeeded) against `pbrsr upscale` on the same asset, options and threads; --jobs jobs on
    --workers workers against the same jobs on one; and, first, the API alone (the polling
    and upload phases of ``bench load``). Fails (exit 1) on any API error or failed job."""
    require_extra("bench", "bench", ("httpx", "redis"))
    from pbrsr_bench.service import print_table, run

    _report(
        run,
        print_table,
        [out / "service.json", out / "service.png"],
        lambda result: not result["ok"],
        out_dir=out,
        asset=asset,
        method=method,
        preset=preset,
        scale=scale,
        workers=workers,
        jobs=jobs,
        procedural_size=procedural_size,
        duration=duration,
        pollers=pollers,
        uploaders=uploaders,
        upload_mb=upload_mb,
    )


def register(app: typer.Typer) -> None:
    app.add_typer(bench_app, name="bench")


@bench_app.command("oracle")
def oracle_cmd(
    out: Path = typer.Option(Path("bench-out/oracle"), "--out", "-o", help="Output directory."),
    asset: list[str] = typer.Option(  # noqa: B006
        [], "--asset", "-a", help="Shared asset folder name (repeatable); default: all."
    ),
    scale: int = typer.Option(4, help="Upscaling factor (the LR input is degraded by it)."),
    eval_res: int = typer.Option(256, help="Render size of the evaluation views."),
    eval_views: int = typer.Option(240, help="Evaluation views (the paper's 240)."),
    procedural: bool = typer.Option(True, help="Include the procedural demo asset."),
) -> None:
    """Where the render error lives: render PSNR of bicubic maps, and with each map replaced
    by the ground truth's (the most an upscaler of that map alone can add)."""
    from pbrsr_bench.oracle import markdown_table, run

    _report(
        run,
        lambda rows: typer.echo(markdown_table(rows)),
        [out / "oracle.json", out / "oracle.png"],
        out_dir=out,
        assets=asset or None,
        scale=scale,
        eval_res=eval_res,
        eval_views=eval_views,
        include_procedural=procedural,
    )


@bench_app.command("paper")
def paper_cmd(
    out: Path = typer.Option(Path("bench-out/paper"), "--out", "-o", help="Output directory."),
    asset: str = typer.Option(
        "procedural", "--asset", "-a", help="procedural, or a shared asset folder name."
    ),
    elev: int = typer.Option(3, min=1, max=15, help="Elevations of the sampled view grid."),
    azim: int = typer.Option(10, min=1, max=50, help="Azimuths of the sampled view grid."),
    iterations: int = typer.Option(20, min=1, max=2000, help="Optimisation steps sampled."),
    scale: int = typer.Option(4, help="Upscaling factor (the LR input is degraded by it)."),
    prior: str = typer.Option(DEFAULT_PRIOR, help="Image prior."),
) -> None:
    """What the paper preset (750 views, 2000 steps) costs here: a sample of its views and
    steps run for real, each stage extrapolated by its unit of work."""
    from pbrsr_bench.paper import print_table, run

    _report(
        run,
        print_table,
        [out / "paper.json", out / "paper.png"],
        out_dir=out,
        asset=asset,
        elev=elev,
        azim=azim,
        iterations=iterations,
        scale=scale,
        prior=prior,
    )
