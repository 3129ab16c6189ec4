"""``pbrsr render IN -o SHEET.png``: a contact sheet of a few views of an asset."""

from __future__ import annotations

from pathlib import Path

import typer


def contact_sheet(
    input: Path,
    output: Path,
    *,
    views: int = 8,
    size: int = 384,
    envmap: Path | None = None,
    device: str = "auto",
    background: float = 0.25,
) -> Path:
    """Render ``views`` orbit views (two rows: elevation 25 and -10 degrees) of the asset,
    normalised to unit size, under ``envmap`` (or the built-in environment), and write them
    side by side as an sRGB PNG. Returns the path written."""
    import numpy as np
    import torch

    from ..asset import load_asset
    from ..asset.images import write_image
    from ..device import resolve_device
    from ..errors import InvalidOptions
    from ..render import camera as cam
    from ..render.light import EnvLight
    from ..scene import asset_textures, make_scene, procedural_light, render_views

    if views < 1 or views > 64:
        raise InvalidOptions("--views must be between 1 and 64")
    if size < 16 or size > 4096:
        raise InvalidOptions("--size must be between 16 and 4096")
    dev = resolve_device(device)
    asset = load_asset(input)
    scene = make_scene(asset, dev)
    textures = asset_textures(asset, dev)
    env = EnvLight.from_file(envmap) if envmap else procedural_light()
    rows = 2 if views >= 4 else 1
    per_row = -(-views // rows)
    cams = []
    for r, elev in enumerate((25.0, -10.0)[:rows]):
        n = min(per_row, views - r * per_row)
        cams += cam.orbit_cameras(1, n, 2.2, 30.0, size, (elev, elev), 30.0 * r)
    images, _ = render_views(scene, textures, cams, env.to(dev), background=background)
    sheet = torch.full((rows * size, per_row * size, 3), background)  # sRGB, as the views
    for k, img in enumerate(images):
        r, c = divmod(k, per_row)
        sheet[r * size : (r + 1) * size, c * size : (c + 1) * size] = img.cpu()
    return write_image(output, np.ascontiguousarray(sheet.numpy(), dtype=np.float32), 8, "png")


def register(app: typer.Typer) -> None:
    @app.command("render")
    def render_cmd(
        input: Path = typer.Argument(..., help="A .glb or .gltf asset."),
        output: Path = typer.Option(..., "-o", "--output", help="The PNG contact sheet."),
        views: int = typer.Option(8, help="Number of views (two rows when 4 or more)."),
        size: int = typer.Option(384, help="Pixels per view (square)."),
        envmap: Path = typer.Option(
            None, help="Equirectangular .hdr/.exr lighting (default: built-in environment)."
        ),
        device: str = typer.Option("auto", help="auto, cpu, cuda or cuda:N."),
    ) -> None:
        """Render a contact sheet of orbit views of an asset (PBR, split-sum lighting)."""
        written = contact_sheet(input, output, views=views, size=size, envmap=envmap, device=device)
        typer.echo(f"wrote {written}")
