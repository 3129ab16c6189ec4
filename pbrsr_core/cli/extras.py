"""For commands that other packages add (``pbrsr serve``, ``pbrsr worker``, ``pbrsr bench``):
their packages come with ``pip install pbrsr``, their dependencies with an extra
(``pbrsr[service]``, ``pbrsr[bench]``), so a command is listed everywhere and says what to
install where its dependencies are missing."""

from __future__ import annotations

import importlib.util
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

import typer


def _missing(command: str, extra: str, module: str) -> NoReturn:
    typer.secho(
        f"error: `pbrsr {command}` needs pbrsr's {extra} dependencies (missing module "
        f"{module!r}): pip install 'pbrsr[{extra}]'",
        fg="red",
        err=True,
    )
    raise typer.Exit(2)


@contextmanager
def needs_extra(command: str, extra: str) -> Iterator[None]:
    """Around a command's imports: a missing module exits 2 with the ``pip install`` line
    (``pbrsr[extra]``) instead of a traceback."""
    try:
        yield
    except ModuleNotFoundError as exc:
        _missing(command, extra, (exc.name or "?").split(".")[0])


def require_extra(command: str, extra: str, modules: tuple[str, ...]) -> None:
    """The same for a command whose code imports ``modules`` later, inside its functions:
    checked before it starts."""
    for module in modules:
        if importlib.util.find_spec(module) is None:
            _missing(command, extra, module)
