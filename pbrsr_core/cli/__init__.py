"""The ``pbrsr`` command line (typer). One module per command group; each has
``register(app)``. ``service`` and ``worker`` add ``serve`` and ``worker`` through the
``pbrsr.commands`` entry point group, so this package never imports them."""

from __future__ import annotations

import importlib
import sys
from importlib.metadata import entry_points

import typer

from ..errors import PbrsrError
from .environment import configure_from_env

app = typer.Typer(
    name="pbrsr",
    help="PBR texture super-resolution for glTF/GLB assets (PBR-SR).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_COMMAND_MODULES: list[str] = ["upscale", "priors", "degrade", "kernel", "render"]


def _register_all() -> None:
    for name in _COMMAND_MODULES:
        importlib.import_module(f"{__name__}.{name}").register(app)
    for ep in entry_points(group="pbrsr.commands"):
        try:
            register = ep.load()
        except ImportError:  # service/worker not installed in this environment
            continue
        register(app)


def main() -> None:
    _register_all()
    try:
        configure_from_env()
        app()
    except PbrsrError as exc:
        typer.secho(f"error: {exc.message}", fg="red", err=True)
        sys.exit(exc.exit_code)
