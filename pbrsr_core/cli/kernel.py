"""``pbrsr kernel estimate ASSET``: which kernel made an asset's LR maps (what
``--lr-kernel auto`` runs); ``pbrsr kernel fit``: fit that estimator on a CC0 texture set."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

import typer

kernel_app = typer.Typer(
    help="The LR kernel an asset's maps were made by: estimate it, fit the estimator.",
    no_args_is_help=True,
)


@kernel_app.command("estimate")
def estimate_cmd(
    input: Path = typer.Argument(..., help="A .glb or .gltf asset (its maps as they are)."),
    as_json: bool = typer.Option(False, "--json", help="Print the estimate as JSON."),
    classifier: Path | None = typer.Option(
        None,
        "--classifier",
        help="A classifier of `pbrsr kernel fit` (default: $PBRSR_KERNEL_CLASSIFIER, else the "
        "shipped one).",
    ),
) -> None:
    """Estimate the kernel (gaussian, area, bicubic, lanczos) that made the asset's maps from
    larger ones: each map's spectrum near its Nyquist frequency, pooled over the maps."""
    from ..asset import load_asset
    from ..kernel_estimate import estimate_kernel, load_classifier
    from ..maps import role_label, upscalable_images

    clf = load_classifier(classifier)
    images = upscalable_images(load_asset(input))
    est = estimate_kernel([im.pixels for im in images], clf)
    if as_json:
        typer.echo(json.dumps(est.to_json(), indent=2))
        return
    for im, probs in zip(images, est.per_map, strict=True):
        said = (
            ", ".join(f"{k} {p:.2f}" for k, p in probs.items())
            if probs is not None
            else "not used (flat, non-finite or under 64 texels)"
        )
        typer.echo(f"{role_label(im.roles)} {im.width}x{im.height}: {said}")
    post = ", ".join(f"{k} {p:.2f}" for k, p in est.posterior.items())
    typer.echo(f"estimate: {est.kernel} ({est.maps} maps; {post})")


@kernel_app.command("fit")
def fit_cmd(
    textures: Path | None = typer.Option(
        None, "--textures", help="CC0 texture folder (default: $PBRSR_TEXTURES, shared/textures)."
    ),
    output: Path = typer.Option(
        ...,
        "-o",
        "--output",
        help="Where to write the classifier (the shipped one is "
        "pbrsr_core/prior/weights/lr-kernel/classifier.json).",
    ),
) -> None:
    """Fit the kernel estimator on the texture set's training materials (every map made LR
    at x2 and x4 by each kernel, half JPEG-compressed) and score it on the held-out ones."""
    from ..prior.train.data import texture_folder
    from ..prior.train.kernel_fit import fit_kernel_classifier

    root = texture_folder(textures)
    command = "pbrsr kernel fit" + "".join(f" {shlex.quote(a)}" for a in sys.argv[3:])
    clf = fit_kernel_classifier(root, command)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(clf.to_json(), indent=1) + "\n", encoding="utf-8")
    held = clf.meta.get("held_out")
    if held:
        typer.echo(
            f"held out: {held['map_accuracy']:.1%} of {held['maps']} maps, "
            f"{held['group_accuracy']:.1%} of {held['groups']} material groups"
        )
    typer.echo(f"wrote {output} (runs use it with PBRSR_KERNEL_CLASSIFIER={output})")


def register(app: typer.Typer) -> None:
    app.add_typer(kernel_app, name="kernel")
