"""For commands that other packages add (``pbrsr serve``, ``pbrsr worker``): their packages
come with ``pip install pbrsr``, their dependencies with an extra (``pbrsr[service]``), so a
command is listed everywhere and says what to install where its dependencies are missing."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import typer


@contextmanager
def needs_extra(command: str, extra: str) -> Iterator[None]:
    """Around a command's imports: a missing module exits 2 with the ``pip install`` line
    (``pbrsr[extra]``) instead of a traceback."""
    try:
        yield
    except ModuleNotFoundError as exc:
        typer.secho(
            f"error: `pbrsr {command}` needs pbrsr's {extra} dependencies (missing module "
            f"{(exc.name or '?').split('.')[0]!r}): pip install 'pbrsr[{extra}]'",
            fg="red",
            err=True,
        )
        raise typer.Exit(2) from None
