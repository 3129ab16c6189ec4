"""``pbrsr degrade IN -o OUT --scale 4``: the paper's LR protocol applied to an asset."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("degrade")
    def degrade_cmd(
        input: Path = typer.Argument(..., help="A .glb or .gltf asset (the HR ground truth)."),
        output: Path = typer.Option(..., "-o", "--output", help="The LR .glb/.gltf to write."),
        scale: int = typer.Option(4, "--scale", "-s", help="Downsampling factor (2, 4, 8)."),
        image_format: str = typer.Option(
            "same",
            "--format",
            help="LR image format: same (JPEG stays JPEG, compressed again; KTX2, WebP, AVIF "
            "keep their encodings), png, png16, exr, jpeg (quality 95, 4:4:4), jpeg:Q (quality "
            "Q), jpeg:Q:420 (quality Q, chroma at half resolution), ktx2, webp, avif.",
        ),
        kernel: str = typer.Option(
            "gaussian",
            "--kernel",
            help="gaussian: the evaluation protocol; area: the mean of each LR texel's HR "
            "texels (mipmaps); bicubic, lanczos: antialiased resizing (image editors).",
        ),
    ) -> None:
        """Make the LR input of the evaluation protocol: Gaussian blur (sigma = 0.375 x
        scale) then bicubic downsampling of every texture, or another downsampling filter
        (--kernel); everything else unchanged."""
        from ..degrade import degrade_asset

        written = degrade_asset(input, output, scale, image_format=image_format, kernel=kernel)
        typer.echo(f"wrote {written[0]} ({len(written) - 1} extra files)")
